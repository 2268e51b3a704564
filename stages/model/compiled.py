"""The field as training runs it: a :class:`~stages.model.field.StyleField` wrapped by
:class:`CompiledField` with the levers that trade compilation time or precision for speed and
change what it computes by rounding only: the renderer (or the networks and the renderer as one
graph) through torch.compile, each call's points padded to the size a graph was built for, and the
networks' matrix products under bfloat16 autocast. The field itself stays the model, eager.

Whether a lever is on, on this device, is :mod:`stages.core.device`'s policy; what a compiled graph
depends on is said here, beside the field: its kind (:func:`renderer_kind`, from the field settings
marked :data:`~stages.config.sections.COMPILED_RENDERER`; :func:`networks_kind`;
:func:`static_kind`) and the sources it is built from (:data:`RENDERER_SOURCES`), which the
policy's marks of a compilation made before on this machine are keyed by."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from ..config.sections import COMPILED_RENDERER, FieldSettings, OptimizeSettings
from ..core.device import bf16_choice, compile_plan, lever_choice, mark_compiled, use_inductor_cache
from ..core.safefiles import RECORD_LIMIT, read_bytes
from ..render import brdf as brdfs
from ..render.light import Light, Visibility, map_visibility
from ..render.shading import Shading
from ..render.specular_albedo import preload_table
from .field import FieldOutput, MaterialEdit, StyleField, shade_material
from .networks import Material

log = logging.getLogger(__name__)

#: inductor's C++ code sums a float32 reduction of more than this many terms in chunks (for its
#: accuracy) and guards on the side of it that the first call's number fell on (torch 2.13,
#: ``CppKernel.need_use_acc_helper``): a graph first run on fewer points than a step's compiled
#: again at the first step (70 s cold, as long as the first compilation)
INDUCTOR_SUM_CHUNK = 4096

#: the compiled renderer's code and data, relative to the ``stages`` package: a change to any of
#: them makes its compilation new (:func:`renderer_sources_digest`)
RENDERER_SOURCES = ("render/**/*.py", "render/**/*.npz", "model/field.py", "model/networks.py", "model/compiled.py")


def renderer_kind(settings: FieldSettings, shadowed: bool | None = None, light_learns: bool = True) -> str:
    """What the compiled renderer's graph depends on beyond its code: the field settings marked
    :data:`~stages.config.sections.COMPILED_RENDERER` (the BRDF, the lobe model, shadows, the
    light's channels, whether a normal network predicts the shading normal: its backward differs;
    without it in the kind, the ``fast`` preset, which has none, was marked warm by the paper's
    compilation and compiled for 67 s), ``name=value`` each, with ``shadows`` as given where
    ``shadowed`` is (a ray cache without visibility shades none whatever the settings ask), and
    whether the light learns (``light_learns``: a fixed light takes no gradient). The numbers of
    points and lobes are free in it."""
    values = {name: getattr(settings, name) for name in settings.marked(COMPILED_RENDERER)}
    if shadowed is not None:
        values["shadows"] = shadowed
    words = [f"{name}={value}" for name, value in values.items()]
    return ", ".join([*words, f"light={'learned' if light_learns else 'fixed'}"])


def networks_kind(settings: FieldSettings, bf16: bool) -> str:
    """What the networks compiled into the renderer's graph depend on (to add to
    :func:`renderer_kind`): their settings (encodings, widths, heads, normal network; every field
    setting but the seed, which changes only the starting values) and their precision."""
    fields = {k: v for k, v in dataclasses.asdict(settings).items() if k != "seed"}
    digest = hashlib.sha256(repr(sorted(fields.items())).encode()).hexdigest()[:12]
    return f"networks {digest} in the graph, {'bfloat16' if bf16 else 'float32'}"


def static_kind(points: int, lobes: int) -> str:
    """What the one graph's kind (:func:`networks_kind`) adds when it has static shapes, compiled
    for ``points`` points and ``lobes`` light lobes: each size is another compilation (sizes
    unknown, 0, as the doctor's before any ray cache exists, are a kind never compiled)."""
    return f", static shapes of {points} points and {lobes} lobes"


def compile_kinds(
    settings: FieldSettings, shadowed: bool | None, light_learns: bool, bf16: bool, shape: tuple[int, int] = (0, 0)
) -> tuple[str, str, str]:
    """The kinds :func:`~stages.core.device.compile_plan` looks up: the renderer's alone, the one
    graph's with the networks (of free shapes), and that graph's with static shapes of ``shape``
    (points, lobes)."""
    kind = renderer_kind(settings, shadowed, light_learns)
    whole = f"{kind}, {networks_kind(settings, bf16)}"
    return kind, whole, whole + static_kind(*shape)


@functools.cache
def renderer_sources_digest() -> str:
    """sha256 of :data:`RENDERER_SOURCES`' contents (read once per process: the doctor asks for
    every cell of a grid)."""
    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for pattern in RENDERER_SOURCES:
        for source in sorted(package.glob(pattern)):
            digest.update(read_bytes(source, RECORD_LIMIT))
    return digest.hexdigest()


def planned_path(settings: OptimizeSettings, device: torch.device, shadowed: bool | None) -> str:
    """What an optimisation of ``settings`` on ``device`` would compile, and why, before any ray
    cache exists (the doctor's; :meth:`CompiledField.use_compiled_shading` decides the same way):
    ``shadowed`` as the mesh's ray cache allows (None: as the settings ask)."""
    bf16 = bf16_choice(settings.bf16_networks, device, "bf16_networks")[0]
    kinds = compile_kinds(settings.field_settings(), shadowed, settings.light == "learn", bf16)
    levers = (settings.compile_shading, settings.compile_networks, settings.compile_static)
    return compile_plan(levers, device, settings.iterations, kinds, bf16, renderer_sources_digest())[3]


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


def compiled(fn: Callable, brdf: brdfs.Brdf | str, device: torch.device, static: bool = False) -> Callable:
    """``fn`` through ``torch.compile(dynamic=True, fullgraph=True)`` (the number of points and of
    lobes free; one graph or an error, never pieces of it run eager, nor all of it where dynamo
    has given up on ``fn``'s code, which it does for good once ``fn`` has run under a dispatch
    mode, such as a FLOP counter's: the callers fall back to eager and say so), as training runs
    it: ``brdf``'s specular table (a BRDF or its name) read first on ``device`` (read inside the compiled
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
    preload_table(device, brdfs.get(brdf))
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


def compiled_shade_material(brdf: brdfs.Brdf | str, device: torch.device) -> Callable[..., Shading]:
    """:func:`~stages.model.field.shade_material` through :func:`compiled` (the renderer alone)."""
    return compiled(shade_material, brdf, device)


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


class CompiledField:
    """A :class:`~stages.model.field.StyleField` (:attr:`field`, the model: its parameters, light
    and eager forward pass) as training runs it: called as the field is (:meth:`__call__`,
    :meth:`shade`), it shades through the graphs :meth:`use_compiled_shading` compiled, each
    call's points padded to a graph's size, with the networks in the precision :meth:`use_bf16`
    chose. Outside training mode (the field's ``eval()``), and until a graph is compiled, every
    call is the field's own."""

    def __init__(self, field: StyleField) -> None:
        #: the model this runs
        self.field = field
        #: the renderer compiled by torch.compile for training (:meth:`use_compiled_shading`)
        self.shade_graph: Callable[..., Shading] | None = None
        #: the networks and the renderer compiled together for training (:meth:`use_compiled_shading`)
        self.field_graph: Callable[..., tuple[Material, Tensor, Shading]] | None = None
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

    def use_bf16(self, setting: str | bool, device: torch.device) -> str:
        """Run the networks' matrix products under bfloat16 autocast in training mode (the
        optimisation's option ``bf16_networks``: ``auto``, ``on``, ``off``; booleans mean on and
        off; evaluation, baking and relighting run float32) where ``device`` runs bfloat16
        natively (:func:`~stages.core.device.bf16_choice`); the encodings, the heads' outputs
        (sigmoid, tanh), the normals and the renderer stay float32 (the field's :attr:`bf16`).
        Returns what runs, for the metadata: ``"bfloat16 autocast (<why>)"``, ``"float32"`` or
        ``"float32 (<why not>)"``."""
        self.field.bf16, precision = bf16_choice(setting, torch.device(device), "bf16_networks")
        return precision

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
        compiled into the same graph (:meth:`~stages.model.field.StyleField.surface_and_shade`),
        where the renderer is. It is compiled here, forward and backward, on a few points of this
        field's kind (:func:`compile_kinds`), so that a compilation that fails (a compiler that
        cannot build, missing headers) costs a warning and the renderer alone, or the eager one,
        not the run; inductor's disk cache is :func:`~stages.core.device.use_inductor_cache`'s.
        ``shadowed``: whether the step will pass each lobe's visible share (None: the field's
        ``shadows``; a ray cache without visibility passes none), which the compiled graph depends
        on. ``static`` (``compile_static``, :func:`~stages.core.device.compile_static_choice`):
        that one graph compiled for ``points`` points (the most a step shades: the training pool's
        largest view), each call's points padded to them (:meth:`__call__`), and on CUDA captured
        as CUDA graphs (none where the pool has no points: free shapes, warned). ``typical``: the
        points a step's call shades (about; 0: unknown), which sizes the first pass of a graph of
        free shapes (:func:`first_pass_points`). Returns what runs, for the metadata
        (:attr:`shading_path`)."""
        f, device = self.field, torch.device(device)
        self._compile_args = (setting, device, iterations, shadowed, networks, static, points, typical)
        self.typical_points = typical
        shadowed = f.shadows if shadowed is None else shadowed
        if points < 1 and lever_choice(static, "compile_static") == "on":
            log.warning("compile_static asked for, but the training pool has no points to pad to: free shapes")
            static = "off"
        kinds = compile_kinds(f.settings, shadowed, f.light_learns, f.bf16, (points, f.light.lobes))
        sources = renderer_sources_digest()
        enabled, whole, static, path = compile_plan((setting, networks, static), device, iterations, kinds, f.bf16, sources)
        self.shade_graph = self.field_graph = None
        self.static_points, self.cuda_graphs = 0, False
        self.least_points = padded_points(device, typical) if enabled else 0
        if enabled:
            use_inductor_cache()
        if whole:
            failed = self._compile_one_graph(device, shadowed, points if static else 0)
            if failed is None:
                mark_compiled(kinds[2] if static else kinds[1], device, sources)
            else:
                reasons = path[path.index("(") + 1 : -1]
                path = f"torch.compile ({reasons}; the networks' graph failed: {failed})"
        if enabled and self.field_graph is None:
            graph = compiled_shade_material(f.brdf, device)
            failed = _failed("the renderer's", lambda: self._first_compiled_pass(graph, device, shadowed))
            if failed is None:
                self.shade_graph = graph
                mark_compiled(kinds[0], device, sources)
            else:
                path = f"eager (the compilation failed: {failed})"
        self._shading_path = path
        return path

    @property
    def shading_path(self) -> str:
        """What shades while training, and why, for the metadata: :meth:`use_compiled_shading`'s
        decision, and, where dynamo gave up on the compiled graph during training, that and why."""
        graph = self.field_graph if self.field_graph is not None else self.shade_graph
        gave_up = getattr(graph, "gave_up", None)
        return self._shading_path if gave_up is None else f"{self._shading_path}; eager since torch.compile gave up ({gave_up})"

    def _compile_one_graph(self, device: torch.device, shadowed: bool, size: int) -> str | None:
        """Compile the field's ``surface_and_shade`` (free shapes, or for ``size`` points: static,
        CUDA graphs on CUDA) and run its first pass: None where it ran (the graph then trains),
        else why it failed."""
        graph = compiled(self.field.surface_and_shade, self.field.brdf, device, size > 0)
        failed = _failed("the networks' and renderer's", lambda: self._first_field_pass(graph, device, shadowed, size))
        if failed is None:
            self.field_graph = graph
            self.static_points, self.cuda_graphs = size, size > 0 and device.type == "cuda"
        return failed

    def lobes_changed(self) -> None:
        """The light's number of lobes changed (light pruning, or a pruned checkpoint loaded): a
        graph of static shapes, compiled for the old number, is compiled anew for the new one
        through the same plan, first pass and fallbacks (:meth:`use_compiled_shading`), rather
        than inside a training step, where a failure would end the run. Free shapes need nothing."""
        if self.static_points and self.field_graph is not None:
            self.use_compiled_shading(*self._compile_args)

    def _first_compiled_pass(self, graph: Callable, device: torch.device, shadowed: bool) -> None:
        """``compiled`` forward and backward on a few random points shaped as this field shades in
        training (the same BRDF, lobe model, lobes and shadows; the same inputs needing gradients:
        the networks' outputs, the light and the shares where the light learns, the normal where a
        network predicts it), so the step reuses what it built (its guards check which inputs need
        gradients)."""
        f = self.field
        gen = torch.Generator().manual_seed(0)
        n = first_pass_points(2 * f.light.lobes + 3, self.typical_points)

        def leaf(*shape: int, grad: bool = True) -> Tensor:
            return torch.rand(*shape, generator=gen).to(device).requires_grad_(grad)

        normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.nn.functional.normalize(normal + 0.5 * torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.where((view * normal).sum(-1, keepdim=True) < 0, -view, view).to(device)
        normal = normal.to(device)
        material = f.random_material(leaf, n)
        with torch.no_grad():
            light = f.light()
        learns = f.light_learns
        # a fixed light (``light: fixed``) and its shares take no gradient: another backward
        light = light.like(lambda *shape: leaf(*shape, grad=learns))  # (a light of the field's components' shapes)
        shares = light.visibility_like(lambda *shape: leaf(*shape, grad=learns), n) if shadowed else None
        # the shading normal needs a gradient only where a network predicts it: a mismatch with the
        # step's made torch.compile compile the renderer a second time at the first step (58 s cold)
        normal.requires_grad_(f.normal_net is not None)
        out = graph(normal, view, material, light, f.specular_lobe, shares)
        out.rgb.sum().backward()

    def _first_field_pass(self, graph: Callable, device: torch.device, shadowed: bool, size: int = 0) -> None:
        """``graph`` (the field's ``surface_and_shade`` compiled) forward and backward as the step
        runs it, on random points (:func:`first_pass_points`; at least 17: inductor computes a
        matrix product of at most 16 rows pointwise, and the guard it leaves made the step compile
        a second time), or on ``size`` of them for a static graph, under the field's own light,
        with random shares where the step passes them (a gradient where the light learns); the
        gradients it leaves on the parameters are dropped. A graph captured as CUDA graphs is run
        three times, as CUDA graph trees take a first call to warm up, a second to capture and a
        third to replay: a capture that fails, fails here."""
        f = self.field
        captured = size > 0 and device.type == "cuda"
        for _ in range(3 if captured else 1):
            if captured:
                torch.compiler.cudagraph_mark_step_begin()
            # each pass from no gradients, as a step is: a captured graph's gradients live in its
            # memory, which the next pass frees (adding to them would raise)
            f.zero_grad(set_to_none=True)
            self._field_pass(graph, device, shadowed, size or first_pass_points(2 * f.light.lobes + 67, self.typical_points))
        f.zero_grad(set_to_none=True)

    def _field_pass(self, graph: Callable, device: torch.device, shadowed: bool, n: int) -> None:
        """One of :meth:`_first_field_pass`'s passes, on ``n`` random points."""
        f = self.field
        gen = torch.Generator().manual_seed(0)
        points = (2.0 * torch.rand(n, 3, generator=gen) - 1.0).to(device)
        normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.nn.functional.normalize(normals + 0.5 * torch.randn(n, 3, generator=gen), dim=-1)
        view = torch.where((view * normals).sum(-1, keepdim=True) < 0, -view, view).to(device)
        light = f.light()
        shares = None
        if shadowed:
            shares = light.visibility_like(
                lambda *shape: torch.rand(*shape, generator=gen).to(device).requires_grad_(f.light_learns), n
            )
        graph(points, normals.to(device), view, light, shares)[2].rgb.sum().backward()

    def __call__(
        self,
        points: Tensor,
        normals: Tensor,
        view: Tensor,
        light: Light | None = None,
        edit: MaterialEdit | None = None,
        visibility: Callable[[Light], Visibility] | None = None,
    ) -> FieldOutput:
        """The field's forward pass (:meth:`~stages.model.field.StyleField.forward`, the same
        arguments) in training mode through the compiled graphs: the one graph of the networks
        and the renderer under the learned light, unedited, or the field's networks then the
        compiled renderer; eager where none is compiled or outside training."""
        f = self.field
        if self.field_graph is not None and f.training and light is None and edit is None:
            light = f.light()
            shares = f.shares(visibility, light)
            if self.static_points:
                return self._static_forward(points, normals, view, light, shares)
            n = points.shape[0]  # fewer points padded to the graph's side (first_pass_points); none: as they are
            return self._padded_forward(points, normals, view, light, shares, max(n, self.least_points) if n else 0)
        if self.shade_graph is None or not f.training:
            return f(points, normals, view, light, edit, visibility)
        material, normal = f.surface(points, normals, view)
        if edit is not None:
            material = edit.apply(material, f.svbrdf.min_roughness)
        return FieldOutput(self.shade(material, normal, view, light, visibility), material, normal)

    def _static_forward(
        self, points: Tensor, normals: Tensor, view: Tensor, light: Light, shares: Visibility | None
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
            material, normal, shading = self.field.surface_and_shade(points, normals, view, light, shares)
            return FieldOutput(shading, material, normal)
        return self._padded_forward(points, normals, view, light, shares, size)

    def _padded_forward(
        self, points: Tensor, normals: Tensor, view: Tensor, light: Light, shares: Visibility | None, size: int
    ) -> FieldOutput:
        """The one graph at the ``N`` points padded to ``size`` (:func:`padded`, ``0 < N <= size``),
        its outputs cut back to ``N`` rows (nothing padded where ``N`` is ``size``)."""
        n = points.shape[0]
        shares = map_visibility(lambda v: padded(v, size), shares)
        material, normal, shading = self.field_graph(
            padded(points, size), padded(normals, size), padded(view, size), light, shares
        )
        if n == size:
            return FieldOutput(shading, material, normal)
        return FieldOutput(first_rows(shading, n), first_rows(material, n), normal[:n])

    def begin_step(self) -> None:
        """Mark the start of a training step for CUDA graph trees, where the one graph is captured
        as CUDA graphs (:attr:`cuda_graphs`): a step may call the field several times (one per
        view) before its backward, and the last step's outputs are no longer read."""
        if self.cuda_graphs and self.field_graph is not None:
            torch.compiler.cudagraph_mark_step_begin()

    def shade(
        self,
        material: Material,
        normal: Tensor,
        view: Tensor,
        light: Light | None = None,
        visibility: Callable[[Light], Visibility] | None = None,
    ) -> Shading:
        """The field's :meth:`~stages.model.field.StyleField.shade` (the same arguments) through
        the compiled renderer in training mode, fewer points than :attr:`least_points` padded to
        them; eager where it is not compiled or outside training."""
        f = self.field
        if self.shade_graph is None or not f.training:
            return f.shade(material, normal, view, light, visibility)
        light = light if light is not None else f.light()
        shares = f.shares(visibility, light)
        n = normal.shape[0]
        if not 0 < n < self.least_points:
            return self.shade_graph(normal, view, material, light, f.specular_lobe, shares)
        size = self.least_points  # fewer points padded to the graph's side (first_pass_points)
        shares = map_visibility(lambda v: padded(v, size), shares)
        out = self.shade_graph(
            padded(normal, size), padded(view, size), padded_rows(material, size), light, f.specular_lobe, shares
        )
        return first_rows(out, n)
