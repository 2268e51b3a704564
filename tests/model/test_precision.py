"""The networks under bfloat16 autocast (``optimize.bf16_networks``): close to float32, finite in
value and gradient at the extremes, float32 where the renderer reads, float32 outside training,
and never silently ignored."""

from __future__ import annotations

import copy
import logging

import pytest
import torch
from torch._dynamo.utils import counters

from stages.config.sections import OptimizeSettings
from stages.core import device as policy
from stages.core.device import bf16_support, compiled_before
from stages.model.compiled import INDUCTOR_SUM_CHUNK, CompiledField, renderer_kind, renderer_sources_digest
from stages.model.field import StyleField
from stages.model.networks import FourierFeatures

CPU = torch.device("cpu")
#: a step's typical points, more than inductor's sum chunk (the compiled tests' first passes)
MANY = INDUCTOR_SUM_CHUNK + 904


def _extreme_inputs():
    """Points on the normalised box's corners and faces, at the origin, tiny and off-centre;
    normals at both poles (where the tangent frame switches), grazing and random."""
    g = torch.Generator().manual_seed(0)
    corners = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0])] * 3)
    pts = torch.cat(
        [
            corners,
            torch.zeros(1, 3),
            torch.full((1, 3), 1e-7),
            torch.tensor([[0.99, -0.999, 0.5]]),
            torch.rand(200, 3, generator=g) * 2 - 1,
        ]
    )
    nrm = torch.randn(len(pts), 3, generator=g)
    nrm[:4] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 1e-7]])
    return pts, nrm / nrm.norm(dim=-1, keepdim=True)


def _compilations() -> int:
    """Graphs dynamo has compiled in this process (its ``frames.ok`` counts none under
    ``fullgraph``: an assertion on it could not fail)."""
    return counters["stats"]["unique_graphs"]


