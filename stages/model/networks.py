"""TANGO's learnable parts: positional encodings and the SVBRDF and normal MLPs (the light's
are its components' modules, :mod:`stages.model.lights`).

Constraints live in the parametrisation, so the renderer always receives valid inputs: albedo
and specular colour in [0, 1] (sigmoid), roughness in [min_roughness, 1], unit normals tilted by a
bounded offset, positive light sharpness and energy (their logarithms, so that they move by
factors). Parts a scene does not need
(the normal network, the specular/roughness heads) are not built at all when switched off, so
they cost nothing at run time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import torch
from torch import Tensor, nn

from ..render import brdf as brdfs
from ..render.brdf import Brdf
from ..render.products import Linear
from ..render.shading import tangent_frame


# ------------------------------------------------------------------------------------ encodings
class IdentityEncoding(nn.Module):
    """No positional encoding (the ablation): the input passes through."""

    def __init__(self, in_dim: int = 3) -> None:
        super().__init__()
        self.out_dim = in_dim

    def forward(self, x: Tensor) -> Tensor:
        return x


class FourierFeatures(nn.Module):
    """Gaussian random Fourier features (Tancik et al. 2020): ``[x, cos(2 pi B x), sin(2 pi B x)]``
    with ``B (count, in_dim)`` drawn once from N(0, sigma^2) by ``generator`` (a fixed buffer).
    ``x (N, in_dim)`` -> ``(N, in_dim + 2 count)``."""

    def __init__(self, count: int, sigma: float, in_dim: int = 3, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.register_buffer("B", torch.randn(count, in_dim, generator=generator) * sigma)
        self.out_dim = in_dim + 2 * count

    def forward(self, x: Tensor) -> Tensor:
        with torch.autocast(x.device.type, enabled=False):  # large phases: never in bfloat16
            proj = 2.0 * math.pi * x.float() @ self.B.T
        return torch.cat([x, torch.cos(proj), torch.sin(proj)], dim=-1)


class NerfEncoding(nn.Module):
    """NeRF's frequency encoding (Mildenhall et al. 2020): ``[x, sin(2^k pi x), cos(2^k pi x)]``
    for ``k = 0 .. frequencies - 1``. ``x (N, in_dim)`` -> ``(N, in_dim (1 + 2 frequencies))``."""

    def __init__(self, frequencies: int, in_dim: int = 3) -> None:
        super().__init__()
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(frequencies, dtype=torch.float32))
        self.out_dim = in_dim * (1 + 2 * frequencies)

    def forward(self, x: Tensor) -> Tensor:
        xf = (x[..., None] * self.freqs).flatten(-2)  # (N, in_dim * F)
        return torch.cat([x, torch.sin(xf), torch.cos(xf)], dim=-1)


class _GridInterpolation(torch.autograd.Function):
    """``out[l, n] = sum_c w[l, n, c] table[index[l, n, c]]``: ``table (R, F)``, ``index (L, N, 8)``
    rows, ``w (L, N, 8)`` -> ``(L, N, F)`` (level-major, so that each level's scatter stays in its
    own part of the table). Backward: the table's gradient by ``index_add_`` (a scatter-add: on
    a GPU its order, and so its last bits, vary between runs) and the weights' by the gathered
    rows. ``tests/model/test_hashgrid.py`` checks it with ``gradcheck`` in float64 and the
    encoding against the paper's loop."""

    @staticmethod
    def forward(ctx, table: Tensor, index: Tensor, w: Tensor) -> Tensor:
        rows = table.index_select(0, index.reshape(-1)).view(*index.shape, table.shape[1])  # (L, N, 8, F)
        ctx.save_for_backward(table, index, w)
        return torch.einsum("lncf,lnc->lnf", rows, w)  # a batched product: 3x faster than multiply-and-sum

    @staticmethod
    def backward(ctx, grad: Tensor):
        table, index, w = ctx.saved_tensors
        g_table = g_w = None
        if ctx.needs_input_grad[0]:
            contrib = (grad[:, :, None, :] * w[..., None]).reshape(-1, table.shape[1])
            g_table = torch.zeros_like(table).index_add_(0, index.reshape(-1), contrib)
        if ctx.needs_input_grad[2]:
            rows = table.index_select(0, index.reshape(-1)).view(*index.shape, table.shape[1])
            g_w = (rows * grad[:, :, None, :]).sum(-1)
        return g_table, None, g_w


