"""Float32 and bfloat16 against float64 at the extremes: values and gradients of every shading
term, the shadows' visible shares, the light's parametrisation and a mesh's path to the renderer.

Every term runs on the same inputs three times: in float64 (the reference), in float32, and in
bfloat16 (inputs rounded to bfloat16 and the term run on bfloat16 tensors inside a bfloat16
autocast: every product that autocast lowers is lowered, and a term that works in float32 inside,
as the fitted lobe and the shares do, does so). The grid: light lobes of sharpness 1e-4 to 1e5
whose axes lie at n . l from -1 (below the horizon) through 0 (on it) to 1, views at n . v from
1e-4 (grazing) to 1, roughness 0.02 to 1, each configuration turned by its own random rotation;
the mesh rows take a sphere at scales 1e-4 to 1e4, centred and off its origin by 1,000 radii,
with its positions stored in float32 (as glTF stores them) and normalised by the pipeline; the
last rows sum the light's gradient over 100,000 points (10,000 on the quick grid) whose normals
cover the sphere, where its terms cancel (:func:`many_point_cases`).

For each term and precision the table gives the worst, over its inputs, of

* ``value``: ``|out - out64| / |out64|`` per point (the point's colour);
* ``point grad``: ``|g - g64| / |g64|`` with ``g`` the gradient of a fixed weighting of the
  outputs to the point's own inputs (normal, view, material, direction), per point;
* ``light grad``: the same for the gradient to the light's axes, sharpnesses and amplitudes (or
  the raw parameters, for the light's own row), per light;

and where it occurs. Inputs whose float64 norm is below 1e-6 of the term's median norm (a lobe's
value 1e5 radians of sharpness away from its axis, a point lit only below its horizon) are not
in the worst; they are counted in the last columns with their worst ``|g - g64|`` over the median,
so that nothing is skipped silently. Beside each term's worst float32 gradient: how far float64's
own gradient moves at that input when the unit vectors among the inputs turn by float32's
roundoff (:func:`conditioning`), the floor of any float32 arithmetic there. The last line:
``worst_grad_rel_f32=... worst_grad_rel_bf16=...`` over every term and both gradient kinds.

:func:`summary_lines` is everything the benchmark prints (``python -m benchmarks.render.precision``:
the full grid, about 90 s on 2 cores; ``--quick``: the coarser grid the tests use,
``tests/render/test_precision.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from ..geometry.normalization import normalization_transform
from ..geometry.normals import unit_face_normals
from ..model.lights.sg import SGLightModule, fibonacci_sphere
from ..model.networks import Material
from ..render import shading as sh
from ..render.brdf import GLTF, TANGO, Brdf
from ..render.brdf.gltf import diffuse_radiance_gltf
from ..render.fitted_lobe import specular_radiance_fitted
from ..render.isotropic_lobe import specular_radiance
from ..render.light.bounce import BounceLight, indirect_irradiance
from ..render.light.sun import SunLight
from ..render.sg import sg_hemisphere_integral
from ..render.split_sum import specular_radiance_split_sum
from ..render.visibility import lobe_visibility_bits

F64 = torch.float64
#: an input's float64 norm below this fraction of its term's median is reported apart
TINY_SHARE = 1e-6
#: the light lobes of one configuration (equally spaced in azimuth about the normal)
LOBES = 4
#: stored directions of the shares' quadrature (the ray cache's default)
DIRECTIONS = 512
#: the grid's most grazing view: a bfloat16-rounded normal is bent back to it (``face_viewer``)
MIN_COS_NV = 1e-4


@dataclass(frozen=True)
class Grid:
    sharpness: tuple[float, ...]
    cos_nl: tuple[float, ...]
    cos_nv: tuple[float, ...]
    roughness: tuple[float, ...]
    azimuths: int


FULL = Grid(
    sharpness=(1e-4, 1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0, 1e3, 1e4, 1e5),
    cos_nl=(-1.0, -0.5, -1e-4, 0.0, 1e-4, 1e-2, 0.5, 1.0),
    cos_nv=(MIN_COS_NV, 1e-3, 1e-2, 0.1, 0.5, 1.0),
    roughness=(0.02, 0.05, 0.1, 0.3, 0.6, 1.0),
    azimuths=2,
)
QUICK = Grid(
    sharpness=(1e-4, 1.0, 100.0, 1e5),
    cos_nl=(-0.5, 0.0, 1e-4, 1.0),
    cos_nv=(MIN_COS_NV, 0.1, 1.0),
    roughness=(0.02, 0.3, 1.0),
    azimuths=1,
)


@dataclass
class Case:
    """One light (``light``: leaves ``axis (K, 3)``, ``sharpness (K, 1)``, ``amplitude (K, 3)``)
    and its points (``points``: ``(N, ...)`` float64 tensors), with a label per point."""

    name: str
    points: dict[str, Tensor]
    light: dict[str, Tensor]
    labels: list[str]
    fixed: dict[str, Tensor] = field(default_factory=dict)
    #: the points' inputs in a precision, where they are not the float64 ones rounded (the mesh's)
    points_in: Callable[[torch.dtype], dict[str, Tensor]] | None = None


def rotation(g: torch.Generator) -> Tensor:
    """A random rotation (QR of a Gaussian matrix, sign-fixed), float64 ``(3, 3)``."""
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def direction(cos: float, azimuth: float) -> Tensor:
    """The unit vector at polar cosine ``cos`` from +z and ``azimuth``, float64 ``(3,)``."""
    sin = math.sqrt(max(0.0, 1.0 - cos * cos))
    return torch.tensor([sin * math.cos(azimuth), sin * math.sin(azimuth), cos], dtype=F64)


def shading_cases(grid: Grid, seed: int = 0) -> list[Case]:
    """A light of :data:`LOBES` lobes of one sharpness at one ``n . l`` per case; points at every
    roughness, ``n . v`` and view azimuth; materials random; the whole turned at random."""
    g = torch.Generator().manual_seed(seed)
    cases = []
    for lam in grid.sharpness:
        for cos_nl in grid.cos_nl:
            rot = rotation(g)
            offset = float(torch.rand(1, generator=g)) * 2 * math.pi
            axes = torch.stack([direction(cos_nl, offset + 2 * math.pi * k / LOBES) for k in range(LOBES)])
            views, rough, labels = [], [], []
            for r in grid.roughness:
                for cos_nv in grid.cos_nv:
                    for a in range(grid.azimuths):
                        phi = float(torch.rand(1, generator=g)) * 2 * math.pi if a else offset + 0.3
                        views.append(direction(cos_nv, phi))
                        rough.append(r)
                        labels.append(f"lam {lam:g}, n.l {cos_nl:g}, n.v {cos_nv:g}, roughness {r:g}")
            n = len(views)
            # directions at 0 to 3 lobe widths from the first lobe's axis, for the light's own values
            near = [
                torch.nn.functional.normalize(
                    axes[0] + 3.0 * i / max(n - 1, 1) / math.sqrt(lam) * direction(0.0, offset + 1.7), dim=0
                )
                for i in range(n)
            ]
            points = {
                "normal": torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(n, 3) @ rot.T,
                "view": torch.stack(views) @ rot.T,
                "direction": torch.stack(near) @ rot.T,
                "albedo": torch.rand(n, 3, generator=g, dtype=F64),
                "specular": torch.rand(n, 3, generator=g, dtype=F64),
                "metallic": torch.rand(n, 1, generator=g, dtype=F64),
                "roughness": torch.tensor(rough, dtype=F64)[:, None],
            }
            light = {
                "axis": axes @ rot.T,
                "sharpness": torch.full((LOBES, 1), lam, dtype=F64),
                "amplitude": torch.rand(LOBES, 3, generator=g, dtype=F64) + 0.1,
            }
            fixed = {
                "bits": torch.randint(0, 256, (n, DIRECTIONS // 8), generator=g, dtype=torch.uint8),
                "normal": points["normal"].clone(),  # the ray cache's stored normal, for the shares
            }
            cases.append(Case(f"lam {lam:g}, n.l {cos_nl:g}", points, light, labels, fixed))
    return cases


def _light(light: dict[str, Tensor]) -> sh.SGLight:
    return sh.SGLight(light["axis"], light["sharpness"], light["amplitude"])


def _directions(count: int, dtype: torch.dtype) -> Tensor:
    return fibonacci_sphere(count).to(dtype)


def _shares(lt: dict[str, Tensor], f: dict) -> Tensor:
    """The shadows' shares as training computes them: the quadrature's products in bfloat16 under
    the bfloat16 column's autocast (``f["bf16_products"]``), the rest of the renderer outside it."""
    normal = f["normal"]
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=f["bf16_products"]):
        return lobe_visibility_bits(normal, f["bits"], _directions(DIRECTIONS, normal.dtype), lt["axis"], lt["sharpness"])