def _more_points_than_the_chunk(compiled: CompiledField, eager: StyleField, shadowed: bool = False) -> None:
    """A training call of more points than inductor's sum chunk runs the graph the first pass
    built (the extreme inputs, fewer, were padded to that side): no compilation, the eager
    field's colours, every gradient within 1e-2 of its norm of float64's (the precision
    benchmark's float32 bound) and the light's within 2e-3. Summed over 5,000 points a broad
    lobe's log-sharpness gradient, whose terms cancel, erred by 5.4e-3 compiled (6e-4 eager) while
    the renderer summed it over the points in float32; in float64
    (``tests/render/test_light_gradient.py``), 5.2e-4."""
    g = torch.Generator().manual_seed(2)
    n = MANY
    pts = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    view = torch.nn.functional.normalize(nrm + 0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    reference = copy.deepcopy(eager).double()

    def visibility(light):  # the SG lobes' shares (the light's one component)
        (sg,) = light.components
        return ((0.5 + 0.5 * (nrm.to(sg.axis.dtype) @ sg.axis.T)).clamp(0.0, 1.0),)

    before, outs = _compilations(), []
    for f, module in ((reference, reference), (eager, eager), (compiled, compiled.field)):
        module.zero_grad(set_to_none=True)
        dtype = next(module.parameters()).dtype
        rgb = f(pts.to(dtype), nrm.to(dtype), view.to(dtype), visibility=visibility if shadowed else None).shading.rgb
        (rgb * torch.linspace(0, 1, rgb.numel(), dtype=dtype).view_as(rgb)).sum().backward()
        outs.append((rgb.detach(), [(name, p.grad.double()) for name, p in module.named_parameters() if p.requires_grad]))
    assert _compilations() == before
    torch.testing.assert_close(outs[2][0], outs[1][0], rtol=1e-5, atol=1e-6)
    for (name, want), (_, got) in zip(outs[0][1], outs[2][1], strict=True):
        assert float((got - want).norm() / want.norm()) < (2e-3 if name.startswith("light.") else 1e-2), name


@pytest.mark.parametrize("encoding", ["nerf", "fourier", "hashgrid"])
def test_bf16_networks_close_to_float32_and_finite(encoding):
    supported, why = bf16_support(CPU)
    if not supported:
        pytest.skip(f"no native bfloat16 here: {why}")
    s = OptimizeSettings(material_encoding=encoding, normal_encoding=encoding, width=64)
    fp32 = StyleField(s.field_settings())
    bf16 = copy.deepcopy(fp32)
    assert CompiledField(bf16).use_bf16(True, CPU).startswith("bfloat16 autocast")
    assert CompiledField(fp32).use_bf16(False, CPU) == "float32"
    # a trained-looking field: heads away from their constant initialisation
    with torch.no_grad():
        for a, b in zip(fp32.parameters(), bf16.parameters(), strict=True):
            a.add_(0.05 * torch.randn(a.shape, generator=torch.Generator().manual_seed(a.numel())))
            b.copy_(a)
    pts, nrm = _extreme_inputs()
    outs = []
    for f in (fp32, bf16):
        mat, n = f.surface(pts, nrm)
        for t in (mat.albedo, mat.specular, mat.roughness, n):
            assert t.dtype == torch.float32 and torch.isfinite(t).all()
        assert ((mat.roughness >= s.min_roughness) & (mat.roughness <= 1)).all()
        torch.testing.assert_close(n.norm(dim=-1), torch.ones(len(n)), rtol=0, atol=1e-5)
        (mat.albedo.sum() + mat.specular.sum() + mat.roughness.sum() + (n * nrm).sum()).backward()
        nets = [*f.svbrdf.parameters(), *f.normal_net.parameters()]
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in nets)
        outs.append((mat, n))
    (m32, n32), (m16, n16) = outs
    for a, b in ((m32.albedo, m16.albedo), (m32.specular, m16.specular), (m32.roughness, m16.roughness)):
        assert (a - b).abs().max() < 0.02
    angle = torch.rad2deg(torch.acos((n32 * n16).sum(-1).clamp(-1, 1)))
    assert angle.max() < 1.0, angle.max()
    assert (m32.albedo - m16.albedo).abs().max() > 0  # bfloat16 really ran
    # outside training (evaluation, baking, relighting): float32, bit for bit
    bf16.eval(), fp32.eval()
    torch.testing.assert_close(bf16.surface(pts, nrm)[0].albedo, fp32.surface(pts, nrm)[0].albedo, rtol=0, atol=0)


def test_fourier_phases_stay_float32_under_autocast():
    """Random Fourier features multiply coordinates by large frequencies: their projection never
    runs in bfloat16 (the phase error would be radians)."""
    enc = FourierFeatures(64, sigma=20.0, generator=torch.Generator().manual_seed(0))
    x = torch.rand(100, 3) * 2 - 1
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = enc(x)
    assert y.dtype == torch.float32
    torch.testing.assert_close(y, enc(x), rtol=0, atol=0)


def test_bf16_networks_not_silently_ignored(monkeypatch):
    monkeypatch.setattr(policy, "bf16_support", lambda device: (False, "no native bfloat16 in this test"))
    f = StyleField(OptimizeSettings(width=16).field_settings())
    assert CompiledField(f).use_bf16(True, CPU) == "float32 (no native bfloat16 in this test)" and not f.bf16


def test_shadow_shares_follow_the_networks_lever_in_training_only(monkeypatch):
    """The shading opens the networks' bfloat16 autocast around the shadows' shares, so their
    quadrature's products (``lobe_visibility_bits``) run in bfloat16 in training with
    ``bf16_networks`` on, and in float32 with it off and outside training (evaluation, baking)."""
    from stages.render import visibility

    seen = []
    monkeypatch.setattr(
        visibility,
        "products_dtype",
        lambda device, work, real=visibility.products_dtype: seen.append(real(device, work)) or seen[-1],
    )
    monkeypatch.setattr(policy, "bf16_support", lambda device: (True, "bfloat16 in this test"))
    f = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    pts, nrm = _extreme_inputs()
    mat, n = f.surface(pts, nrm)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    bits = torch.full((len(pts), 8), 0b10110011, dtype=torch.uint8)

    def shares(light):
        (sg,) = light.components
        return (visibility.lobe_visibility_bits(n.detach(), bits, dirs, sg.axis, sg.sharpness),)

    for setting, training, want in ((True, True, torch.bfloat16), (False, True, torch.float32), (True, False, torch.float32)):
        CompiledField(f).use_bf16(setting, CPU)
        f.train(training)
        out = f.shade(mat, n, nrm, visibility=shares)
        assert seen[-1] == want and torch.isfinite(out.rgb).all()