class HashGridEncoding(nn.Module):
    """Multiresolution hash encoding (Mueller et al. 2022, "Instant neural graphics primitives",
    ACM TOG 41(4), Sec. 3): ``levels`` grids with resolutions ``N_l = floor(N_min b^l)``,
    ``b = exp((ln N_max - ln N_min) / (levels - 1))``, over the unit sphere's box ``[-1, 1]^3``
    (points outside are clamped to it). A level whose ``(N_l + 1)^3`` vertices fit in its table
    of ``T = 2^log2_size`` entries indexes them one to one; finer levels hash each vertex,
    ``(x * 1 XOR y * 2654435761 XOR z * 805459861) mod T``. Each level trilinearly interpolates
    the ``features``-vectors of its cell's 8 vertices; the output concatenates the point and
    every level's features: ``x (N, 3)`` -> ``(N, 3 + levels * features)``.

    Exact up to float32 rounding (the interpolation is a batched product, so TF32 where a CUDA run
    enables it); computed in float32, or float64 with a float64 table; continuous in ``x``; finite
    everywhere, including the box's faces and far outside it. The table is stored as ``raw`` and
    used as ``step_scale * raw``, so an optimiser's step on it is about ``step_scale`` times the
    networks' (Adam's updates do not depend on a gradient's scale, up to its epsilon), without a
    learning rate of its own: at the paper's 5e-4, ``step_scale = 20`` gives Instant NGP's 1e-2
    (the ``fast`` and ``balanced`` presets' 5e-3 gives 0.1); entries start in ``+-1e-4``.
    The gather and its backward (:class:`_GridInterpolation`) are written out because torch's
    ``embedding`` backward sorts the indices on a CPU (0.5 s a step at 30k points); the rest is
    plain tensors.
    """

    PRIMES = (1, 2654435761, 805459861)

    def __init__(
        self,
        *,
        levels: int = 16,
        features: int = 2,
        log2_size: int = 17,
        min_resolution: int = 16,
        max_resolution: int = 1024,
        step_scale: float = 20.0,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.levels, self.features, self.size = levels, features, 2**log2_size
        growth = math.exp((math.log(max_resolution) - math.log(min_resolution)) / max(levels - 1, 1))
        # floor(N_min b^l), with the rounding of b^l forgiven (16 b^15 is 1023.99999... in floats)
        res = [math.floor(min_resolution * growth**level + 1e-6) for level in range(levels)]
        self.register_buffer("resolution", torch.tensor(res), persistent=False)  # int64: no dtype casts
        #: the levels indexed one to one come first (resolutions grow); a Python int, no device sync
        self.dense_levels = sum((r + 1) ** 3 <= self.size for r in res)
        self.register_buffer("offset", torch.arange(levels) * self.size, persistent=False)
        self.step_scale = float(step_scale)
        init = (torch.rand(levels * self.size, features, generator=generator) * 2.0 - 1.0) * 1e-4
        self.raw = nn.Parameter(init / self.step_scale)
        self.out_dim = 3 + levels * features

    def vertex_index(self, base: Tensor) -> Tensor:
        """Table rows of the 8 vertices of the cells whose lowest vertices are ``base (L, N, 3)``
        (integers): ``(L, N, 8)``, vertex ``c`` at offset ``(c & 1, c >> 1 & 1, c >> 2)``."""
        t = torch.stack([base, base + 1], dim=-1)  # (L, N, 3, 2): each axis' two coordinates
        tx, ty, tz = t[:, :, 0, None, None, :], t[:, :, 1, None, :, None], t[:, :, 2, :, None, None]
        k = self.dense_levels
        n1 = (self.resolution[:k] + 1).view(-1, 1, 1, 1, 1)
        dense = tx[:k] + n1 * (ty[:k] + n1 * tz[:k])
        p = self.PRIMES
        hashed = ((tx[k:] * p[0]) ^ (ty[k:] * p[1]) ^ (tz[k:] * p[2])) & (self.size - 1)
        rows = torch.cat([dense, hashed]).flatten(2)  # (L, N, 8)
        return rows + self.offset.view(-1, 1, 1)

    def forward(self, x: Tensor) -> Tensor:
        work = torch.promote_types(self.raw.dtype, torch.float32)
        with torch.autocast(x.device.type, enabled=False):
            x = x.to(work)
            u = ((x + 1.0) * 0.5).clamp(0.0, 1.0)
            res = self.resolution.to(work).view(-1, 1, 1)
            pos = u * res  # (L, N, 3)
            base = torch.minimum(pos.floor(), res - 1.0)
            frac = pos - base  # in [0, 1]
            wt = torch.stack([1.0 - frac, frac], dim=-1)  # (L, N, 3, 2)
            w = (wt[:, :, 2, :, None, None] * wt[:, :, 1, None, :, None] * wt[:, :, 0, None, None, :]).flatten(2)
            grid = _GridInterpolation.apply(self.raw, self.vertex_index(base.long()), w)  # (L, N, F)
            grid = grid.permute(1, 0, 2).flatten(1) * self.step_scale
            return torch.cat([x, grid], dim=-1)


def make_encoding(
    kind: str, *, frequencies: int, count: int, sigma: float, generator: torch.Generator, hashgrid: dict | None = None
) -> nn.Module:
    """``kind``: ``"nerf"`` (frequencies), ``"fourier"`` (count, sigma), ``"hashgrid"``
    (:class:`HashGridEncoding`'s keyword arguments in ``hashgrid``) or ``"none"``."""
    if kind == "nerf":
        return NerfEncoding(frequencies)
    if kind == "fourier":
        return FourierFeatures(count, sigma, generator=generator)
    if kind == "hashgrid":
        return HashGridEncoding(**(hashgrid or {}), generator=generator)
    if kind == "none":
        return IdentityEncoding()
    raise ValueError(f"unknown encoding {kind!r}; use nerf, fourier, hashgrid or none")


def symmetric(x: Tensor) -> Tensor:
    """TANGO's symmetry prior: encode ``(x, y, |z|)`` (bilateral symmetry across the x-y plane)."""
    return torch.cat([x[..., :2], x[..., 2:].abs()], dim=-1)


def _mlp(in_dim: int, width: int, layers: int, out_dim: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = in_dim
    for _ in range(layers - 1):
        mods += [Linear(d, width), nn.ReLU(inplace=True)]
        d = width
    mods.append(Linear(d, out_dim))
    return nn.Sequential(*mods)


def _init_constant(head: nn.Sequential, value: Tensor) -> None:
    """Make a sigmoid head start near ``value`` everywhere: small last weights, bias = logit."""
    last = head[-1]
    with torch.no_grad():
        last.weight.mul_(0.01)
        last.bias.copy_(torch.logit(value))


# --------------------------------------------------------------------------------------- SVBRDF
@dataclass(frozen=True)
class Material:
    """Per-point material: ``albedo (N, 3)`` and, unless diffuse-only, ``specular (N, 3)`` in
    [0, 1] and ``roughness (N, 1)`` in [min_roughness, 1] (TANGO's terms: diffuse albedo,
    specular colour F0).

    A material carries its BRDF (:attr:`brdf`, an object of :mod:`stages.render.brdf`, by its
    class: this one TANGO's, :class:`GltfMaterial` glTF's), which shades it and names the
    parameters it was made of (``brdf.parameters``). A material of glTF's BRDF (``optimize.brdf:
    gltf``) also carries those: ``base (N, 3)`` colour and ``metallic (N, 1)``; its ``albedo`` and
    ``specular`` are then their TANGO equivalents, ``base (1 - metallic)`` and ``lerp(0.04, base,
    metallic)``, so that figures and material errors read both models alike, while shading,
    baking and export use ``base`` and ``metallic``. Build one from its BRDF's parameters with
    :meth:`of`."""

    albedo: Tensor
    specular: Tensor | None
    roughness: Tensor | None
    base: Tensor | None = None
    metallic: Tensor | None = None

    #: the BRDF whose parameters these are
    brdf: ClassVar[Brdf] = brdfs.TANGO

    @staticmethod
    def of(brdf: Brdf | str, colour: Tensor, specular: Tensor | None = None, roughness: Tensor | None = None) -> Material:
        """A material of ``brdf`` (its object or name) from its parameters in head order
        (``brdf.parameters``: the colour, the specular parameter, the roughness), with the
        channels its BRDF makes of them (``brdf.channels``)."""
        brdf = brdfs.get(brdf)
        return material_type(brdf)(**brdf.channels(colour, specular, roughness))

    @staticmethod
    def gltf(base: Tensor, metallic: Tensor, roughness: Tensor) -> Material:
        """A glTF material with its TANGO equivalents filled in."""
        return Material.of(brdfs.GLTF, base, metallic, roughness)

    def parameters(self) -> dict[str, Tensor | None]:
        """What it was made of, by name: its BRDF's parameters (``brdf.parameters``)."""
        return {name: getattr(self, name) for name in self.brdf.parameters}


@dataclass(frozen=True)
class GltfMaterial(Material):
    """A :class:`Material` of glTF's BRDF (:meth:`Material.of` makes it)."""

    brdf: ClassVar[Brdf] = brdfs.GLTF


#: the material class of each BRDF, by name (one per name of :mod:`stages.render.brdf`)
MATERIAL_TYPES: dict[str, type[Material]] = {kind.brdf.name: kind for kind in (Material, GltfMaterial)}


def material_type(brdf: Brdf) -> type[Material]:
    """The :class:`Material` class of ``brdf``: its own where it has one (:data:`MATERIAL_TYPES`),
    else one made for it once (a frozen subclass whose class attribute ``brdf`` is the model)."""
    kind = MATERIAL_TYPES.get(brdf.name)
    if kind is not None and kind.brdf is brdf:
        return kind
    if brdf not in _MADE_TYPES:
        attributes = {"brdf": brdf, "__doc__": f"A material of {brdf!r}."}
        _MADE_TYPES[brdf] = dataclass(frozen=True)(type(f"{type(brdf).__name__}Material", (Material,), attributes))
    return _MADE_TYPES[brdf]


#: the material classes made for BRDFs without their own (:func:`material_type`)
_MADE_TYPES: dict[Brdf, type[Material]] = {}


def cat_materials(materials: list[Material]) -> Material:
    """The points of several :class:`Material` s of one BRDF as one, in order."""
    first = materials[0]

    def cat(name: str) -> Tensor | None:
        return None if getattr(first, name) is None else torch.cat([getattr(m, name) for m in materials])

    return replace(first, **{name: cat(name) for name in ("albedo", "specular", "roughness", "base", "metallic")})


def material_variation(a: Material, b: Material) -> Tensor:
    """The mean absolute change of a material between two sets of points ``a``, ``b`` (the same
    number ``N`` of points, pairwise, of one BRDF): nvdiffrec's smoothness regulariser (Munkberg et
    al. 2022, "Extracting Triangular 3D Models, Materials, and Lighting From Images", Sec. 4: the
    mean of ``|k(x) - k(x + eps)|`` for a small random ``eps``, for the diffuse and the specular
    parameters). Here, in the BRDF's own parameters (``brdf.parameters``): the mean over points
    and channels of the colour's change (glTF's base colour, or TANGO's diffuse albedo) plus that
    of the other parameters (metallic and roughness, or TANGO's specular colour and roughness;
    none for a diffuse-only material). Each term is in [0, 1]; zero exactly where the material is
    the same at both; subgradient 0 at equality."""
    colour, *others = a.brdf.parameters
    total = (getattr(a, colour) - getattr(b, colour)).abs().mean()
    rest = [(getattr(a, name) - getattr(b, name)).abs() for name in others if getattr(a, name) is not None]
    if rest:
        total = total + torch.cat(rest, dim=-1).mean()
    return total


def normal_tilt(predicted: Tensor, geometric: Tensor) -> Tensor:
    """The mean of ``1 - cos`` of the angle between unit ``predicted (N, 3)`` and unit
    ``geometric (N, 3)`` normals (both on the viewer's side, as a view's hits hold them): 0 where
    the normal network adds nothing, in [0, 2]; half the squared tilt in radians, to fourth order,
    for small tilts; smooth everywhere. nvdiffrec regularises its normal map's perturbation
    likewise (the perturbed normal's change over a jitter); here against the mesh's own normal."""
    return (1.0 - (predicted * geometric).sum(-1)).mean()


class SVBRDFNet(nn.Module):
    """TANGO's SVBRDF MLP: a shared trunk (two layers) and three heads of three layers each for
    the BRDF's parameters (``brdf.parameters``, widths ``brdf.widths``), all bounded by sigmoids:
    TANGO's diffuse albedo (3), specular colour (3) and roughness (1), or glTF's base colour (3),
    metallic (1) and roughness (1) (:meth:`Material.of` makes the material of them).
    ``specular=False`` builds the colour head only (the paper's "-spec, rough" ablation), for a
    BRDF that allows it (``brdf.spec.diffuse_only``). ``init_specular`` / ``init_metallic``: the
    specular head starts near that value everywhere, the one the BRDF reads
    (``brdf.spec.start_setting``)."""

    def __init__(
        self,
        encoding: nn.Module,
        *,
        width: int = 256,
        specular: bool = True,
        init_specular: float | None = None,
        init_roughness: float | None = None,
        init_metallic: float | None = None,
        min_roughness: float = 0.01,
        brdf: Brdf | str = brdfs.TANGO,
    ) -> None:
        super().__init__()
        brdf = brdfs.get(brdf)
        if not specular and not brdf.spec.diffuse_only:
            heads = " and ".join(brdf.parameters[1:])
            raise ValueError(f"the {brdf.name} BRDF needs its {heads} heads (specular: true)")
        self.encoding = encoding
        self.min_roughness = min_roughness
        self.brdf = brdf
        self.trunk = nn.Sequential(
            Linear(encoding.out_dim, width),
            nn.ReLU(inplace=True),
            Linear(width, width),
            nn.ReLU(inplace=True),
        )
        colour, second, rough = brdf.widths
        self.diffuse = _mlp(width, width, 3, colour)
        self.specular = _mlp(width, width, 3, second) if specular else None
        self.roughness = _mlp(width, width, 3, rough) if specular else None
        start = {"init_specular": init_specular, "init_metallic": init_metallic}[brdf.spec.start_setting]
        if specular and start is not None:
            _init_constant(self.specular, brdf.head_start(start))
        if specular and init_roughness is not None:
            u = (float(init_roughness) - min_roughness) / (1.0 - min_roughness)
            _init_constant(self.roughness, torch.tensor([u]))

    def forward(self, points: Tensor) -> Material:
        """``points (N, 3)`` (already symmetrised if the prior is on) -> :class:`Material`."""
        h = self.trunk(self.encoding(points))
        # heads' outputs back to float32 (a no-op unless the products ran under bfloat16 autocast)
        colour = torch.sigmoid(self.diffuse(h).float())
        if self.specular is None:
            return Material.of(self.brdf, colour)
        spec = torch.sigmoid(self.specular(h).float())
        rough = self.min_roughness + (1.0 - self.min_roughness) * torch.sigmoid(self.roughness(h).float())
        return Material.of(self.brdf, colour, spec, rough)


# --------------------------------------------------------------------------------------- normals


class NormalNet(nn.Module):
    """TANGO's normal-offset MLP (three layers) on the encoded point and the face normal.

    TANGO offsets the normal's spherical angles, which is singular at the poles (the azimuth is
    undefined at ``n = +-z``: its gradient is infinite there and an azimuth offset does nothing;
    see ``tests/model/test_networks.py``). Here the network predicts an equivalent bounded offset in
    the normal's tangent frame instead: ``n' = normalize(n + d1 t + d2 b)`` with
    ``d = max_delta tanh(.)``, so the tilt is at most ``atan(sqrt(2) max_delta)`` everywhere.
    """

    def __init__(self, encoding: nn.Module, *, width: int = 256, max_delta: float = 0.3) -> None:
        super().__init__()
        self.encoding = encoding
        self.max_delta = max_delta
        self.mlp = _mlp(encoding.out_dim + 3, width, 3, 2)
        with torch.no_grad():  # start from the geometric normal
            self.mlp[-1].weight.mul_(0.01)
            self.mlp[-1].bias.zero_()

    def forward(self, points: Tensor, normals: Tensor) -> Tensor:
        """``points (N, 3)``, unit ``normals (N, 3)`` -> unit predicted normals ``(N, 3)``."""
        d = self.max_delta * torch.tanh(self.mlp(torch.cat([self.encoding(points), normals], dim=-1)).float())
        t, b = tangent_frame(normals)
        out = normals + d[:, :1] * t + d[:, 1:] * b
        return out / torch.linalg.vector_norm(out, dim=-1, keepdim=True)
