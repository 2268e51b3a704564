"""On a CUDA device: the renderer and a training step against CPU float64 references, bfloat16
finite at the extremes, and the tiny and offline-demo workflows end to end on the GPU.

Every CUDA test here is marked ``gpu`` and skips without CUDA (CI machines have none; a lent GPU
runs them with ``pytest -m gpu tests/gpu``); the float32-against-float64 comparisons also run on
the CPU, on every machine. Relative errors are ``|out - ref| / |ref|`` over the whole tensor,
against float64 on the CPU (TF32 is off here). First run on a GPU (an H100) on 2026-11-25:
docs/measurements/speed.md#gpu.
"""

from __future__ import annotations

import json
import math
import shutil

import pytest
import torch
from conftest import REPO, dispatched_ops, run_snakemake

from stages.config.sections import ClipSpec, OptimizeSettings
from stages.geometry.raycache import RayCache
from stages.guidance.clip import TINY_MODEL, load_clip
from stages.model.compiled import CompiledField
from stages.model.field import StyleField
from stages.model.lights.sg import SGLightModule
from stages.model.networks import Material
from stages.render.brdf import TANGO
from stages.render.shading import face_viewer
from stages.training.optimizer import Optimizer

NEEDS_CUDA = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]
CUDA = torch.device("cuda")
#: the float32 device of the comparisons against float64: the GPU, and (without the GPU marks, so
#: that every machine runs it) the CPU, whose float32 is the same arithmetic up to its own rounding
FLOAT32_DEVICES = [pytest.param("cpu", marks=[]), pytest.param("cuda", marks=NEEDS_CUDA)]


@pytest.fixture(autouse=True)
def no_tf32():
    """Full float32 products (TF32 would be a reduced precision of its own)."""
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def rel(out: torch.Tensor, ref: torch.Tensor) -> float:
    out = out.detach().double().cpu()
    assert torch.isfinite(out).all()
    return float((out - ref.detach().cpu()).norm() / ref.detach().cpu().norm())