def _specular(model: Callable, *brdf: Brdf) -> tuple[tuple[str, ...], Callable]:
    reads = ("normal", "view", "specular", "roughness")
    return reads, lambda p, lt, f: model(*(p[k] for k in reads), _light(lt), *brdf)


def _sun(lt: dict[str, Tensor]) -> SunLight:
    """The case's lobes as suns: each axis a sun's direction, its amplitude the irradiance, its
    width ``1 / sqrt(lam)`` the disc's radius (at most 0.35 radians): a sharpness of 1e4 is a
    0.6-degree sun."""
    radius = torch.clamp(torch.rsqrt(lt["sharpness"]), max=0.35)
    return SunLight(lt["axis"], lt["amplitude"], radius, 8)


def _sun_shading(brdf: Brdf) -> tuple[tuple[str, ...], Callable]:
    """A BRDF's shading under the case's suns (:func:`_sun`), unshadowed: TANGO's from the
    points' albedo, specular colour and roughness, glTF's with ``albedo`` its base colour."""
    if brdf is TANGO:
        reads = ("normal", "view", "albedo", "specular", "roughness")
        return (
            reads,
            lambda p, lt, f: (
                _sun(lt)
                .shade(TANGO, p["normal"], p["view"], Material.of(TANGO, p["albedo"], p["specular"], p["roughness"]), None, None)
                .rgb
            ),
        )
    reads = ("normal", "view", "albedo", "metallic", "roughness")
    return (
        reads,
        lambda p, lt, f: (
            _sun(lt)
            .shade(GLTF, p["normal"], p["view"], Material.gltf(p["albedo"], p["metallic"], p["roughness"]), None, None)
            .rgb
        ),
    )