def _evaluation_stays_eager(compiled: CompiledField, eager: StyleField, graph: str, pts, nrm, view) -> None:
    """Outside training ``compiled`` never runs its compiled ``graph`` (an attribute of it) and
    shades as ``eager`` does."""

    def not_in_evaluation(*args, **kwargs):
        raise AssertionError(f"the {graph} ran outside training")

    setattr(compiled, graph, not_in_evaluation)
    compiled.field.eval()
    with torch.no_grad():
        torch.testing.assert_close(compiled(pts, nrm, view).shading.rgb, eager.eval()(pts, nrm, view).shading.rgb)


@pytest.mark.slow(minutes=1)
@pytest.mark.parametrize(
    ("init", "tolerance", "normal_network", "fixed_light"),
    [("broad", 3e-4, True, False), ("tango", 3e-3, False, False), ("broad", 3e-4, False, True)],
)
def test_compiled_shading_equals_eager_in_training_only(init, tolerance, normal_network, fixed_light):
    """``compile_shading``: the field shades through torch.compile while training, with the same
    colours and gradients as the eager renderer; evaluation (baking, relighting) stays eager.
    Gradients agree to float32's rounding summed in another order: 3e-4 with broad lobes (measured
    1.4e-4 in the gradient of a log-sharpness); a lobe
    of sharpness ~300 (``light_init: tango``) scales the rounding of its cosines by as much
    (measured 1.1e-3 in the gradient of its log-sharpness)."""
    s = OptimizeSettings(
        width=16, light_lobes=4, specular_lobe="isotropic", brdf="tango", light_init=init, normal_network=normal_network
    )
    eager = StyleField(s.field_settings())
    if fixed_light:  # as light: fixed holds it (LightModule.hold): no gradient, another backward
        eager.light.requires_grad_(False)
    compiled = CompiledField(copy.deepcopy(eager))
    # no visibility passed below: compiled for a renderer without shadows
    assert compiled.use_compiled_shading("on", CPU, 1, shadowed=False, typical=MANY).startswith("torch.compile (C++ compiler ")
    kind = renderer_kind(s.field_settings(), False, not fixed_light)
    assert compiled_before(kind, CPU, renderer_sources_digest())  # the next run's auto knows its caches are warm
    off = CompiledField(eager)
    assert off.use_compiled_shading("off", CPU, 1) == "eager" and off.shade_graph is None
    pts, nrm = _extreme_inputs()
    view = torch.nn.functional.normalize(nrm + 0.3 * torch.randn(nrm.shape, generator=torch.Generator().manual_seed(1)), dim=-1)
    outs = []
    compilations = _compilations()
    for f, module in ((eager, eager), (compiled, compiled.field)):
        rgb = f(pts, nrm, view).shading.rgb
        (rgb * torch.linspace(0, 1, rgb.numel()).view_as(rgb)).sum().backward()
        outs.append((rgb.detach(), [p.grad for p in module.parameters() if p.requires_grad]))
    # the first compiled pass built what the step runs: no second compilation (a normal or a fixed
    # light needing a gradient only there, or its points as many as the lobes, made one at the
    # first step: 58 s; so did a step's points on the other side of inductor's sum chunk: 70 s)
    assert _compilations() == compilations
    torch.testing.assert_close(outs[1][0], outs[0][0], rtol=1e-5, atol=1e-6)
    for a, b in zip(outs[1][1], outs[0][1], strict=True):
        assert float((a - b).norm() / b.norm()) < tolerance
    assert len(pts) <= INDUCTOR_SUM_CHUNK == compiled.least_points - 1  # the extreme inputs were padded
    _more_points_than_the_chunk(compiled, eager)
    _evaluation_stays_eager(compiled, eager, "shade_graph", pts, nrm, view)


