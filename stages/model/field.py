"""The stylisation field: SVBRDF network, optional normal network and SG light, built from a
:class:`~stages.config.sections.FieldSettings`, and its forward pass, the one path from cached
hits to shaded colour that training, evaluation, relighting (a light override), material editing
(scales), baking (:meth:`StyleField.surface`) and the benchmarks all use."""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..config.sections import FieldSettings
from ..core.device import (
    bf16_choice,
    compile_plan,
    lever_choice,
    mark_compiled,
    networks_kind,
    renderer_kind,
    static_kind,
    use_inductor_cache,
)
from ..geometry.normals import NormalSpec
from ..render.shading import SGLight, Shading, face_viewer, shade, shade_gltf
from ..render.specular_albedo import preload_table
from .networks import Material, NormalNet, SGLightModule, SVBRDFNet, make_encoding, symmetric

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FieldOutput:
    shading: Shading
    material: Material
    normal: Tensor  # (N, 3) shading normal (predicted, facing the viewer)


#: inductor's C++ code sums a float32 reduction of more than this many terms in chunks (for its
#: accuracy) and guards on the side of it that the first call's number fell on (torch 2.13,
#: ``CppKernel.need_use_acc_helper``): a graph first run on fewer points than a step's compiled
#: again at the first step (70 s cold, as long as the first compilation)
INDUCTOR_SUM_CHUNK = 4096


def first_pass_points(least: int, typical: int) -> int:
    """Points of a compiled graph's first pass (free shapes), so that the steps reuse what it
    built: the step's ``typical`` number where that is more than :data:`INDUCTOR_SUM_CHUNK` (the
    sums' side, and on a GPU the sizes inductor tunes its kernels for, the step's; no other
    dimension of the graph is that large: lobes, channels, directions and widths are at most
    4,096), else ``least``, a number the caller picks equal to no other size of the graph (lobes,
    channels, 1): sizes that happen to be equal are taken as one symbol (duck sizing), and the
    step's differ: a second compilation. On a CPU the calls of fewer points than the chunk are
    then padded past it (:func:`padded_points`); a call of more than the chunk where ``typical``
    was fewer (small images, a step's crops) compiles once more."""
    return typical if typical > INDUCTOR_SUM_CHUNK else least


def padded_points(device: torch.device, typical: int) -> int:
    """The fewest points a call of a compiled graph of free shapes takes on ``device`` where a
    step's ``typical`` points sized its first pass, fewer padded to them (:func:`padded`): one more
    than :data:`INDUCTOR_SUM_CHUNK` on a CPU where those were more (inductor's code there guards
    on that side: :func:`first_pass_points`; steps of a thin object's views fall on both, and
    each side compiled once), else none (0): a run of small steps pays no padding."""
    return INDUCTOR_SUM_CHUNK + 1 if device.type == "cpu" and typical > INDUCTOR_SUM_CHUNK else 0


def compiled(fn: Callable, brdf: str, device: torch.device, static: bool = False) -> Callable:
    """``fn`` through ``torch.compile(dynamic=True, fullgraph=True)`` (the number of points and of
    lobes free; one graph or an error, never pieces of it run eager, nor all of it where dynamo
    has given up on ``fn``'s code, which it does for good once ``fn`` has run under a dispatch
    mode, such as a FLOP counter's: the callers fall back to eager and say so), as training runs
    it: ``brdf``'s specular table read first on ``device`` (read inside the compiled
    function, the file read broke its graph in two), and Python floats (the renderer's constants)
    taken as the constants they are (``specialize_float``; as inputs, dynamo traced the renderer
    twice per process). The compilation happens at the first call; with inductor's and
    AOTAutograd's caches warm it took 3 s (20 s before these two changes). ``static``: compiled
    for the shapes of its first call instead (``dynamic=False``; another shape compiles again) as
    one graph (``fullgraph``: a graph break is an error, not a piece run outside it), and on CUDA
    with the option of the ``reduce-overhead`` mode that captures the graph, forward and backward,
    as CUDA graphs replayed with one launch each (``compile_static``), and a graph that cannot be
    captured whole an error: ``cudagraph_or_error``, with inductor's graph partitions off, which
    would otherwise run the operations CUDA graphs cannot hold outside them (left alone, inductor
    runs such a graph uncaptured with a log line, while the metadata said CUDA graphs)."""
    preload_table(device, brdf)
    if static:
        capture = {"triton.cudagraphs": True, "triton.cudagraph_or_error": True, "graph_partition": False}
        graph = torch.compile(fn, dynamic=False, fullgraph=True, options=capture if device.type == "cuda" else None)
    else:
        graph = torch.compile(fn, dynamic=True, fullgraph=True)

    @functools.wraps(fn)
    def run_compiled(*args, **kwargs):
        if run_compiled.gave_up is not None:
            return fn(*args, **kwargs)
        try:
            with torch._dynamo.config.patch(specialize_float=True):
                out = graph(*args, **kwargs)
        except (torch._dynamo.exc.Unsupported, torch._dynamo.exc.FailOnRecompileLimitHit, RuntimeError) as exc:
            if not run_compiled.ran or not _refused(exc):
                raise  # the first call's failure is the caller's to handle (it falls back and says so)
            run_compiled.gave_up = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
            log.warning("torch.compile gave up on %s in training (%s): eager from here", fn.__name__, run_compiled.gave_up)
            return fn(*args, **kwargs)
        run_compiled.ran = True
        return out

    #: whether a call ran compiled, and why dynamo refused a later one (the rest then run ``fn``)
    run_compiled.ran, run_compiled.gave_up = False, None
    return run_compiled