def _bounce_shading(p: dict[str, Tensor], lt: dict[str, Tensor]) -> Tensor:
    """glTF's diffuse term under one bounce: the case's lobe amplitudes as the table of the face
    sides sent from, each point meeting 16 of them (or missing, -1) drawn from a seed of its own
    (the cases' draws untouched), through :func:`~stages.render.light.bounce.indirect_irradiance`."""
    table = lt["amplitude"]
    sides = torch.randint(-1, table.shape[0], (p["normal"].shape[0], 16), generator=torch.Generator().manual_seed(7))
    material = Material.gltf(p["albedo"], p["metallic"], torch.full_like(p["metallic"], 0.5))
    return BounceLight(table).shade(GLTF, p["normal"], p["view"], material, None, indirect_irradiance(table, sides)).rgb


#: term -> (the point inputs it reads, its function of (points, light, fixed) -> (N, C))
TERMS: dict[str, tuple[tuple[str, ...], Callable]] = {
    "light radiance L(d)": (("direction",), lambda p, lt, f: _light(lt).radiance(p["direction"])),
    "diffuse (TANGO)": (("normal", "albedo"), lambda p, lt, f: sh.diffuse_radiance(p["normal"], p["albedo"], _light(lt))),
    "diffuse (glTF, Fresnel-weighted)": (
        ("normal", "view", "albedo", "metallic"),
        lambda p, lt, f: diffuse_radiance_gltf(p["normal"], p["view"], p["albedo"] * (1 - p["metallic"]), _light(lt)),
    ),
    "specular isotropic (TANGO)": _specular(specular_radiance),
    "specular split sum (TANGO)": _specular(specular_radiance_split_sum, TANGO),
    "specular split sum (glTF)": _specular(specular_radiance_split_sum, GLTF),
    "specular fitted (TANGO)": _specular(specular_radiance_fitted, TANGO),
    "specular fitted (glTF)": _specular(specular_radiance_fitted, GLTF),
    "visible shares (512 directions)": ((), lambda p, lt, f: _shares(lt, f)),
    "glTF shading with shares": (
        ("normal", "view", "albedo", "metallic", "roughness"),
        lambda p, lt, f: _gltf_shading(p, _light(lt), _shares(lt, f)),
    ),
    "sun (TANGO)": _sun_shading(TANGO),
    "sun (glTF)": _sun_shading(GLTF),
    "bounce (glTF)": (("normal", "view", "albedo", "metallic"), lambda p, lt, f: _bounce_shading(p, lt)),
}


@dataclass
class Run:
    """One term on one case in one precision: outputs and gradients, as float64."""

    value: Tensor  # (N, C)
    point_grad: Tensor | None  # (N, G)
    light_grad: Tensor | None  # (L,)


