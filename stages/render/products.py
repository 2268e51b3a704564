"""Float32 linear layers by oneDNN's matrix kernels on a CPU (``optimize.onednn_products``).

torch computes a float32 ``linear`` on a CPU with ATen's matrix product, which calls MKL's
``sgemm``. MKL picks its code by CPU vendor as well as by instruction set: on an AMD CPU it runs
its AVX2 code even where the CPU has AVX-512, and oneDNN (which torch also carries, and uses for
bfloat16) does not. Measured on a 2-core AMD EPYC with AVX-512 (``python -m benchmarks.training.optimize``,
docs/measurements/speed.md): the products of CLIP's image tower (250 x 768 by 768 x 3,072 and
the like) ran at 163-182 GFLOP/s by MKL and 417-431 by oneDNN; held to AVX2, 203-205 against 231-233.

:func:`linear` is ``torch.nn.functional.linear``; inside :func:`onednn_products` (entered by the
training step where :func:`onednn_choice` decides so) a float32 product on a CPU outside any
autocast and outside ``torch.compile`` runs forward by ``torch.ops.mkldnn._linear_pointwise``,
with a backward written here (:class:`_OneDNNLinear`): the input's gradient ``g W`` by oneDNN
as well (the transposes of frozen weights, CLIP's, kept for the region's owner: a training run),
the weight's ``g^T x`` by ATen (the long sums over a step's points: oneDNN, given the transposed
operands it takes, ran them slower held to AVX2, 155 against 193 GFLOP/s), the bias's ``sum(g)``.
The same function to float32 rounding (tested against float64 in
``tests/render/test_products.py``). Everything else, bfloat16 under autocast included, runs
ATen's path as before (bfloat16 products already go to oneDNN).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import time
from collections.abc import Iterator
from contextvars import ContextVar

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from ..core.device import lever_choice

log = logging.getLogger(__name__)

#: inside :func:`onednn_products` with routing on: the transposes of frozen weights kept for the
#: region's owner (``(data pointer, shape, strides, version) -> transpose``); None: not routed
_ROUTED: ContextVar[dict | None] = ContextVar("onednn_products", default=None)
#: what a run records where none of its linear layers could be routed
NOTHING_ROUTED = "none (the networks run bfloat16, and CLIP bfloat16 or on open_clip's own modules)"
#: ``auto`` takes oneDNN where it measured at least this many times as fast as ATen
MIN_SPEEDUP = 1.05
#: the shapes :func:`measured_speedup` times, ``(rows, inner, columns)``: CLIP ViT-B's MLP at a
#: paper step's 250 tokens and a width-256 network's layer at 8,192 points
PROBE_SHAPES = ((250, 768, 3072), (8192, 256, 256))


def onednn_available() -> bool:
    """Whether this torch can run float32 linear layers by oneDNN on a CPU (built with it, and
    with the operator this module calls)."""
    return (
        torch.backends.mkldnn.is_available()
        and torch.backends.mkldnn.enabled  # (a user's torch.backends.mkldnn.flags(enabled=False) holds)
        and hasattr(torch.ops.mkldnn, "_linear_pointwise")
    )


def _onednn(x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """``x W^T + b`` by oneDNN, any leading shape of ``x (..., in)``; ``weight (out, in)``."""
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")


def _transposed(weight: Tensor, kept: dict) -> Tensor:
    """``weight^T`` contiguous; for a frozen weight (CLIP's) kept in ``kept`` under its memory,
    shape, strides and version (an in-place change makes a new one; a view made afresh at each
    call, as the patch embedding's, finds the same). A trained weight changes every step and is
    transposed at each use. The owner of ``kept`` drops it with the weights' last use."""
    if weight.requires_grad:
        return weight.detach().t().contiguous()
    key = (weight.data_ptr(), tuple(weight.shape), weight.stride(), weight._version)
    if key not in kept:
        for old in [k for k in kept if k[:3] == key[:3]]:  # an older version of the same weight
            del kept[old]
        kept[key] = weight.t().contiguous()
    return kept[key]


class _OneDNNLinear(torch.autograd.Function):
    """``y = x W^T + b`` forward by oneDNN; backward ``dx = g W`` (oneDNN), ``dW = g^T x`` (ATen),
    ``db = sum of g over rows``, each only where its input needs it."""

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, kept: dict) -> Tensor:
        ctx.save_for_backward(x, weight)
        ctx.kept = kept
        return _onednn(x, weight, bias)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        x, weight = ctx.saved_tensors
        need_x, need_w, need_b, _ = ctx.needs_input_grad
        grad = grad.contiguous()
        rows = grad.reshape(-1, grad.shape[-1])
        dx = _onednn(grad, _transposed(weight, ctx.kept), None) if need_x else None
        dw = rows.t() @ x.reshape(-1, x.shape[-1]) if need_w else None
        db = rows.sum(0) if need_b else None
        return dx, dw, db, None


def routed(x: Tensor, weight: Tensor) -> bool:
    """Whether :func:`linear` takes oneDNN's path for these operands here and now."""
    return (
        not torch.compiler.is_compiling()  # first: a traced graph keeps ATen's (and never reads the flag)
        and _ROUTED.get() is not None
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and weight.dtype == torch.float32
        and weight.shape[-1] > 0  # (oneDNN has no product over nothing)
        and not torch.is_autocast_enabled("cpu")
        and torch.backends.mkldnn.enabled
    )


def linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``torch.nn.functional.linear(x, weight, bias)``: ``x (..., in)``, ``weight (out, in)``,
    ``bias (out,)`` -> ``(..., out)``; by oneDNN where :func:`routed`, else ATen."""
    if routed(x, weight):
        return _OneDNNLinear.apply(x, weight, bias, _ROUTED.get())
    return F.linear(x, weight, bias)


class Linear(nn.Linear):
    """``nn.Linear`` (the same parameters and state dict) computed by :func:`linear`."""

    def forward(self, x: Tensor) -> Tensor:
        return linear(x, self.weight, self.bias)


def route_linear_modules(module: nn.Module) -> int:
    """Make every plain ``nn.Linear`` inside ``module`` a :class:`Linear` (in place; the same
    parameters); returns how many changed."""
    count = 0
    for m in module.modules():
        if type(m) is nn.Linear:
            m.__class__ = Linear
            count += 1
    return count


def onednn_linear_flops(x_shape, w_shape, *args, out_shape=None, **kwargs) -> int:
    """FLOPs of oneDNN's linear layer (``mkldnn._linear_pointwise``, :func:`linear`'s routed
    forward) counted as torch's ``FlopCounterMode`` counts ATen's ``addmm``: 2 per multiply-add of
    ``x W^T`` (``x (..., in)``, ``W (out, in)``), the bias not counted."""
    return 2 * math.prod(x_shape[:-1]) * w_shape[0] * w_shape[1]


def flop_formulas() -> dict:
    """The products this module runs that ``FlopCounterMode`` does not know, with their formulas
    (its ``custom_mapping``), so that a count is the same whichever kernels ran; empty where this
    torch has no oneDNN."""
    return {torch.ops.mkldnn._linear_pointwise: onednn_linear_flops} if onednn_available() else {}


@contextlib.contextmanager
def onednn_products(enabled: bool, kept: dict | None = None) -> Iterator[None]:
    """Inside, :func:`linear` takes oneDNN's path where :func:`routed` (``enabled``), or never.
    ``kept``: where the transposes of frozen weights are kept across regions (a training run
    passes its own for every step, so that CLIP's are made once and dropped with the run); by
    default the region's own."""
    token = _ROUTED.set(({} if kept is None else kept) if enabled else None)
    try:
        yield
    finally:
        _ROUTED.reset(token)


def _seconds(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


@functools.cache
def measured_speedup(threads: int, repeats: int = 3) -> float:
    """ATen's time over oneDNN's for float32 products of :data:`PROBE_SHAPES` on this CPU at
    ``threads`` threads, summed over the shapes, the best of ``repeats`` each, taken in turns
    (about 0.05 s at 2 threads); measured once per process and thread count."""
    gen = torch.Generator().manual_seed(0)
    aten = onednn = 0.0
    for rows, inner, cols in PROBE_SHAPES:
        x, w = torch.randn(rows, inner, generator=gen), torch.randn(cols, inner, generator=gen)
        F.linear(x, w), _onednn(x, w, None)  # first calls: kernels chosen, memory touched
        aten += _seconds(lambda x=x, w=w: F.linear(x, w), repeats)
        onednn += _seconds(lambda x=x, w=w: _onednn(x, w, None), repeats)
    return aten / onednn


def run_choice(setting: str | bool, device: torch.device, networks_bf16: bool, clip: tuple[bool, str] | None) -> tuple[bool, str]:
    """:func:`onednn_choice` for a training run whose networks run bfloat16 or not
    (``networks_bf16``) and whose CLIP (``clip``: ``(bfloat16, tower)``; None where CLIP does not
    guide) runs so: ``(False, NOTHING_ROUTED)`` without timing anything where no float32 layer
    would be routed (the networks bfloat16, and CLIP bfloat16 or on open_clip's own modules)."""
    clip_routed = clip is not None and not clip[0] and clip[1] == "batched"
    if networks_bf16 and not clip_routed:
        return False, NOTHING_ROUTED
    return onednn_choice(setting, device)


def onednn_choice(setting: str | bool, device: torch.device) -> tuple[bool, str]:
    """Whether training's float32 linear layers (the networks', CLIP's) run by oneDNN on ``device``
    (``optimize.onednn_products``: auto, on or off; booleans mean on and off), and what runs, for
    the metadata, the plan and the doctor: ``"oneDNN (<why>)"`` or ``"ATen (<why not>)"``. Only
    on a CPU with oneDNN in torch; ``auto`` where :func:`measured_speedup` found it at least
    :data:`MIN_SPEEDUP` times as fast as ATen here; ``on`` wherever it can (it warns elsewhere)."""
    choice = lever_choice(setting, "onednn_products")
    if choice == "off":
        return False, "ATen (onednn_products: off)"
    device = torch.device(device)
    if device.type != "cpu" or not onednn_available():
        why = f"no oneDNN products on {device.type}" if device.type != "cpu" else "this torch has no oneDNN"
        if choice == "on":
            log.warning("onednn_products asked for, but %s: ATen runs the float32 products", why)
        return False, f"ATen ({why})"
    if choice == "on":
        return True, "oneDNN (onednn_products: on)"
    speedup = measured_speedup(torch.get_num_threads())
    measured = f"measured {speedup:.2f} times ATen's speed on this CPU at {torch.get_num_threads()} threads"
    if speedup >= MIN_SPEEDUP:
        return True, f"oneDNN (auto: {measured})"
    return False, f"ATen (auto: oneDNN {measured}, under {MIN_SPEEDUP})"