def shading_inputs(n: int, seed: int) -> dict[str, torch.Tensor]:
    """Random unit normals (both poles and a grazing view among them), views in the normal's
    hemisphere, materials with roughness from 0.01 to 1 (float64, CPU)."""
    g = torch.Generator().manual_seed(seed)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    nrm[:2] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    view = torch.nn.functional.normalize(nrm + torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    view = torch.where((view * nrm).sum(-1, keepdim=True) < 0, -view, view)
    view[2] = torch.nn.functional.normalize(torch.cross(nrm[2], torch.tensor([1.0, 0, 0], dtype=torch.float64), dim=0), dim=0)
    rough = torch.rand(n, 1, generator=g, dtype=torch.float64) * 0.99 + 0.01
    rough[:4] = torch.tensor([[0.01], [1.0], [0.01], [1.0]], dtype=torch.float64)
    # the renderer's valid inputs face the viewer (n . v > 0): as the field does, bend the normals
    # (the grazing view's n . v becomes 5e-4; exactly 0 gave NaN in float32, outside the range)
    nrm = face_viewer(nrm, view)
    return {
        "normal": nrm,
        "view": view,
        "albedo": torch.rand(n, 3, generator=g, dtype=torch.float64),
        "specular": torch.rand(n, 3, generator=g, dtype=torch.float64),
        "roughness": rough,
    }


@pytest.mark.parametrize("dev", FLOAT32_DEVICES)
@pytest.mark.parametrize("lobe", ["isotropic", "split_sum", "fitted"])
def test_renderer_in_float32_matches_float64(lobe, dev):
    """shade() in float32 (on the GPU, and on the CPU) against float64 on the CPU: radiance and
    its gradients to the material, the normal, the view and the light (fresh random inputs,
    grazing views, both poles, roughness at both ends, 32 lobes of a random light). Gradients
    within 1e-3: the float32 rounding of a cosine is scaled by its lobe's sharpness (up to ~e^3
    here; measured on the CPU: 4.3e-4 in the log-sharpnesses' gradient, 7.1e-4 in the view's under
    split_sum at n . v = 0.0025). The fitted lobe's gradients to the normal and the view, once off
    by 2% and 29% (a half vector and a Fresnel factor taken by cancelling differences and clamped,
    and the axis's component across the view's plane as ``1 - nl^2 - tl^2``), measure 3.8e-6 and
    9.6e-6 on the CPU."""
    x64 = shading_inputs(4096, seed=1)
    light = SGLightModule(32).double()
    with torch.no_grad():
        light.log_sharpness.add_(
            torch.randn(light.log_sharpness.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        )
    results = {}
    for name, device, dtype in (("reference", torch.device("cpu"), torch.float64), ("float32", torch.device(dev), torch.float32)):
        lm = SGLightModule(32).to(device, dtype)
        lm.load_state_dict({k: v.to(device, dtype) for k, v in light.state_dict().items()})
        # copies: the float64 pass must not make the reference inputs themselves leaves with grads
        x = {k: v.to(device, dtype, copy=True).requires_grad_() for k, v in x64.items()}
        out = TANGO.shade(x["normal"], x["view"], Material(x["albedo"], x["specular"], x["roughness"]), lm(), lobe)
        rgb = out.diffuse + out.specular
        weights = torch.linspace(0.5, 1.5, rgb.numel(), device=device, dtype=dtype).view_as(rgb)
        (rgb * weights).sum().backward()
        results[name] = (rgb, {k: v.grad for k, v in x.items()}, [p.grad for p in lm.parameters()])
    (ref, gref, lref), (out, gout, lout) = results["reference"], results["float32"]
    assert rel(out, ref) < 1e-5
    for k in sorted(gref):
        assert rel(gout[k], gref[k]) < 1e-3, k
    for a, b in zip(lout, lref, strict=True):
        assert rel(a, b) < 1e-3


@pytest.mark.parametrize("dev", FLOAT32_DEVICES)
def test_field_forward_backward_in_float32_matches_float64(dev):
    """The field's networks, shading and an image loss: loss and every parameter's gradient in
    float32 (on the GPU, and on the CPU) against float64 on the CPU. Within 1e-3, except the
    material network's first layer (1e-2): its inputs are the NeRF encoding's sines of
    ``2^k pi x`` up to k = 9, whose float32 phases are rounded by up to ``2^9 pi`` ulps (measured:
    3.6e-3 on the CPU and on the H100 alike)."""
    s = OptimizeSettings(width=64, light_lobes=16)
    ref_field = StyleField(s.field_settings()).double()
    x = shading_inputs(8192, seed=3)
    pts = torch.rand(8192, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 2 - 1
    target = torch.rand(8192, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    grads, losses = {}, {}
    for name, device, dtype in (("reference", torch.device("cpu"), torch.float64), ("float32", torch.device(dev), torch.float32)):
        f = StyleField(s.field_settings()).to(device, dtype)
        f.load_state_dict({k: v.to(device, dtype) for k, v in ref_field.state_dict().items()})
        out = f(pts.to(device, dtype), x["normal"].to(device, dtype), x["view"].to(device, dtype))
        loss = ((out.shading.rgb - target.to(device, dtype)) ** 2).mean()
        loss.backward()
        losses[name] = loss
        grads[name] = {k: p.grad for k, p in f.named_parameters() if p.grad is not None}
    assert rel(losses["float32"], losses["reference"]) < 1e-5
    assert grads["float32"].keys() == grads["reference"].keys()
    for k, g in grads["reference"].items():
        assert rel(grads["float32"][k], g) < (1e-2 if k == "svbrdf.trunk.0.weight" else 1e-3), k


@pytest.mark.skipif(torch.cuda.is_available(), reason="takes the path of a machine without CUDA")
def test_the_gpu_checks_stop_with_a_message_without_cuda(tmp_path):
    """``benchmarks/gpu_checks.sh`` (and ``benchmarks.training.gpu`` under it) on a machine without CUDA:
    one line saying so and what to run instead, exit status 2, no logs that look like results."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PATH": f"{os.path.dirname(sys.executable)}{os.pathsep}{os.environ.get('PATH', '')}"}  # this torch's
    script = [str(REPO / "benchmarks" / "gpu_checks.sh"), str(tmp_path / "out")]
    done = subprocess.run(["bash", *script], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "torch sees no CUDA device; on a CPU use python -m benchmarks.training.optimize" in done.stderr
    assert not any((tmp_path / "out").iterdir())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_training_steps_on_cuda_match_cpu(cache):
    """Three real steps of the optimiser (image guidance, our own targets) on the GPU and on the
    CPU from the same seed: the same views and crops, losses within float32 rounding."""
    s = OptimizeSettings(
        guidance="image", target_renderer="sg", image_size=64, width=32, crops=2, light_lobes=8, iterations=3, bf16_networks="off"
    )
    losses = {}
    for dev in ("cpu", "cuda"):
        opt = Optimizer(s, RayCache(cache / "train.npz"), "", dev)
        losses[dev] = [opt.step(_timer())["loss"] for _ in range(3)]
    for a, b in zip(losses["cuda"], losses["cpu"], strict=True):
        assert math.isfinite(a) and abs(a - b) <= 1e-4 * abs(b) + 1e-7, losses


def _timer():
    from stages.core.provenance import Timer

    return Timer()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.slow(minutes=2)
def test_compiled_renderer_on_cuda_equals_eager():
    """``compile_shading: on`` on CUDA (Triton): the field's compiled renderer gives the eager
    renderer's colours and, to float32's rounding in another order, its gradients; or, where
    Triton cannot build, the field says so and runs eager."""
    import copy

    s = OptimizeSettings(width=16, light_lobes=8)
    eager = StyleField(s.field_settings()).cuda()
    compiled = CompiledField(copy.deepcopy(eager))
    path = compiled.use_compiled_shading("on", torch.device("cuda"), 1, shadowed=False)
    if not path.startswith("torch.compile"):
        assert path.startswith("eager (") and compiled.shade_graph is None, path
        return
    g = torch.Generator().manual_seed(3)
    pts = (torch.rand(4096, 3, generator=g) * 2 - 1).cuda()
    nrm = torch.nn.functional.normalize(torch.randn(4096, 3, generator=g), dim=-1).cuda()
    view = torch.nn.functional.normalize(nrm + 0.5 * torch.randn(4096, 3, generator=g).cuda(), dim=-1)
    outs = []
    for f, module in ((eager, eager), (compiled, compiled.field)):
        rgb = f(pts, nrm, view).shading.rgb
        (rgb * torch.linspace(0, 1, rgb.numel(), device="cuda").view_as(rgb)).sum().backward()
        outs.append((rgb.detach(), [p.grad for p in module.parameters()]))
    torch.testing.assert_close(outs[1][0], outs[0][0], rtol=1e-4, atol=1e-5)
    for a, b in zip(outs[1][1], outs[0][1], strict=True):
        assert float((a - b).norm() / b.norm().clamp(min=1e-12)) < 3e-3


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.slow(minutes=3)
def test_one_graph_captured_as_cuda_graphs_trains_as_eager(cache):
    """``compile_static: on`` on CUDA: the networks' and renderer's graph, each step's points padded
    to the largest view's, captured whole as CUDA graphs (a graph break, a skipped capture or a
    partition left outside is an error, which would fall back to the renderer alone), trains as
    the eager field: three steps of two views each (two calls of the graph before one backward)
    take the eager run's losses, with no compilation inside a step."""
    from torch._dynamo.utils import counters

    from stages.core.device import compile_support

    if not compile_support(CUDA)[0]:
        pytest.skip(compile_support(CUDA)[1])
    s = {"guidance": "image", "target_renderer": "sg", "image_size": 64, "width": 32, "crops": 2, "light_lobes": 8}
    s.update(iterations=3, views_per_step=2, bf16_networks="off")
    eager = Optimizer(OptimizeSettings(**s), RayCache(cache / "train.npz"), "", "cuda")
    on = {"compile_shading": "on", "compile_networks": "on", "compile_static": "on"}
    graphs = Optimizer(OptimizeSettings(**s, **on), RayCache(cache / "train.npz"), "", "cuda")
    assert "one graph as CUDA graphs (" in graphs.shading_path and graphs.compiled.cuda_graphs, graphs.shading_path
    assert graphs.compiled.static_points == graphs.views.largest
    compiled = counters["stats"]["unique_graphs"]
    for _ in range(3):
        a, b = eager.step(_timer()), graphs.step(_timer())
        assert math.isfinite(b["loss"]) and abs(a["loss"] - b["loss"]) <= 1e-4 * abs(a["loss"]) + 1e-6, (a, b)
    assert counters["stats"]["unique_graphs"] == compiled  # replayed, never compiled again in a step


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_bf16_finite_at_the_extremes_on_cuda():
    """bfloat16 networks and CLIP on the GPU: finite values and gradients at the box's corners,
    both poles and a grazing normal, and for black and white images."""
    s = OptimizeSettings(width=64)
    f = StyleField(s.field_settings()).to(CUDA)
    if not CompiledField(f).use_bf16(True, CUDA).startswith("bfloat16 autocast"):
        pytest.skip("this GPU has no native bfloat16")
    corners = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0])] * 3)
    pts = torch.cat([corners, torch.zeros(1, 3), torch.full((1, 3), 1e-7)]).to(CUDA)
    nrm = torch.nn.functional.normalize(torch.randn(len(pts), 3), dim=-1)
    nrm[:3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 1.0, 1e-7]])
    mat, n = f.surface(pts, nrm.to(CUDA))
    (mat.albedo.sum() + mat.specular.sum() + mat.roughness.sum() + n.sum()).backward()
    assert all(torch.isfinite(t).all() for t in (mat.albedo, mat.specular, mat.roughness, n))
    assert all(torch.isfinite(p.grad).all() for p in f.svbrdf.parameters())
    guide = load_clip(ClipSpec(model=TINY_MODEL, pretrained="", tiny_test=True), device=CUDA, bf16=True)
    assert guide.bf16
    text = guide.embed_text("a vase made of wood")
    for images in (torch.zeros(2, 3, 64, 64), torch.ones(2, 3, 64, 64)):
        x = images.to(CUDA).requires_grad_()
        guide.similarity(x, text).backward()
        assert torch.isfinite(x.grad).all()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.slow