@dataclass(frozen=True)
class Precision:
    """How a column computes: every input first rounded to ``inputs``, the networks' outputs
    further to ``network``, the term run on ``compute`` tensors, and ``autocast``: the shares'
    products in bfloat16 (the autocast training opens around them alone). ``reference``: the
    float64 run it is compared with."""

    name: str
    inputs: torch.dtype
    network: torch.dtype
    compute: torch.dtype
    autocast: bool = False
    reference: Precision | None = None


REFERENCE = Precision("float64", F64, F64, F64)
#: float32 against float64 on the same (float32) inputs: the code's arithmetic alone (the
#: inputs' own rounding is the problem's conditioning, which no code removes)
FLOAT32 = Precision(
    "float32", torch.float32, torch.float32, torch.float32, reference=Precision("float64", torch.float32, torch.float32, F64)
)
#: bfloat16 as training uses it (``bf16_networks``): the networks' outputs carry bfloat16's
#: rounding (an upper bound: the normal network's output is a bounded tilt of a float32 normal),
#: the renderer computes in float32, the shares' products in bfloat16; against float64 on the
#: unrounded inputs, so that it shows what the lever costs
BFLOAT16 = Precision("bfloat16", torch.float32, torch.bfloat16, torch.float32, autocast=True, reference=REFERENCE)
PRECISIONS = (FLOAT32, BFLOAT16)
#: the point inputs that the networks produce (rounded to ``Precision.rounded``)
NETWORK_OUTPUTS = frozenset({"normal", "albedo", "specular", "metallic", "roughness"})
#: inputs that are unit vectors: only their gradients' components across the vector count (the
#: networks and the light normalise them, which projects the component along the vector out)
UNIT = frozenset({"normal", "view", "direction", "axis"})


def _tangential(grad: Tensor, unit: Tensor) -> Tensor:
    """``grad - (grad . u) u`` per row: the gradient on the unit sphere."""
    return grad - (grad * unit).sum(-1, keepdim=True) * unit


def _grads(leaves: dict[str, Tensor], keys, rows: int) -> list[Tensor]:
    """The leaves' gradients, float64, ``(rows, -1)`` each; a unit vector's on the sphere at the
    leaf's own (normalised) value."""
    out = []
    for k in keys:
        leaf = leaves[k].detach().to(F64)
        g = torch.zeros_like(leaf) if leaves[k].grad is None else leaves[k].grad.to(F64)
        if k in UNIT:
            g = _tangential(g, torch.nn.functional.normalize(leaf, dim=-1))
        out.append(g.reshape(rows, -1))
    return out


def run_term(fn: Callable, reads: tuple[str, ...], case: Case, precision: Precision) -> Run:
    """``fn`` on ``case`` in ``precision``, with the gradient of a fixed weighting of its outputs
    to the points' inputs and the light (on the sphere for unit vectors)."""
    source = case.points if case.points_in is None else case.points_in(precision.compute)

    def leaf(key: str, v: Tensor, grad: bool) -> Tensor:
        # copies: the float64 pass must not make the case's own tensors leaves with gradients
        rounded = v.detach().to(precision.inputs)
        rounded = rounded.to(precision.network) if key in NETWORK_OUTPUTS else rounded
        return rounded.to(precision.compute, copy=True).requires_grad_(grad)

    points = {k: leaf(k, v, k in reads) for k, v in source.items()}
    if precision.network == torch.bfloat16 and "normal" in points:
        # the field normalises its normal network's output and keeps it facing the viewer
        with torch.no_grad():
            unit = torch.nn.functional.normalize(points["normal"], dim=-1)
            points["normal"].copy_(sh.face_viewer(unit, points["view"], min_cos=MIN_COS_NV))
    light = {k: leaf(k, v, True) for k, v in case.light.items()}
    fixed = {k: v.to(precision.compute) if v.is_floating_point() else v for k, v in case.fixed.items()}
    out = fn(points, light, fixed | {"bf16_products": precision.autocast})
    weights = torch.linspace(0.5, 1.5, out.numel(), dtype=F64).view_as(out)
    (out.to(F64) * weights).sum().backward()
    n = out.shape[0]
    grads = _grads(points, reads, n)
    lgrads = [g.reshape(-1) for g in _grads(light, light, 1)]
    return Run(out.detach().to(F64), torch.cat(grads, dim=1) if grads else None, torch.cat(lgrads) if lgrads else None)


