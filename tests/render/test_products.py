"""Float32 linear layers by oneDNN (``optimize.onednn_products``): the same function and gradients
as ``x W^T + b`` written out in float64 here, taken only inside a step that routes them, decided
at run time, recorded, and ATen's path wherever oneDNN is not there (simulated)."""

from __future__ import annotations

import json
import logging

import pytest
import torch
from conftest import TINY_OPTIMIZE, dispatched_ops
from torch import nn

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core.device import bf16_support
from stages.render import products
from stages.render.products import Linear, linear, onednn_choice, onednn_products, route_linear_modules

pytestmark = pytest.mark.skipif(not products.onednn_available(), reason="this torch has no oneDNN")


def _operands(shape: tuple[int, ...], inner: int = 24, out: int = 40, frozen: bool = False, bias: bool = True):
    g = torch.Generator().manual_seed(len(shape) * 100 + inner)
    x = torch.randn(*shape, inner, generator=g, requires_grad=True)
    w = torch.randn(out, inner, generator=g, requires_grad=not frozen)
    b = torch.randn(out, generator=g, requires_grad=True) if bias else None
    return x, w, b


def _textbook(x, w, b, weights):
    """``sum(weights * (x W^T + b))`` and its gradients, in float64, from the definition."""
    x64, w64 = x.detach().double().requires_grad_(), w.detach().double().requires_grad_()
    b64 = None if b is None else b.detach().double().requires_grad_()
    y = torch.einsum("...i,oi->...o", x64, w64) + (0.0 if b64 is None else b64)
    (y * weights.double()).sum().backward()
    return y, [t.grad for t in (x64, w64, b64) if t is not None]


@pytest.mark.parametrize(
    "shape, frozen, bias",
    [((33,), False, True), ((5, 7), False, True), ((5, 7), True, True), ((), False, True), ((300,), True, False)],
    ids=["rows", "batch of rows", "frozen weight", "one vector", "frozen, no bias"],
)
def test_onednn_linear_equals_the_textbook_product_in_value_and_gradient(shape, frozen, bias):
    x, w, b = _operands(shape, frozen=frozen, bias=bias)
    weights = torch.linspace(0.5, 1.5, int(torch.tensor(shape).prod()) * 40).reshape(*shape, 40)
    ref, grads = _textbook(x, w, b, weights)
    with onednn_products(True), dispatched_ops() as ops:
        y = linear(x, w, b)
        (y * weights).sum().backward()
    assert "_linear_pointwise" in ops and "addmm" not in ops
    assert y.dtype == torch.float32 and y.shape == ref.shape
    torch.testing.assert_close(y.double(), ref, rtol=1e-5, atol=1e-5)
    mine = [t.grad for t in (x, w, b) if t is not None and t.requires_grad]
    expected = [g for g, t in zip(grads, (x, w, b) if b is not None else (x, w), strict=True) if t.requires_grad]
    assert len(mine) == len(expected)
    for got, want in zip(mine, expected, strict=True):
        torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-4)


def test_a_non_contiguous_input_and_a_frozen_weight_changed_in_place():
    """A transposed input gives the contiguous one's product; a frozen weight's kept transpose is
    dropped when the weight changes in place (the next input gradient uses the new values)."""
    x, w, b = _operands((6, 9), frozen=True)
    xt = x.detach().transpose(0, 1).contiguous().transpose(0, 1).requires_grad_()
    with onednn_products(True):
        torch.testing.assert_close(linear(xt, w, b), linear(x, w, b))
        linear(x, w, b).sum().backward()
        first = x.grad.clone()
        with torch.no_grad():
            w.mul_(2.0)
        x.grad = None
        linear(x, w, b).sum().backward()
    torch.testing.assert_close(x.grad, 2.0 * first)
    torch.testing.assert_close(x.grad, torch.ones(6, 9, 40) @ w.detach())