@pytest.mark.slow(minutes=1.5)
def test_networks_compiled_with_the_renderer_equal_eager_in_training_only():
    """``compile_networks``: the SVBRDF and normal networks compiled into the renderer's graph
    (one graph, :meth:`StyleField.surface_and_shade` compiled by :class:`CompiledField`) give the colours, materials, normals and
    every parameter's gradient of the eager field, with shadows' shares passed, compiled once: the
    first pass leaves no gradient behind and builds what the step runs; evaluation stays eager."""
    s = OptimizeSettings(width=16, light_lobes=4, normal_network=True, light_init="broad")
    eager = StyleField(s.field_settings())
    compiled = CompiledField(copy.deepcopy(eager))
    path = compiled.use_compiled_shading("on", CPU, 1, shadowed=True, networks="on", typical=MANY)
    assert path.startswith("torch.compile, networks and renderer in one graph (C++ compiler ") and path.endswith(
        "; compile_networks: on)"
    )
    assert compiled.field_graph is not None and compiled.shade_graph is None
    assert all(p.grad is None for p in compiled.field.parameters())  # the first pass's gradients dropped
    pts, nrm = _extreme_inputs()
    view = torch.nn.functional.normalize(nrm + 0.3 * torch.randn(nrm.shape, generator=torch.Generator().manual_seed(1)), dim=-1)

    def visibility(light):  # a differentiable share per lobe, as the shadows' are
        (sg,) = light.components
        return ((0.5 + 0.5 * (nrm @ sg.axis.T)).clamp(0.0, 1.0),)

    outs, compilations = [], _compilations()
    for f, module in ((eager, eager), (compiled, compiled.field)):
        out = f(pts, nrm, view, visibility=visibility)
        weights = torch.linspace(0, 1, out.shading.rgb.numel()).view_as(out.shading.rgb)
        ((out.shading.rgb * weights).sum() + out.material.roughness.sum() + out.normal[:, 0].sum()).backward()
        outs.append((out, [p.grad for p in module.parameters() if p.requires_grad]))
    assert _compilations() == compilations  # no second compilation at the first step
    (a, grads_a), (b, grads_b) = outs
    torch.testing.assert_close(b.shading.rgb, a.shading.rgb, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(b.material.albedo, a.material.albedo, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(b.normal, a.normal, rtol=1e-5, atol=1e-6)
    for ga, gb in zip(grads_a, grads_b, strict=True):
        assert float((gb - ga).norm() / ga.norm()) < 3e-4
    _more_points_than_the_chunk(compiled, eager, shadowed=True)
    _evaluation_stays_eager(compiled, eager, "field_graph", pts, nrm, view)


@pytest.mark.slow(minutes=2.5)
def test_a_graph_of_static_shapes_pads_each_step_and_trains_as_eager(cache, caplog):
    """``compile_static``: the one graph compiled for the training pool's largest view; each step's
    points (fewer, and as many as no other step's) padded to it and the outputs cut back, so that
    three steps of the optimiser take the eager run's losses and end at its parameters, with no
    compilation inside a step: light pruning (after step 2, in both runs) compiles the graph anew
    for the fewer lobes before the next step. A step with more points than the graph's runs eager,
    warned."""
    from stages.core.provenance import Timer
    from stages.geometry.raycache import RayCache
    from stages.training.optimizer import Optimizer

    def run(**compile_settings) -> Optimizer:
        s = OptimizeSettings(
            clip_tiny_test=True,
            image_size=64,
            width=16,
            crops=2,
            light_lobes=4,
            iterations=5,
            bf16="off",
            bf16_networks="off",
            light_prune_after=2,
            light_prune_share=0.3,
            **compile_settings,
        )
        return Optimizer(s, RayCache(cache / "train.npz"), "a vase", "cpu")

    eager = run(compile_shading="off")
    assert eager.compiled.typical_points == eager.views.global_points(64) > 0  # what a first pass of free shapes takes
    compilations = counters["stats"]["unique_graphs"]
    static = run(compile_shading="on", compile_networks="on", compile_static="on")
    assert "one graph, static shapes (" in static.shading_path, static.shading_path
    assert counters["stats"]["unique_graphs"] > compilations  # (graphs compiled: fullgraph counts no frames)
    assert static.compiled.static_points == static.views.largest > 0 and not static.compiled.cuda_graphs
    rows = []
    for i in range(3):
        compilations = counters["stats"]["unique_graphs"]
        rows.append((eager.step(Timer()), static.step(Timer())))
        if i != 1:  # padded: the graph of the first pass (or of the pruning), never another in a step
            assert counters["stats"]["unique_graphs"] == compilations, i
    assert static.light_pruned["dropped"] > 0 and static.field.light.lobes == eager.field.light.lobes < 4
    assert static.compiled.field_graph is not None and static.compiled.static_points == static.views.largest
    points = [a["points"] for a, _ in rows]
    assert len(set(points)) > 1 and min(points) < max(points) <= static.compiled.static_points, points  # some padded
    for a, b in rows:
        assert a["points"] == b["points"] and abs(a["loss"] - b["loss"]) <= 1e-5 * abs(a["loss"]) + 1e-7, (a, b)
    for (name, pa), pb in zip(eager.field.named_parameters(), static.field.parameters(), strict=True):
        assert float((pb - pa).norm() / pa.norm().clamp(min=1e-12)) < 1e-4, name
    static.compiled.static_points = 10  # a step of more points than the graph's: eager
    with caplog.at_level(logging.WARNING, logger="stages.model.compiled"):
        a, b = eager.step(Timer()), static.step(Timer())
    assert abs(a["loss"] - b["loss"]) <= 1e-5 * abs(a["loss"]) + 1e-7
    assert any("more than the" in r.getMessage() and "they run eager" in r.getMessage() for r in caplog.records)


def test_each_pass_of_a_captured_graph_starts_from_no_gradients(monkeypatch):
    """A graph captured as CUDA graphs is run three times before training (warm-up, capture,
    replay), each from no gradients, as a step is (a captured graph's gradients live in its
    memory, which the next pass frees: adding to them raises), and leaves none; a CPU's graph runs
    once. (The passes stand in for the real ones, which need CUDA.)"""
    f = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    seen = []

    def a_pass(self, graph, device, shadowed, n):
        seen.append((n, all(p.grad is None for p in self.field.parameters())))
        for p in self.field.parameters():  # as a backward leaves them
            p.grad = torch.ones_like(p)

    monkeypatch.setattr(CompiledField, "_field_pass", a_pass)
    monkeypatch.setattr(torch.compiler, "cudagraph_mark_step_begin", lambda: seen.append("step"))
    CompiledField(f)._first_field_pass(None, torch.device("cuda"), False, 123)
    assert seen == ["step", (123, True)] * 3 and all(p.grad is None for p in f.parameters())
    seen.clear()
    CompiledField(f)._first_field_pass(None, CPU, False, 123)
    assert seen == [(123, True)] and all(p.grad is None for p in f.parameters())


def test_a_compiled_graphs_first_pass_takes_the_steps_side_of_inductors_sum_chunk():
    """The first pass of a graph of free shapes runs on a step's typical points where they are
    more than inductor's sum chunk, then on a CPU the calls of fewer are padded past it; fewer (or
    unknown), on the caller's number, and no padding (a run of small steps pays none)."""
    from stages.model.compiled import first_pass_points, padded_points

    cuda = torch.device("cuda")  # (a device object: nothing runs on it)
    chunk = INDUCTOR_SUM_CHUNK
    typical = (0, 300, chunk, chunk + 1, 25_000)
    assert [first_pass_points(11, t) for t in typical] == [11, 11, 11, chunk + 1, 25_000]
    assert [padded_points(CPU, t) for t in typical] == [0, 0, 0, chunk + 1, chunk + 1]
    assert [padded_points(cuda, t) for t in typical] == [0] * 5