@dataclass
class Errors:
    """Reference norms, difference norms and labels of one quantity of one term, over inputs, with
    each input's place (its case's index and its row, or ``None`` for a whole case)."""

    ref: list[float] = field(default_factory=list)
    diff: list[float] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    places: list[tuple[int, int | None]] = field(default_factory=list)

    def add(self, ref: Tensor, out: Tensor, labels: list[str], case: int = 0, whole: bool = False) -> None:
        """Rows of ``ref``/``out (M, ...)`` as M inputs (non-finite outputs count as infinite error);
        ``whole``: one input, the whole case ``case``."""
        ref, out = ref.reshape(len(labels), -1), out.reshape(len(labels), -1)
        diff = (out - ref).norm(dim=1)
        diff = torch.where(torch.isfinite(out).all(dim=1), diff, torch.full_like(diff, math.inf))
        self.ref += ref.norm(dim=1).tolist()
        self.diff += diff.tolist()
        self.labels += labels
        self.places += [(case, None)] if whole else [(case, row) for row in range(len(labels))]

    def summary(self) -> Summary:
        ref, diff = np.asarray(self.ref), np.asarray(self.diff)
        if len(ref) == 0:
            return Summary(math.nan, "", 0, math.nan)
        median = float(np.median(ref))
        tiny = ref <= TINY_SHARE * median
        rel = np.where(tiny, -1.0, diff / np.where(tiny, 1.0, ref))
        worst = int(np.argmax(rel))
        apart = float(diff[tiny].max() / median) if tiny.any() and median > 0 else (math.inf if tiny.any() else 0.0)
        rel_worst = float(rel[worst]) if not tiny.all() else math.nan
        return Summary(rel_worst, self.labels[worst], int(tiny.sum()), apart, self.places[worst])


@dataclass(frozen=True)
class Summary:
    worst: float  # the largest relative error over inputs of normal norm
    where: str
    apart: int  # inputs whose reference norm is below TINY_SHARE of the median
    apart_worst: float  # their largest |difference| over the median norm
    place: tuple[int, int | None] = (0, None)  # the worst input's case and row
    floor: float = math.nan  # float64's own change there when the unit inputs turn by float32's rounding


#: float32's unit roundoff, 2^-24: a unit vector's components rounded to float32 turn it by about
#: this many radians
ROUNDOFF_F32 = 2.0**-24
#: random turns of the inputs per conditioning figure (the largest change counts)
TURNS = 8
EXACT = Precision("float64", F64, F64, F64)


def _turned(values: dict[str, Tensor], g: torch.Generator) -> dict[str, Tensor]:
    """``values`` with every unit vector turned by float32's roundoff in a random direction across it."""
    out = dict(values)
    for key in UNIT & values.keys():
        x = values[key].to(torch.float32).to(F64)
        across = torch.nn.functional.normalize(_tangential(torch.randn(x.shape, generator=g, dtype=F64), x), dim=-1)
        # its length kept (to u^2): a float32-rounded vector is unit only to u, and normalising it
        # would move a cosine by as much as the turn does
        out[key] = x + ROUNDOFF_F32 * torch.linalg.vector_norm(x, dim=-1, keepdim=True) * across
    return out


def conditioning(fn: Callable, reads: tuple[str, ...], case: Case, quantity: str, row: int | None, seed: int = 0) -> float:
    """The largest relative change, over :data:`TURNS` draws, of ``quantity`` of float64 at the
    input ``row`` of ``case`` (``None``: the whole case) when the unit vectors among the float32
    inputs turn by float32's roundoff: what storing directions in float32 alone makes uncertain,
    a floor for any float32 arithmetic (NaN where the case has no unit vector to turn or its
    points are not given in float64)."""
    if case.points_in is not None or not (UNIT & (case.points.keys() | case.light.keys())):
        return math.nan
    g = torch.Generator().manual_seed(seed)
    rounded = {k: v.to(torch.float32).to(F64) for k, v in case.points.items()}
    light = {k: v.to(torch.float32).to(F64) for k, v in case.light.items()}
    pick = {"value": lambda r: r.value, "point grad": lambda r: r.point_grad, "light grad": lambda r: r.light_grad[None]}
    pick = pick[quantity]
    base = pick(run_term(fn, reads, Case(case.name, rounded, light, case.labels, case.fixed), EXACT))
    base = base if row is None else base[row : row + 1]
    worst = 0.0
    for _ in range(TURNS):
        turned = Case(case.name, _turned(rounded, g), _turned(light, g), case.labels, case.fixed)
        moved = pick(run_term(fn, reads, turned, EXACT))
        moved = moved if row is None else moved[row : row + 1]
        worst = max(worst, float((moved - base).norm() / base.norm()))
    return worst