@pytest.mark.parametrize("where", ["outside a routed step", "float64", "bfloat16 autocast"])
def test_aten_runs_outside_a_routed_step_for_float64_and_under_autocast(where):
    x, w, b = _operands((4,))
    if where == "float64":
        x, w, b = (t.detach().double() for t in (x, w, b))
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=where == "bfloat16 autocast")
    with onednn_products(where != "outside a routed step"), autocast, dispatched_ops() as ops:
        linear(x, w, b)
        assert not products.routed(x, w)
    assert "addmm" in ops and "_linear_pointwise" not in ops


def test_linear_modules_keep_their_parameters_and_state_dict():
    net = nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Sequential(nn.Linear(8, 2)))
    before = {k: v.clone() for k, v in net.state_dict().items()}
    assert route_linear_modules(net) == 2 and route_linear_modules(net) == 0
    assert all(type(m) is Linear for m in (net[0], net[2][0]))
    assert net.state_dict().keys() == before.keys()
    x = torch.randn(5, 3)
    with onednn_products(True):
        routed = net(x)
    hidden = torch.relu(x @ before["0.weight"].T + before["0.bias"])
    torch.testing.assert_close(routed, hidden @ before["2.0.weight"].T + before["2.0.bias"])


@pytest.mark.parametrize(
    "setting, speedup, device, runs, label, warns",
    [
        ("off", 3.0, "cpu", False, "ATen (onednn_products: off)", False),
        (False, 3.0, "cpu", False, "ATen (onednn_products: off)", False),
        ("on", 0.5, "cpu", True, "oneDNN (onednn_products: on)", False),
        ("auto", 2.13, "cpu", True, "oneDNN (auto: measured 2.13 times ATen's speed on this CPU at {t} threads)", False),
        (
            "auto",
            1.02,
            "cpu",
            False,
            "ATen (auto: oneDNN measured 1.02 times ATen's speed on this CPU at {t} threads, under 1.05)",
            False,
        ),
        ("auto", 3.0, "meta", False, "ATen (no oneDNN products on meta)", False),
        ("on", 3.0, "meta", False, "ATen (no oneDNN products on meta)", True),
    ],
)
def test_the_choice_is_decided_at_run_time(monkeypatch, caplog, setting, speedup, device, runs, label, warns):
    monkeypatch.setattr(products, "measured_speedup", lambda threads: speedup)
    with caplog.at_level(logging.WARNING, logger="stages.render.products"):
        assert onednn_choice(setting, torch.device(device)) == (runs, label.format(t=torch.get_num_threads()))
    assert bool(caplog.records) == warns


def test_the_measured_speedup_is_a_real_ratio_of_two_timings(monkeypatch):
    """Measured, not assumed: slowing one path down (a mutation of the kernels it times) moves the ratio."""
    products.measured_speedup.cache_clear()
    try:
        first = products.measured_speedup(torch.get_num_threads(), repeats=2)
        assert 0.05 < first < 50
        slow = products._onednn

        def slower(x, w, b):
            for _ in range(4):
                out = slow(x, w, b)
            return out

        monkeypatch.setattr(products, "_onednn", slower)
        assert products.measured_speedup(torch.get_num_threads() + 100, repeats=2) < first / 2
    finally:
        products.measured_speedup.cache_clear()


def test_without_onednn_training_runs_aten_and_says_so(monkeypatch, caplog, cache, tmp_path):
    """The fallback taken: a torch without oneDNN (simulated) trains with ATen's products under
    ``on`` (with a warning) and ``auto``, and meta.json records it; the setting is left out of
    the settings' digest (the same products by other kernels: a run resumes across it)."""
    monkeypatch.setattr(products, "onednn_available", lambda: False)
    base = dict(TINY_OPTIMIZE, clip_tiny_test=True, crops=0, normal_network=False, bf16="off", bf16_networks="off")
    s = OptimizeSettings(**base, onednn_products="on")
    with caplog.at_level(logging.WARNING, logger="stages.render.products"):
        optimize.run(cache / "train.npz", cache / "eval.npz", "a vase made of wood", tmp_path, s, "cpu")
    assert any("this torch has no oneDNN" in r.getMessage() for r in caplog.records)
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["float32_products"] == "ATen (this torch has no oneDNN)"
    assert OptimizeSettings(**base, onednn_products="off").digest() == s.digest()