def _refused(exc: BaseException) -> bool:
    """Whether ``exc`` is dynamo refusing to run a graph compiled as one (``fullgraph``), before any
    of it ran compiled: its recompilation limit reached, a graph break in a new recompilation, or
    its code skipped (the call then ran eager, its result dropped: the renderer and the networks'
    forward change no state, so running them again changes nothing)."""
    if isinstance(exc, torch._dynamo.exc.Unsupported | torch._dynamo.exc.FailOnRecompileLimitHit):
        return True
    return isinstance(exc, RuntimeError) and "found no compiled frames" in str(exc)


def compiled_shade_material(brdf: str, device: torch.device) -> Callable[..., Shading]:
    """:func:`shade_material` through :func:`compiled` (the renderer alone)."""
    return compiled(shade_material, brdf, device)


def shade_material(
    normal: Tensor, view: Tensor, material: Material, light: SGLight, lobe: str, visibility: Tensor | None = None
) -> Shading:
    """The renderer for ``material``'s BRDF: TANGO's sum (:func:`~stages.render.shading.shade`) or
    glTF's (:func:`~stages.render.shading.shade_gltf`, from the base colour and metallic);
    ``visibility (N, K)``: each light lobe's visible share (shadows, :mod:`stages.model.shadows`)."""
    if material.metallic is not None:
        return shade_gltf(normal, view, material.base, material.metallic, material.roughness, light, lobe, visibility)
    return shade(normal, view, material.albedo, light, material.specular, material.roughness, lobe, visibility)


def first_rows(value, n: int):
    """A :class:`~stages.model.networks.Material` or :class:`~stages.render.shading.Shading` (any
    dataclass of ``(N, ...)`` tensors or None) cut to its first ``n`` rows."""
    return dataclasses.replace(
        value, **{f.name: getattr(value, f.name)[:n] for f in dataclasses.fields(value) if getattr(value, f.name) is not None}
    )


def padded_rows(value, size: int):
    """:func:`padded` for each tensor of a :class:`~stages.model.networks.Material` (any dataclass
    of ``(N, ...)`` tensors or None)."""
    return dataclasses.replace(
        value,
        **{f.name: padded(getattr(value, f.name), size) for f in dataclasses.fields(value) if getattr(value, f.name) is not None},
    )


def padded(x: Tensor, size: int) -> Tensor:
    """``x (N, ...)``, ``0 < N <= size``, with ``size - N`` copies of its first row appended: rows
    whose values are as finite as a real one's and whose outputs, dropped, give them no gradient."""
    return torch.cat([x, x[:1].expand(size - x.shape[0], *x.shape[1:])]) if x.shape[0] < size else x


@dataclass(frozen=True)
class MaterialEdit:
    """TANGO's material editing (Fig. 6): roughness and specular colour scaled, then clamped back
    into their valid ranges (``[min_roughness, 1]`` and ``[0, 1]``); for a glTF material the
    specular scale scales the metalness."""

    roughness_scale: float = 1.0
    specular_scale: float = 1.0

    def apply(self, material: Material, min_roughness: float) -> Material:
        if material.specular is None:
            return material
        rough = (material.roughness * self.roughness_scale).clamp(min_roughness, 1.0)
        if material.metallic is not None:  # glTF: the specular scale scales the metalness
            return Material.gltf(material.base, (material.metallic * self.specular_scale).clamp(0.0, 1.0), rough)
        return Material(
            material.albedo,
            (material.specular * self.specular_scale).clamp(0.0, 1.0),
            (material.roughness * self.roughness_scale).clamp(min_roughness, 1.0),
        )