def measure(cases: list[Case], terms: dict[str, tuple[tuple[str, ...], Callable]]) -> dict[str, dict[str, dict[str, Summary]]]:
    """term -> precision -> quantity (value, point grad, light grad) -> :class:`Summary`."""
    out = {}
    for name, (reads, fn) in terms.items():
        errors = {p: {q: Errors() for q in ("value", "point grad", "light grad")} for p in ("float32", "bfloat16")}
        for index, case in enumerate(cases):
            for precision in PRECISIONS:
                prec = precision.name
                ref = run_term(fn, reads, case, precision.reference)
                got = run_term(fn, reads, case, precision)
                errors[prec]["value"].add(ref.value, got.value, case.labels, index)
                if ref.point_grad is not None:
                    errors[prec]["point grad"].add(ref.point_grad, got.point_grad, case.labels, index)
                if ref.light_grad is not None:
                    errors[prec]["light grad"].add(ref.light_grad[None], got.light_grad[None], [case.name], index, whole=True)
        out[name] = {p: {q: e.summary() for q, e in qs.items()} for p, qs in errors.items()}
        for q, s in out[name]["float32"].items():
            if not math.isnan(s.worst):
                out[name]["float32"][q] = replace(s, floor=conditioning(fn, reads, cases[s.place[0]], q, s.place[1]))
    return out


def hemisphere_cases(grid: Grid) -> list[Case]:
    """The hemisphere integral of one lobe at every sharpness (the light's, and the products'
    up to 10 times sharper) and every cosine of its axis with the pole."""
    lam = torch.tensor([*grid.sharpness, 10 * grid.sharpness[-1]], dtype=F64)
    cos = torch.tensor(sorted({*grid.cos_nl, *(-c for c in grid.cos_nl)}), dtype=F64)
    ll, cc = torch.meshgrid(lam, cos, indexing="ij")
    labels = [f"lam {a:g}, cos {b:g}" for a, b in zip(ll.reshape(-1).tolist(), cc.reshape(-1).tolist(), strict=True)]
    return [Case("hemisphere", {"lam": ll.reshape(-1, 1), "cos": cc.reshape(-1, 1)}, {}, labels)]


def light_cases(grid: Grid, seed: int = 1) -> list[Case]:
    """The light's parametrisation (:class:`~stages.model.lights.sg.SGLightModule`) at every
    sharpness: its raw axes, log-sharpnesses and log-energies as the leaves."""
    g = torch.Generator().manual_seed(seed)
    cases = []
    for lam in grid.sharpness:
        light = {
            "axis_raw": torch.randn(LOBES, 3, generator=g, dtype=F64),
            "log_sharpness": torch.full((LOBES, 1), math.log(lam), dtype=F64),
            "log_energy": torch.randn(LOBES, 3, generator=g, dtype=F64),
        }
        cases.append(Case(f"lam {lam:g}", {}, light, [f"lam {lam:g}, lobe {k}" for k in range(LOBES)]))
    return cases


def _parametrised_light(params: dict[str, Tensor]) -> sh.SGLight:
    """The light of :class:`~stages.model.lights.sg.SGLightModule`'s raw parameters ``params``
    (``axis_raw``, ``log_sharpness``, ``log_energy``), in their dtype, differentiable in them."""
    module = SGLightModule(params["axis_raw"].shape[0]).to(params["axis_raw"].dtype)
    return torch.func.functional_call(module, dict(params), ())


def _light_module(p, lt, f) -> Tensor:
    light = _parametrised_light(lt)
    return torch.cat([light.axis, light.sharpness, light.amplitude], dim=1)


#: points of the many-point rows (the full grid's, the quick grid's): the light's gradient there is
#: one sum over all of them
MANY_POINTS = (100_000, 10_000)
#: the many-point rows' lights: the parametrisation's initial lobes (32, as the defaults)
MANY_POINT_LIGHTS = ("tango", "broad")