def test_a_step_by_onednn_trains_as_one_by_aten(cache):
    """Three float32 steps from the same start by each path: the same losses and parameters to
    float32 rounding, and the step's linear layers went through oneDNN (none through ATen's addmm)."""
    from stages.core.provenance import Timer
    from stages.geometry.raycache import RayCache
    from stages.guidance.clip import ClipSpec, load_clip
    from stages.training.optimizer import Optimizer

    runs = {}
    for path in ("off", "on"):
        s = OptimizeSettings(**TINY_OPTIMIZE, clip_tiny_test=True, crops=2, bf16="off", bf16_networks="off", onednn_products=path)
        guide = load_clip(ClipSpec(tiny_test=True), "cpu", bf16="off")
        opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase made of wood", "cpu", guide=guide)
        with dispatched_ops() as ops:
            losses = [opt.step(Timer())["loss"] for _ in range(3)]
        runs[path] = (losses, [p.detach().clone() for p in opt.field.parameters()], ops, opt.float32_products)
    assert runs["on"][3] == "oneDNN (onednn_products: on)" and runs["off"][3] == "ATen (onednn_products: off)"
    assert "_linear_pointwise" in runs["on"][2] and "addmm" not in runs["on"][2]
    assert "_linear_pointwise" not in runs["off"][2] and "addmm" in runs["off"][2]
    assert runs["on"][0] == pytest.approx(runs["off"][0], rel=1e-4)
    for a, b in zip(runs["on"][1], runs["off"][1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-5)


def test_the_doctor_names_who_runs_the_float32_linear_layers_of_each_run(monkeypatch):
    from stages import doctor
    from stages.config.workflow import WorkflowConfig

    monkeypatch.setattr(products, "measured_speedup", lambda threads: 2.5)
    cfg = WorkflowConfig(
        {
            "device": "cpu",
            "meshes": {"vase": {"builtin": "vase"}},
            "prompts": {"wood": {"text": "a {object} made of wood"}},
            "variants": {
                "routed": {},
                "aten": {"optimize": {"onednn_products": "off"}},
                "bf16": {"optimize": {"bf16": "on", "bf16_networks": "on"}},
            },
            "optimize": {"clip_tiny_test": True, "iterations": 3, "bf16": "off", "bf16_networks": "off"},
        }
    )
    detail = doctor.check_torch(cfg).detail
    measured = f"measured 2.50 times ATen's speed on this CPU at {torch.get_num_threads()} threads"
    plans = f"oneDNN (auto: {measured}); ATen (onednn_products: off)"
    if bf16_support(torch.device("cpu"))[0]:  # (where bfloat16 is not native, "on" runs float32)
        plans += f"; {products.NOTHING_ROUTED}"
    assert f"float32 linear layers: {plans}" in detail, detail


def test_flops_are_counted_the_same_whichever_kernels_run():
    """``FlopCounterMode`` with :func:`~stages.render.products.flop_formulas` (what the benchmarks'
    floors count with) counts oneDNN's linear layers, which it does not know, as ATen's: forward,
    input and weight gradients, 2 per multiply-add, the bias not counted."""
    from torch.utils.flop_counter import FlopCounterMode

    x, w, b = _operands((5, 7), inner=24, out=40)

    def counted(routed: bool) -> int:
        with FlopCounterMode(display=False, custom_mapping=products.flop_formulas()) as mode, onednn_products(routed):
            linear(x, w, b).sum().backward()
        return mode.get_total_flops()

    assert counted(True) == counted(False) == 3 * 2 * 35 * 24 * 40


def test_nothing_is_timed_or_routed_where_every_linear_layer_runs_bfloat16(cache, monkeypatch):
    """A run whose networks run bfloat16 and CLIP bfloat16 (or on open_clip's own modules, which
    are not routed) has no float32 linear layer to route: it neither times the kernels nor routes,
    and says so; one routed float32 part is enough to decide."""
    from stages.geometry.raycache import RayCache
    from stages.training.optimizer import Optimizer

    timed = []
    monkeypatch.setattr(products, "measured_speedup", lambda threads: timed.append(threads) or 2.0)
    s = OptimizeSettings(**TINY_OPTIMIZE, clip_tiny_test=True, crops=0, bf16="off", bf16_networks="off")
    opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase made of wood", "cpu")
    assert (opt.onednn, opt.float32_products.split(" (")[0]) == (True, "oneDNN") and len(timed) == 1
    opt.field.bf16 = True  # the networks in bfloat16, CLIP still float32: still routed
    assert opt.products_choice()[0] and len(timed) == 2
    opt.guidance.guide.tower = "open_clip"  # CLIP float32 on open_clip's modules: not routed
    assert opt.products_choice() == (False, products.NOTHING_ROUTED)
    opt.guidance.guide.tower, opt.guidance.guide.bf16 = "batched", True
    assert opt.products_choice() == (False, products.NOTHING_ROUTED)
    assert len(timed) == 2


def test_frozen_weights_transposes_are_kept_for_their_owner_only():
    """A run's ``kept`` holds one transpose per frozen weight across its steps: a view made afresh
    at each call (the patch embedding's reshape) finds the same one, an in-place change replaces
    it, and nothing is left on the weight itself (dropped with the run)."""
    conv = torch.randn(40, 3, 2, 4)  # frozen, as CLIP's; used through a new view at each call
    kept: dict = {}
    x = torch.randn(6, 24, requires_grad=True)
    for _ in range(3):
        with onednn_products(True, kept):
            linear(x, conv.reshape(40, -1)).sum().backward()
    assert len(kept) == 1 and not hasattr(conv, "_onednn_transposed")
    (transpose,) = kept.values()
    torch.testing.assert_close(transpose, conv.reshape(40, -1).T)
    conv.mul_(-1.0)
    x.grad = None
    with onednn_products(True, kept):
        linear(x, conv.reshape(40, -1)).sum().backward()
    assert len(kept) == 1
    torch.testing.assert_close(x.grad, torch.ones(6, 40) @ conv.reshape(40, -1))


def test_aten_runs_in_a_compiled_graph_off_the_cpu_for_other_dtypes_and_with_mkldnn_off():
    """``torch.compile`` traces ATen's linear even inside a routed region (the flag never read);
    a tensor off the CPU, a float64 weight, and torch's own switch for oneDNN turned off are not
    routed either."""
    layer = Linear(24, 40)
    x = torch.randn(5, 24)
    graphs = []

    def backend(gm, inputs):  # the graph dynamo traced, kept to read its operations
        graphs.append({str(node.target) for node in gm.graph.nodes})
        return gm.forward

    compiled = torch.compile(layer, backend=backend, fullgraph=True)
    with onednn_products(True):
        torch.testing.assert_close(compiled(x), torch.nn.functional.linear(x, layer.weight, layer.bias))
    assert len(graphs) == 1 and any("linear" in t for t in graphs[0]), graphs
    assert not any("mkldnn" in t or "OneDNN" in t for t in graphs[0]), graphs
    with onednn_products(True):
        assert products.routed(x, layer.weight)
        assert not products.routed(x.to("meta"), layer.weight.to("meta"))
        assert not products.routed(x, layer.weight.double())
        assert not products.routed(torch.randn(5, 0), torch.randn(40, 0))
        with torch.backends.mkldnn.flags(enabled=False):
            assert not products.routed(x, layer.weight)
            assert not products.onednn_available()