@pytest.mark.parametrize("configfile", ["config/tiny.yaml", "config/demo-offline.yaml"])
def test_workflow_end_to_end_on_cuda(tmp_path, configfile):
    """The tiny and the offline-demo experiments with ``device: cuda``: every job succeeds and
    every optimisation ran on the GPU (its metadata says so)."""
    # the configs name their environment maps relative to the repository (config/envmaps/...)
    shutil.copytree(REPO / "config" / "envmaps", tmp_path / "config" / "envmaps")
    proc = run_snakemake(
        tmp_path, "--cores", "4", "--configfile", str(REPO / configfile), "--config", "device=cuda", timeout=3000
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    # results/<experiment>/<mesh>/<prompt>/<variant>/optimize
    metas = list((tmp_path / "results").glob("*/*/*/*/optimize/meta.json"))
    assert metas
    for m in metas:
        assert json.loads(m.read_text())["device"].startswith("cuda"), m


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_shadow_shares_on_cuda_match_the_cpu():
    """Each lobe's visible share with the light on the GPU (the stored bits stay on the CPU and
    are moved per batch) against the same shares on the CPU in float64."""
    import numpy as np
    import trimesh

    from stages.geometry.meshio import TriMesh
    from stages.geometry.tracing import EmbreeTracer
    from stages.model.shadows import ShadowCache
    from stages.render.shading import SGLight

    knot = trimesh.creation.torus(major_radius=0.6, minor_radius=0.2)
    mesh = TriMesh(np.asarray(knot.vertices, np.float64), np.asarray(knot.faces, np.int64))
    pts, nrm = mesh.vertices[mesh.faces[:, 0]], mesh.face_normals
    shadows = ShadowCache(mesh, pts, nrm, EmbreeTracer(mesh), directions=256)
    gen = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(torch.randn(8, 3, generator=gen, dtype=torch.float64), dim=-1)
    sharp = torch.logspace(-2, 1.5, 8, dtype=torch.float64)[:, None]
    ref = shadows.shares(SGLight(axis, sharp, torch.ones(8, 3, dtype=torch.float64)))
    index = torch.arange(0, len(pts), 3, device=CUDA)
    out = shadows.shares(SGLight(axis.float().to(CUDA), sharp.float().to(CUDA), torch.ones(8, 3, device=CUDA)), index)
    assert out.device.type == "cuda"
    assert float((out.double().cpu() - ref[index.cpu()]).abs().max()) < 1e-4


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_clip_attention_on_cuda_takes_the_fused_kernel_and_matches_float64():
    """CLIP's self-attention on the GPU takes torch's fused kernel (``fused_attention``; a
    scaled-dot-product operation dispatched) and gives the float64 function's values and gradients
    (plain products on the CPU) to float32 rounding."""
    from stages.guidance import vit

    assert vit.fused_attention(CUDA)
    gen = torch.Generator().manual_seed(0)
    x, b_in = torch.randn(5, 50, 768, generator=gen), torch.randn(2304, generator=gen)
    w_in = torch.randn(2304, 768, generator=gen) * 0.03
    w_out, b_out = torch.randn(768, 768, generator=gen) * 0.03, torch.randn(768, generator=gen)
    weight = torch.linspace(-1, 1, x.numel()).view_as(x)
    results = []
    for dev, dtype in (("cpu", torch.float64), ("cuda", torch.float32)):
        xi = x.to(dev, dtype).requires_grad_()
        with dispatched_ops() as names:
            y = vit.self_attention(xi, *(t.to(dev, dtype) for t in (w_in, b_in, w_out, b_out)), heads=12)
        assert any("scaled_dot_product" in name for name in names) == (dev == "cuda"), names
        (y * weight.to(dev, dtype)).sum().backward()
        results.append((y.detach().double().cpu(), xi.grad.double().cpu()))
    (y64, g64), (y32, g32) = results
    assert float((y32 - y64).norm() / y64.norm()) < 1e-5
    assert float((g32 - g64).norm() / g64.norm()) < 1e-5