def many_point_cases(points: int, seed: int = 3) -> list[Case]:
    """``points`` points whose normals cover the sphere evenly (a Fibonacci sphere), each seen
    from a random direction on its side, random glTF materials, under the light's
    parametrisation (:class:`~stages.model.lights.sg.SGLightModule`: raw axes, log-sharpnesses and
    log-energies as the leaves) at TANGO's sharp initial lobes and at broad ones. A lobe's
    gradient is then one sum over all the points whose terms cancel: the parametrisation holds a
    lobe's energy, and over a whole sphere of normals its irradiance depends on neither its shape
    nor its direction. The benchmark's weighting of the colours is positive everywhere (a loss that
    brightens every point): rounding that leans one way in every term then adds up over the points
    while the terms themselves cancel. What a step's light gradient sums, over fewer points."""
    g = torch.Generator().manual_seed(seed)
    normal = fibonacci_sphere(points).to(F64)
    view = torch.nn.functional.normalize(normal + torch.randn(points, 3, generator=g, dtype=F64), dim=-1)
    view = torch.where((view * normal).sum(-1, keepdim=True) < 0.05, normal, view)
    materials = {
        "normal": normal,
        "view": view,
        "albedo": torch.rand(points, 3, generator=g, dtype=F64),
        "metallic": torch.rand(points, 1, generator=g, dtype=F64),
        "roughness": torch.rand(points, 1, generator=g, dtype=F64) * 0.9 + 0.1,
    }
    cases = []
    for init in MANY_POINT_LIGHTS:
        params = {k: v.detach().to(F64) for k, v in SGLightModule(32, init=init).named_parameters()}
        # one case per leaf, the others fixed: each leaf's gradient is its own input (as one vector
        # the energies' gradient, the largest, hid the sharpnesses')
        for leaf in params:
            label = f"{points:,} points, {init} lobes, {leaf}"
            fixed = {k: v for k, v in params.items() if k != leaf}
            cases.append(Case(label, materials, {leaf: params[leaf]}, [f"{label}, point {i}" for i in range(points)], fixed))
    return cases


def _gltf_shading(p: dict[str, Tensor], light: sh.SGLight, shares: Tensor | None = None) -> Tensor:
    """glTF's BRDF through the fitted lobe at the points ``p`` (``albedo`` its base colour)."""
    material = Material.gltf(p["albedo"], p["metallic"], p["roughness"])
    return GLTF.shade(p["normal"], p["view"], material, light, "fitted", shares).rgb


def _many_point_shading(p, lt, f) -> Tensor:
    light = _parametrised_light({k: v for k, v in (f | lt).items() if k in ("axis_raw", "log_sharpness", "log_energy")})
    return _gltf_shading(p, light)


#: the mesh rows: scales and offsets (in radii) of a sphere whose float32 positions the pipeline
#: normalises, and the camera's distance in normalised units
MESH_SCALES = (1e-4, 1.0, 1e4)
MESH_OFFSETS = (0.0, 1000.0)
CAMERA = 2.5