class StyleField(nn.Module):
    """Material + normals + light, built from ``settings`` (networks, encodings, light, seed)."""

    def __init__(self, settings: FieldSettings) -> None:
        super().__init__()
        s = settings
        gen = torch.Generator().manual_seed(s.seed + 7919)
        hashgrid = {
            "levels": s.hashgrid_levels,
            "features": s.hashgrid_features,
            "log2_size": s.hashgrid_log2_size,
            "min_resolution": s.hashgrid_min_resolution,
            "max_resolution": s.hashgrid_max_resolution,
            "step_scale": s.hashgrid_step_scale,
        }
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(s.seed)
            mat_enc = make_encoding(
                s.material_encoding,
                frequencies=s.material_frequencies,
                count=s.material_fourier_count,
                sigma=s.material_fourier_sigma,
                generator=gen,
                hashgrid=hashgrid,
            )
            self.svbrdf = SVBRDFNet(
                mat_enc,
                width=s.width,
                specular=s.specular,
                init_specular=s.init_specular,
                init_roughness=s.init_roughness,
                init_metallic=s.init_metallic,
                min_roughness=s.min_roughness,
                brdf=s.brdf,
            )
            self.normal_net = None
            if s.normal_network and s.normal_max_delta > 0:
                nrm_enc = make_encoding(
                    s.normal_encoding,
                    frequencies=s.normal_frequencies,
                    count=s.normal_fourier_count,
                    sigma=s.normal_fourier_sigma,
                    generator=gen,
                    hashgrid=hashgrid,
                )
                self.normal_net = NormalNet(nrm_enc, width=s.width, max_delta=s.normal_max_delta)
            self.light = SGLightModule(
                s.light_lobes,
                rgb=s.light_rgb,
                total_energy=s.light_energy,
                init=s.light_init,
                init_sharpness=s.light_init_sharpness,
                max_init_sharpness=s.light_init_max_sharpness,
            )
        self.symmetry = s.symmetry
        self.specular_lobe = s.specular_lobe
        self.brdf = s.brdf
        #: whether the field casts shadows where a ray cache holds visibility (every ViewStore of it)
        self.shadows = s.shadows
        #: the shading normals the field is trained and rendered with (every ViewStore and the bake use them)
        self.normals = NormalSpec(s.shading_normals, s.crease_angle_deg, s.normal_weighting)
        #: the networks' matrix products under bfloat16 autocast (:meth:`use_bf16`; off: float32)
        self.bf16 = False
        #: the renderer compiled by torch.compile for training (:meth:`use_compiled_shading`)
        self.compiled_shade = None
        #: the networks and the renderer compiled together for training (:meth:`use_compiled_shading`)
        self.compiled_field = None
        #: the number of points the one graph is compiled for, each call's padded to it (0: any number)
        self.static_points = 0
        #: :meth:`use_compiled_shading`'s arguments, to compile again where the lobes change
        self._compile_args: tuple = ()
        #: the points a step's call shades, about (:meth:`use_compiled_shading`; 0: unknown)
        self.typical_points = 0
        #: calls of a compiled graph of free shapes with fewer points are padded to these (0: none;
        #: :func:`padded_points`)
        self.least_points = 0
        #: whether that graph is captured as CUDA graphs (a training step then begins with :meth:`begin_step`)
        self.cuda_graphs = False
        #: whether a call with more points than :attr:`static_points` has been warned of (once a run)
        self._warned_size = False
        #: what shades while training, and why (:meth:`use_compiled_shading`; :attr:`shading_path`)
        self._shading_path = "eager"
        self._settings = s

    def use_compiled_shading(
        self,
        setting: str | bool,
        device: torch.device,
        iterations: int,
        shadowed: bool | None = None,
        networks: str | bool = "off",
        static: str | bool = "off",
        points: int = 0,
        typical: int = 0,
    ) -> str:
        """Shade through ``torch.compile(shade, dynamic=True)`` in training mode where the
        optimisation's option ``compile_shading`` (``auto``, ``on``, ``off``) resolves to on for a
        run of ``iterations`` steps on ``device`` (:func:`~stages.core.device.compile_choice`):
        inductor fuses the renderer's many small pointwise operations into a few loops. The same
        function (``tests/model/test_precision.py`` compares them). ``networks``
        (``compile_networks``, :func:`~stages.core.device.compile_networks_choice`): the networks
        compiled into the same graph (:meth:`surface_and_shade`), where the renderer is. It is
        compiled here, forward and backward, on a few points of this field's kind (BRDF, lobe
        model, lobes, shadows, and the networks where they are in it), so that a compilation that
        fails (a compiler that cannot build, missing headers) costs a warning and the renderer
        alone, or the eager one, not the run; inductor's disk cache is
        :func:`~stages.core.device.use_inductor_cache`'s. ``shadowed``: whether the step will pass
        each lobe's visible share (None: :attr:`shadows`; a ray cache without visibility passes
        none), which the compiled graph depends on. ``static`` (``compile_static``,
        :func:`~stages.core.device.compile_static_choice`): that one graph compiled for ``points``
        points (the most a step shades: the training pool's largest view), each call's points
        padded to them (:meth:`forward`), and on CUDA captured as CUDA graphs (none where the
        pool has no points: free shapes, warned). ``typical``: the points a step's call shades
        (about; 0: unknown), which sizes the first pass of a graph of free shapes
        (:func:`first_pass_points`). Returns what runs, for the metadata (:attr:`shading_path`)."""
        device = torch.device(device)
        self._compile_args = (setting, device, iterations, shadowed, networks, static, points, typical)
        self.typical_points = typical
        shadowed = self.shadows if shadowed is None else shadowed
        if points < 1 and lever_choice(static, "compile_static") == "on":
            log.warning("compile_static asked for, but the training pool has no points to pad to: free shapes")
            static = "off"
        kind = renderer_kind(self._settings, shadowed, self.light_learns)
        whole_kind = f"{kind}, {networks_kind(self._settings, self.bf16)}"
        shape = (points, self.light.lobes)
        enabled, whole, static, path = compile_plan(
            (setting, networks, static), device, iterations, (kind, whole_kind), self.bf16, shape
        )
        self.compiled_shade = self.compiled_field = None
        self.static_points, self.cuda_graphs = 0, False
        self.least_points = padded_points(device, typical) if enabled else 0
        if enabled:
            use_inductor_cache()
        if whole:
            failed = self._compile_one_graph(device, shadowed, points if static else 0)
            if failed is None:
                mark_compiled(whole_kind + (static_kind(*shape) if static else ""), device)
            else:
                reasons = path[path.index("(") + 1 : -1]
                path = f"torch.compile ({reasons}; the networks' graph failed: {failed})"
        if enabled and self.compiled_field is None:
            graph = compiled_shade_material(self.brdf, device)
            failed = self._failed("the renderer's", lambda: self._first_compiled_pass(graph, device, shadowed))
            if failed is None:
                self.compiled_shade = graph
                mark_compiled(kind, device)
            else:
                path = f"eager (the compilation failed: {failed})"
        self._shading_path = path
        return path

    @property
    def shading_path(self) -> str:
        """What shades while training, and why, for the metadata: :meth:`use_compiled_shading`'s
        decision, and, where dynamo gave up on the compiled graph during training, that and why."""
        graph = self.compiled_field if self.compiled_field is not None else self.compiled_shade
        gave_up = getattr(graph, "gave_up", None)
        return self._shading_path if gave_up is None else f"{self._shading_path}; eager since torch.compile gave up ({gave_up})"

    def _compile_one_graph(self, device: torch.device, shadowed: bool, size: int) -> str | None:
        """Compile :meth:`surface_and_shade` (free shapes, or for ``size`` points: static, CUDA
        graphs on CUDA) and run its first pass: None where it ran (the graph then trains), else why
        it failed."""
        graph = compiled(self.surface_and_shade, self.brdf, device, size > 0)
        failed = self._failed("the networks' and renderer's", lambda: self._first_field_pass(graph, device, shadowed, size))
        if failed is None:
            self.compiled_field = graph
            self.static_points, self.cuda_graphs = size, size > 0 and device.type == "cuda"
        return failed

    def lobes_changed(self) -> None:
        """The light's number of lobes changed (light pruning, or a pruned checkpoint loaded): a
        graph of static shapes, compiled for the old number, is compiled anew for the new one
        through the same plan, first pass and fallbacks (:meth:`use_compiled_shading`), rather
        than inside a training step, where a failure would end the run. Free shapes need nothing."""
        if self.static_points and self.compiled_field is not None:
            self.use_compiled_shading(*self._compile_args)

    @staticmethod
    def _failed(what: str, first_pass: Callable[[], None]) -> str | None:
        """Run a compiled graph's ``first_pass``: None where it ran, else why it failed, with a
        warning naming ``what`` was compiled (any failure to build means: run without it)."""
        try:
            first_pass()
        except Exception as exc:  # noqa: BLE001 - any failure to build means: run without it
            why = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ''}"
            log.warning("compile_shading: %s compilation failed (%s); it runs without it", what, why)
            return why
        return None

    @property
    def light_learns(self) -> bool:
        """Whether the light is learned (not held at a known environment's fit, ``light: fixed``)."""
        return any(p.requires_grad for p in self.light.parameters())

    def _first_compiled_pass(self, graph: Callable, device: torch.device, shadowed: bool) -> None:
        """``compiled`` forward and backward on a few random points shaped as this field shades in
        training (the same BRDF, lobe model, lobes and shadows; the same inputs needing gradients:
        the networks' outputs, the light and the shares where the light learns, the normal where a
        network predicts it), so the step reuses what it built (its guards check which inputs need
        gradients)."""
        gen = torch.Generator().manual_seed(0)
        n = first_pass_points(2 * self.light.lobes + 3, self.typical_points)

        def leaf(*shape: int, grad: bool = True) -> Tensor:
            return torch.rand(*shape, generator=gen).to(device).requires_grad_(grad)

        normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.nn.functional.normalize(normal + 0.5 * torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.where((view * normal).sum(-1, keepdim=True) < 0, -view, view).to(device)
        normal = normal.to(device)
        rough = leaf(n, 1) * 0.9 + 0.1
        if self.brdf == "gltf":
            material = Material.gltf(leaf(n, 3), leaf(n, 1), rough)
        else:
            material = Material(leaf(n, 3), leaf(n, 3), rough)
        with torch.no_grad():
            light = self.light()
        k, learns = light.axis.shape[0], self.light_learns
        # a fixed light (``light: fixed``) and its shares take no gradient: another backward
        axis, sharpness = leaf(k, 3, grad=learns), leaf(k, 1, grad=learns)
        amplitude = leaf(k, light.amplitude.shape[1], grad=learns)
        light = SGLight(torch.nn.functional.normalize(axis, dim=-1), sharpness + 1.0, amplitude)
        shares = leaf(n, k, grad=learns) if shadowed else None
        # the shading normal needs a gradient only where a network predicts it: a mismatch with the
        # step's made torch.compile compile the renderer a second time at the first step (58 s cold)
        normal.requires_grad_(self.normal_net is not None)
        out = graph(normal, view, material, light, self.specular_lobe, shares)
        out.rgb.sum().backward()

    def _first_field_pass(self, graph: Callable, device: torch.device, shadowed: bool, size: int = 0) -> None:
        """``graph`` (:meth:`surface_and_shade` compiled) forward and backward as the step runs it,
        on random points (:func:`first_pass_points`; at least 17: inductor computes a matrix product
        of at most 16 rows pointwise, and the guard it leaves made the step compile a second time),
        or on ``size`` of them for a static graph,
        under the field's own light, with random shares where the step passes them (a gradient
        where the light learns); the gradients it leaves on the parameters are dropped. A graph
        captured as CUDA graphs is run three times, as CUDA graph trees take a first call to warm
        up, a second to capture and a third to replay: a capture that fails, fails here."""
        captured = size > 0 and device.type == "cuda"
        for _ in range(3 if captured else 1):
            if captured:
                torch.compiler.cudagraph_mark_step_begin()
            # each pass from no gradients, as a step is: a captured graph's gradients live in its
            # memory, which the next pass frees (adding to them would raise)
            self.zero_grad(set_to_none=True)
            self._field_pass(graph, device, shadowed, size or first_pass_points(2 * self.light.lobes + 67, self.typical_points))
        self.zero_grad(set_to_none=True)

    def _field_pass(self, graph: Callable, device: torch.device, shadowed: bool, n: int) -> None:
        """One of :meth:`_first_field_pass`'s passes, on ``n`` random points."""
        gen = torch.Generator().manual_seed(0)
        points = (2.0 * torch.rand(n, 3, generator=gen) - 1.0).to(device)
        normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.nn.functional.normalize(normals + 0.5 * torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.where((view * normals).sum(-1, keepdim=True) < 0, -view, view).to(device)
        light = self.light()
        shares = None
        if shadowed:
            shares = torch.rand(n, light.axis.shape[0], generator=gen).to(device).requires_grad_(self.light_learns)
        graph(points, normals.to(device), view, light, shares)[2].rgb.sum().backward()

    def use_bf16(self, setting: str | bool, device: torch.device) -> str:
        """Run the networks' matrix products under bfloat16 autocast in training mode (the
        optimisation's option ``bf16_networks``: ``auto``, ``on``, ``off``; booleans mean on and
        off; evaluation, baking and relighting run float32) where ``device`` runs bfloat16
        natively (:func:`~stages.core.device.bf16_choice`); the encodings, the heads' outputs
        (sigmoid, tanh), the normals and the renderer stay float32. Returns what runs, for the
        metadata: ``"bfloat16 autocast (<why>)"``, ``"float32"`` or ``"float32 (<why not>)"``."""
        self.bf16, precision = bf16_choice(setting, torch.device(device), "bf16_networks")
        return precision

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As ``nn.Module``'s, and a light whose lobes were pruned (``light_prune_after``) is
        shrunk to the saved number of lobes first (its parameters are new objects then)."""
        saved = state_dict.get("light.axis_raw")
        if saved is not None and saved.shape[0] < self.light.lobes:
            self.light.keep(torch.arange(saved.shape[0]))
        return super().load_state_dict(state_dict, strict, assign)

    def symmetric_points(self, points: Tensor) -> Tensor:
        """The points as the networks see them (``(x, y, |z|)`` under the symmetry prior)."""
        return symmetric(points) if self.symmetry else points

    def surface(self, points: Tensor, normals: Tensor, view: Tensor | None = None) -> tuple[Material, Tensor]:
        """The networks at hit ``points (N, 3)`` with shading ``normals (N, 3)`` (:attr:`normals`):
        the material and the unit shading normal.

        With ``view (N, 3)`` (unit, surface -> eye), normals facing away are first turned towards
        the viewer (two-sided surfaces: the inside of an open vase is visible; a no-op for the
        normals of a :class:`~stages.imaging.views.ViewStore`, which orients them by the face the
        viewer sees) and the predicted normal is kept in the viewer's hemisphere
        (:func:`~stages.render.shading.face_viewer`).
        Without it (texture baking) the normals are taken as given and the prediction returned as is.
        """
        if view is not None:
            flip = (normals * view).sum(-1, keepdim=True) < 0
            normals = torch.where(flip, -normals, normals)
        p = self.symmetric_points(points)
        with torch.autocast(points.device.type, dtype=torch.bfloat16, enabled=self.bf16 and self.training):
            if self.normal_net is not None:
                normals = self.normal_net(p, normals)
            material = self.svbrdf(p)
        if view is not None:
            normals = face_viewer(normals, view)
        return material, normals

    def material(self, points: Tensor) -> Material:
        """The material network alone at ``points (N, 3)``, as :meth:`surface` runs it (the symmetry
        prior, training's bfloat16 autocast), for priors that compare it at nearby points."""
        with torch.autocast(points.device.type, dtype=torch.bfloat16, enabled=self.bf16 and self.training):
            return self.svbrdf(self.symmetric_points(points))

    def forward(
        self,
        points: Tensor,
        normals: Tensor,
        view: Tensor,
        light: SGLight | None = None,
        edit: MaterialEdit | None = None,
        visibility: Callable[[SGLight], Tensor] | None = None,
    ) -> FieldOutput:
        """Shade hit ``points (N, 3)`` with flat ``normals (N, 3)`` seen along ``view (N, 3)``
        (unit, surface -> eye) under the learned light, or under ``light`` (relighting), with the
        material optionally edited (``edit``); ``visibility``: each lobe's visible share ``(N, K)``
        of a light (shadows; :meth:`~stages.imaging.views.CachedView.shade` passes its view's)."""
        if self.compiled_field is not None and self.training and light is None and edit is None:
            light = self.light()
            shares = self._shares(visibility, light)
            if self.static_points:
                return self._static_forward(points, normals, view, light, shares)
            n = points.shape[0]  # fewer points padded to the graph's side (first_pass_points); none: as they are
            return self._padded_forward(points, normals, view, light, shares, max(n, self.least_points) if n else 0)
        material, normal = self.surface(points, normals, view)
        if edit is not None:
            material = edit.apply(material, self.svbrdf.min_roughness)
        return FieldOutput(self.shade(material, normal, view, light, visibility), material, normal)

    def _static_forward(
        self, points: Tensor, normals: Tensor, view: Tensor, light: SGLight, shares: Tensor | None
    ) -> FieldOutput:
        """The static graph (``compile_static``) at the ``N`` points padded to :attr:`static_points`
        (:func:`padded`), its outputs cut back to ``N`` rows. A call with more points than that, or
        none, runs the same function eager (the training pool's largest view sets the size, so
        only a pool changed under a running field has more; it is warned once)."""
        n, size = points.shape[0], self.static_points
        if not 0 < n <= size:
            if n > size and not self._warned_size:
                self._warned_size = True
                log.warning("compile_static: %d points, more than the %d the graph was compiled for: they run eager", n, size)
            material, normal, shading = self.surface_and_shade(points, normals, view, light, shares)
            return FieldOutput(shading, material, normal)
        return self._padded_forward(points, normals, view, light, shares, size)

    def _padded_forward(
        self, points: Tensor, normals: Tensor, view: Tensor, light: SGLight, shares: Tensor | None, size: int
    ) -> FieldOutput:
        """The one graph at the ``N`` points padded to ``size`` (:func:`padded`, ``0 < N <= size``),
        its outputs cut back to ``N`` rows (nothing padded where ``N`` is ``size``)."""
        n = points.shape[0]
        shares = None if shares is None else padded(shares, size)
        material, normal, shading = self.compiled_field(
            padded(points, size), padded(normals, size), padded(view, size), light, shares
        )
        if n == size:
            return FieldOutput(shading, material, normal)
        return FieldOutput(first_rows(shading, n), first_rows(material, n), normal[:n])

    def begin_step(self) -> None:
        """Mark the start of a training step for CUDA graph trees, where the one graph is captured
        as CUDA graphs (:attr:`cuda_graphs`): a step may call the field several times (one per
        view) before its backward, and the last step's outputs are no longer read."""
        if self.cuda_graphs and self.compiled_field is not None:
            torch.compiler.cudagraph_mark_step_begin()

    def surface_and_shade(
        self, points: Tensor, normals: Tensor, view: Tensor, light: SGLight, shares: Tensor | None
    ) -> tuple[Material, Tensor, Shading]:
        """Training's forward pass as one function (:meth:`surface`, then the renderer under
        ``light`` with each lobe's visible ``shares``), for the networks and the renderer compiled
        together (``compile_networks``): the material, the unit shading normal and the shading."""
        material, normal = self.surface(points, normals, view)
        return material, normal, shade_material(normal, view, material, light, self.specular_lobe, shares)

    def _shares(self, visibility: Callable[[SGLight], Tensor] | None, light: SGLight) -> Tensor | None:
        """Each lobe of ``light``'s visible share at the shaded points, where ``visibility`` gives
        them (shadows), in bfloat16 products with the networks' (``lobe_visibility_bits``)."""
        if visibility is None:
            return None
        with torch.autocast(light.axis.device.type, dtype=torch.bfloat16, enabled=self.bf16 and self.training):
            return visibility(light)

    def shade(
        self,
        material: Material,
        normal: Tensor,
        view: Tensor,
        light: SGLight | None = None,
        visibility: Callable[[SGLight], Tensor] | None = None,
    ) -> Shading:
        """The renderer's half of the forward pass: ``material`` and unit shading ``normal`` (from
        :meth:`surface`) seen along ``view``, under the learned light or ``light``, shadowed by
        ``visibility(light)`` when given."""
        light = light if light is not None else self.light()
        shares = self._shares(visibility, light)
        if self.compiled_shade is None or not self.training:
            return shade_material(normal, view, material, light, self.specular_lobe, shares)
        n = normal.shape[0]
        if not 0 < n < self.least_points:
            return self.compiled_shade(normal, view, material, light, self.specular_lobe, shares)
        size = self.least_points  # fewer points padded to the graph's side (first_pass_points)
        shares = None if shares is None else padded(shares, size)
        out = self.compiled_shade(
            padded(normal, size), padded(view, size), padded_rows(material, size), light, self.specular_lobe, shares
        )
        return first_rows(out, n)