def _mesh_geometry(stored: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pipeline's path from stored positions: normalised (float64), faces' centroids and unit
    normals."""
    v = normalization_transform(stored, "+y").forward(stored)
    return v[faces].mean(axis=1), unit_face_normals(v, faces)


def _sphere(seed: int) -> tuple[np.ndarray, np.ndarray, torch.Generator]:
    import trimesh

    g = torch.Generator().manual_seed(seed)
    sphere = trimesh.creation.icosphere(3)
    return np.asarray(sphere.vertices) @ rotation(g).numpy().T, np.asarray(sphere.faces), g


def mesh_cases(seed: int = 2) -> list[Case]:
    """An icosphere (1,280 faces) turned at random, at each scale and offset, its positions stored
    in float32 (as glTF stores them) and normalised by the pipeline; every precision starts from
    those stored numbers, so the rows measure what scale and position cost the renderer after
    normalisation. Points are the faces' centroids seen by a camera at +z; light 8 lobes of
    sharpness 1 to 1,000."""
    base, faces, g = _sphere(seed)
    light = {
        "axis": torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=F64), dim=1),
        "sharpness": torch.logspace(0, 3, 8, dtype=F64)[:, None],
        "amplitude": torch.rand(8, 3, generator=g, dtype=F64) + 0.1,
    }
    cases = []
    for scale in MESH_SCALES:
        for offset in MESH_OFFSETS:
            stored = ((base + np.array([offset, -0.5 * offset, 0.25 * offset])) * scale).astype(np.float32)
            centre, normal = _mesh_geometry(stored, faces)
            view = CAMERA * np.array([0.0, 0.0, 1.0]) - centre
            view = view / np.linalg.norm(view, axis=1, keepdims=True)
            seen = (normal * view).sum(1) > 1e-3
            n = int(seen.sum())
            points = {
                "normal": torch.from_numpy(normal[seen]),
                "view": torch.from_numpy(view[seen]),
                "albedo": torch.rand(n, 3, generator=g, dtype=F64),
                "metallic": torch.rand(n, 1, generator=g, dtype=F64),
                "roughness": torch.rand(n, 1, generator=g, dtype=F64) * 0.98 + 0.02,
            }
            label = f"scale {scale:g}, offset {offset:g} radii"
            cases.append(Case(label, points, light, [f"{label}, face {i}" for i in range(n)]))
    return cases


def storage_angles(seed: int = 2) -> list[tuple[str, float]]:
    """The input's own precision, apart from the renderer's: per scale and offset, the largest angle
    (degrees) between the normals from the positions stored in float32 and from the same positions
    in float64 (what a file's float32 positions cost, which no computation after reading recovers)."""
    base, faces, _ = _sphere(seed)
    out = []
    for scale in MESH_SCALES:
        for offset in MESH_OFFSETS:
            exact = (base + np.array([offset, -0.5 * offset, 0.25 * offset])) * scale
            _, n64 = _mesh_geometry(exact, faces)
            _, n32 = _mesh_geometry(exact.astype(np.float32), faces)
            cos = np.clip((n64 * n32).sum(1), -1.0, 1.0)
            out.append((f"scale {scale:g}, offset {offset:g} radii", float(np.degrees(np.arccos(cos)).max())))
    return out


def _mesh_shading(p, lt, f) -> Tensor:
    return _gltf_shading(p, _light(lt))


def all_measurements(grid: Grid) -> dict[str, dict[str, dict[str, Summary]]]:
    results = measure(shading_cases(grid), TERMS)
    results |= measure(
        hemisphere_cases(grid),
        {"SG hemisphere integral": (("lam", "cos"), lambda p, lt, f: sg_hemisphere_integral(p["lam"], p["cos"]))},
    )
    results |= measure(light_cases(grid), {"light parametrisation": ((), _light_module)})
    results |= measure(
        mesh_cases(), {"mesh: glTF shading (fitted)": (("normal", "view", "albedo", "metallic", "roughness"), _mesh_shading)}
    )
    points = MANY_POINTS[grid is QUICK]
    many = {f"light over {points:,} points: glTF shading (fitted)": ((), _many_point_shading)}
    results |= measure(many_point_cases(points), many)
    return results


def fmt(x: float) -> str:
    return "-" if math.isnan(x) else f"{x:.1e}"


def worst_grad(results, precision: str) -> float:
    values = [s.worst for r in results.values() for q, s in r[precision].items() if q != "value" and not math.isnan(s.worst)]
    return max(values, default=math.nan)


def report(results) -> list[str]:
    lines = [
        "| term | value f32 | point grad f32 | light grad f32 | value bf16 | point grad bf16 | light grad bf16 |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, r in results.items():
        cells = [fmt(r[p][q].worst) for p in ("float32", "bfloat16") for q in ("value", "point grad", "light grad")]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Where float32's worst gradient is (the larger of the two kinds), and how far float64's own gradient",
        f"moves there when the unit vectors among the inputs turn by float32's roundoff ({ROUNDOFF_F32:.1e} rad):",
        "",
    ]
    for name, r in results.items():
        pick = max(
            (s for q, s in r["float32"].items() if q != "value" and not math.isnan(s.worst)), key=lambda s: s.worst, default=None
        )
        if pick is not None:
            floor = "" if math.isnan(pick.floor) else f" (float64 itself moves by {fmt(pick.floor)} there)"
            lines.append(f"- {name}: {fmt(pick.worst)} at {pick.where}{floor}")
    lines += [
        "",
        f"Inputs whose float64 norm is below {TINY_SHARE:g} of the term's median (not in the worst above):",
        "",
        "| term | quantity | inputs | f32 worst abs / median | bf16 worst abs / median |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    for name, r in results.items():
        for q, s in r["float32"].items():
            if s.apart:
                lines.append(f"| {name} | {q} | {s.apart} | {fmt(s.apart_worst)} | {fmt(r['bfloat16'][q].apart_worst)} |")
    return lines


def summary_lines(results) -> list[str]:
    """What the benchmark prints of ``results`` (:func:`all_measurements`): the tables of
    :func:`report`, the input's own float32 positions (:func:`storage_angles`) and the last line,
    ``worst_grad_rel_f32=... worst_grad_rel_bf16=...``."""
    lines = report(results)
    lines += ["", "The input's own float32 positions (not the renderer's precision): normals' largest angle to float64's"]
    lines += [f"- {label}: {degrees:.2e} degrees" for label, degrees in storage_angles()]
    lines.append(
        f"worst_grad_rel_f32={worst_grad(results, 'float32'):.3e} worst_grad_rel_bf16={worst_grad(results, 'bfloat16'):.3e}"
    )
    return lines
