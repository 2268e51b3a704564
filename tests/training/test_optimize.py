"""The optimisation loop: a step changes the parameters, kill-and-resume equals an uninterrupted
run, ablations build less, outputs and metadata, and image-target recovery (>= 30 dB)."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
from conftest import THREADS

from stages import optimize
from stages.config.layout import OPTIMIZE_FILES
from stages.config.sections import SPECULAR_LOBES, OptimizeSettings
from stages.core.device import bf16_support
from stages.core.provenance import Timer
from stages.geometry.raycache import RayCache
from stages.model.checkpoint import load_field
from stages.model.field import StyleField
from stages.testing.recovery import MITSUBA_TARGET, fit_mitsuba, mitsuba_scene, recover_mitsuba, recover_sg
from stages.training.optimizer import Optimizer

TINY = dict(
    clip_tiny_test=True,
    image_size=64,
    width=32,
    crops=2,
    light_lobes=8,
    eval_width=32,
    material_frequencies=4,
)


def params(module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def test_one_clip_step_changes_parameters(cache):
    opt = Optimizer(OptimizeSettings(iterations=1, **TINY), RayCache(cache / "train.npz"), "a vase made of wood", "cpu")
    before = params(opt.field)
    row = opt.step(Timer())
    after = params(opt.field)
    changed = [k for k in before if not torch.equal(before[k], after[k])]
    assert any(k.startswith("svbrdf") for k in changed)
    assert any(k.startswith("normal_net") for k in changed)
    assert any(k.startswith("light") for k in changed)
    assert math.isfinite(row["loss"]) and -2 <= row["loss"] <= 2
    # only the pixels the images need were shaded: global 64x64 plus two crops of at most 64x64
    assert 0 < row["points"] <= 3 * 64 * 64


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_a_non_finite_gradient_stops_the_step_before_it_reaches_the_parameters(cache, bad):
    """A NaN (or an infinity) in one lobe's gradient (from a hook on the light's sharpness) raises a clear error naming
    the step and the parameter, and the parameters and the optimiser's state stay as they were: a NaN
    that reached them would spread to every later step and checkpoint."""
    opt = Optimizer(OptimizeSettings(iterations=3, **TINY), RayCache(cache / "train.npz"), "a vase", "cpu")
    opt.step(Timer())
    before, state = params(opt.field), json.dumps(str(opt.adamw.state_dict()["state"]))
    hook = opt.field.light.sg.log_sharpness.register_hook(lambda g: g.index_fill(0, torch.tensor([0]), bad))
    with pytest.raises(FloatingPointError, match=r"step 2: the gradient of light\.sg\.log_sharpness is not finite"):
        opt.step(Timer())
    hook.remove()
    after = params(opt.field)
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert json.dumps(str(opt.adamw.state_dict()["state"])) == state and opt.iteration == 1
    assert math.isfinite(opt.step(Timer())["loss"])  # the next step, with a finite gradient, runs


def test_kill_and_resume_matches_uninterrupted_run(cache, tmp_path):
    s = OptimizeSettings(iterations=8, checkpoint_every=3, background="noise", **TINY)
    ref = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", tmp_path / "ref", s, "cpu")
    # a run that dies after 5 iterations (its last checkpoint is at 3), then a rerun
    out = tmp_path / "killed"
    assert optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", out, s, "cpu", stop_after=5) == {"stopped_at": 5}
    assert (out / "checkpoint.pt").is_file() and not (out / "meta.json").exists()
    resumed = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", out, s, "cpu")
    assert resumed["resumed_from_iteration"] == 3  # the last checkpoint before the kill
    a = torch.load(tmp_path / "ref" / "field.pt", weights_only=True)["state_dict"]
    b = torch.load(out / "field.pt", weights_only=True)["state_dict"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    assert not (out / "checkpoint.pt").exists()
    assert ref["final_similarity"] == pytest.approx(resumed["final_similarity"], abs=1e-6)


def test_a_checkpoint_of_the_unfused_optimiser_resumes_fused_to_the_same_step(cache):
    """A checkpoint written before AdamW was fused (its groups say ``fused: None``) resumes fused,
    and its next step gives the parameters the one from the same checkpoint marked fused gives."""
    s = OptimizeSettings(iterations=4, **TINY)
    opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase", "cpu")
    opt.step(Timer())
    state = copy.deepcopy(opt.state())
    old = copy.deepcopy(state)
    old["optimizer"]["param_groups"] = [{**g, "fused": None} for g in old["optimizer"]["param_groups"]]
    after = []
    for saved in (state, old):
        resumed = Optimizer(s, RayCache(cache / "train.npz"), "a vase", "cpu")
        resumed.load(saved)
        assert all(g["fused"] for g in resumed.adamw.param_groups)
        resumed.step(Timer())
        after.append(params(resumed.field))
    for k in after[0]:
        torch.testing.assert_close(after[1][k], after[0][k], rtol=0, atol=0, msg=k)


def test_hash_grid_run_trains_its_tables_and_resumes_bit_identical(cache, tmp_path):
    """Hash-grid encodings (``material_encoding``/``normal_encoding: hashgrid``) through the real
    stage: the tables learn (the scatter-add of their gradient reaches the optimiser), the
    checkpoint carries them and a killed run resumes to the same tables bit for bit."""
    hg = {**TINY, "material_encoding": "hashgrid", "normal_encoding": "hashgrid", "hashgrid_log2_size": 12}
    s = OptimizeSettings(iterations=5, checkpoint_every=2, **hg)
    opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase", "cpu")
    before = params(opt.field)
    opt.step(Timer())
    after = params(opt.field)
    for key in ("svbrdf.encoding.raw", "normal_net.encoding.raw"):
        moved = (after[key] - before[key]).abs()
        assert 0 < int((moved > 0).sum()) < moved.numel(), key  # the touched entries, not the whole table
    ref = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", tmp_path / "ref", s, "cpu")
    out = tmp_path / "killed"
    assert optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", out, s, "cpu", stop_after=3) == {"stopped_at": 3}
    resumed = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", out, s, "cpu")
    assert resumed["resumed_from_iteration"] == 2 and ref["settings"]["material_encoding"] == "hashgrid"
    a = torch.load(tmp_path / "ref" / "field.pt", weights_only=True)["state_dict"]
    b = torch.load(out / "field.pt", weights_only=True)["state_dict"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


def test_checkpoint_from_other_settings_is_not_resumed(cache, tmp_path):
    s = OptimizeSettings(iterations=4, checkpoint_every=2, **TINY)
    optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", tmp_path, s, "cpu", stop_after=3)
    other = OptimizeSettings(iterations=4, checkpoint_every=2, **{**TINY, "width": 16})
    meta = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", tmp_path, other, "cpu")
    assert meta["resumed_from_iteration"] is None


def test_outputs_and_metadata(cache, tmp_path):
    s = OptimizeSettings(iterations=3, **TINY)
    optimize.run(cache / "train.npz", cache / "eval.npz", "a vase made of wood", tmp_path, s, "cpu")
    for name in OPTIMIZE_FILES.values():
        assert (tmp_path / name).is_file(), name
    saved = json.loads((tmp_path / "meta.json").read_text())
    assert saved["test_only_weights"] is True and "TEST ONLY" in saved["weights"]
    assert saved["prompt"] == "a vase made of wood" and saved["seed"] == 0
    assert "final_similarity" in saved and len(saved["final_similarity_per_view"]) == 8
    assert saved["versions"]["torch"] and saved["timings_s"]["loop"] > 0
    rows = (tmp_path / "loss.csv").read_text().splitlines()
    assert rows[0].startswith("iteration") and len(rows) == 4
    points = [int(float(r.split(",")[rows[0].split(",").index("points")])) for r in rows[1:]]
    assert saved["points_per_iteration"] == pytest.approx(sum(points) / 3) and len(set(points)) > 1, points  # the mean
    light = np.load(tmp_path / "light.npz")
    assert light["equirect"].shape == (128, 256, 3) and (light["equirect"] > 0).all()
    field, settings = load_field(tmp_path / "field.pt")
    assert settings == s and isinstance(field, StyleField)
    # a field.pt written before specular_lobe and shading_normals existed is rebuilt as it was
    # trained (TANGO's isotropic lobe, flat normals, TANGO's BRDF), not with today's defaults
    s_tango = OptimizeSettings(iterations=3, brdf="tango", **TINY)
    optimize.run(cache / "train.npz", cache / "eval.npz", "a vase made of wood", tmp_path / "tango", s_tango, "cpu")
    data = torch.load(tmp_path / "tango" / "field.pt", weights_only=True)
    for key in ("specular_lobe", "shading_normals", "brdf"):
        del data["settings"][key]
    torch.save(data, tmp_path / "old.pt")
    old_field, old = load_field(tmp_path / "old.pt")
    assert (old.specular_lobe, old.shading_normals, old.brdf) == ("isotropic", "flat", "tango")
    assert (old_field.specular_lobe, old_field.normals.mode) == ("isotropic", "flat")
    from PIL import Image

    sheet = Image.open(tmp_path / "renders" / "rgb.png")
    assert sheet.size == (4 * 32, 2 * 32)


def test_specular_lobe_reaches_every_render_of_the_field():
    """``specular_lobe`` is a setting of the field: its forward pass (training, metrics, relighting,
    the bake's reference) shades with that model; an unknown name fails in the settings."""
    from stages.core.errors import ConfigError
    from stages.render.brdf import TANGO

    g = torch.Generator().manual_seed(3)
    points = torch.rand(64, 3, generator=g) - 0.5
    normals = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    view = torch.nn.functional.normalize(normals + 0.5 * torch.randn(64, 3, generator=g), dim=-1)
    specular = {}
    for lobe in SPECULAR_LOBES:
        field = StyleField(OptimizeSettings(width=16, specular_lobe=lobe, brdf="tango").field_settings())
        with torch.no_grad():
            out = field(points, normals, view)
            want = TANGO.shade(out.normal, view, out.material, field.light.sg(), lobe)
        torch.testing.assert_close(out.shading.specular, want.specular, rtol=0, atol=0)
        specular[lobe] = out.shading.specular
    for lobe in SPECULAR_LOBES[1:]:  # the same weights, different models
        assert not torch.allclose(specular["isotropic"], specular[lobe]), lobe
    with pytest.raises(ConfigError, match="specular_lobe"):
        OptimizeSettings(specular_lobe="asg")


def test_shading_normals_reach_every_view_of_the_field(cache):
    """``shading_normals`` is a setting of the field, and every ViewStore built for it (training,
    metrics, relighting, the bake's reference) serves its normals: smooth ones are the corner
    normals interpolated at the hits, turned to the side of the face the viewer sees and never
    facing away from the eye; flat ones are the face normals, turned the same way."""
    from stages.core.errors import ConfigError
    from stages.imaging.views import ViewStore

    rc = RayCache(cache / "eval.npz")
    a = rc.arrays
    served = {}
    for mode in ("flat", "smooth"):
        field = StyleField(OptimizeSettings(width=16, shading_normals=mode).field_settings())
        assert field.normals.mode == mode
        store = ViewStore(rc, "cpu", field.normals)
        v, h = store[1], rc.view(1, field.normals)
        n, view = v.normals.numpy(), v.view.numpy()
        assert np.isfinite(n).all() and ((n * view).sum(1) >= 5e-4 - 1e-6).all()
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
        # the side: the face normal's, whatever the shading normal does near a silhouette
        side = np.sign((h.face_normal * view).sum(1))
        assert ((n * h.face_normal).sum(1) * side > 0).all()
        served[mode] = n
    # written out here: corner normals interpolated with the cached barycentrics
    lo, hi = a["offsets"][1], a["offsets"][2]
    face = a["face"][lo:hi]
    uv = a["bary"][lo:hi].astype(np.float64) / 65535.0
    corners = rc.corner_normals(StyleField(OptimizeSettings(width=16, shading_normals="smooth").field_settings()).normals)
    c = corners[face].astype(np.float64)
    mixed = (1 - uv[:, :1] - uv[:, 1:]) * c[:, 0] + uv[:, :1] * c[:, 1] + uv[:, 1:] * c[:, 2]
    mixed /= np.linalg.norm(mixed, axis=1, keepdims=True)
    view = -rc.view(1).direction
    mixed *= np.sign((a["face_normals"][face] * view).sum(1))[:, None]
    inside = (mixed * view).sum(1) > 1e-3  # where face_viewer leaves the normal alone
    np.testing.assert_allclose(served["smooth"][inside], mixed[inside], atol=1e-5)
    assert np.degrees(np.arccos(np.clip((served["smooth"] * served["flat"]).sum(1), -1, 1))).mean() > 0.5
    with pytest.raises(ConfigError, match="shading_normals"):
        OptimizeSettings(shading_normals="phong")
    with pytest.raises(ConfigError, match="crease_angle_deg"):
        OptimizeSettings(crease_angle_deg=200.0)


def test_switched_off_parts_are_not_built():
    full = StyleField(OptimizeSettings(width=32).field_settings())
    plain = StyleField(
        OptimizeSettings(
            width=32, normal_network=False, specular=False, brdf="tango", material_encoding="none", crops=0
        ).field_settings()
    )
    assert full.normal_net is not None and plain.normal_net is None
    assert plain.svbrdf.specular is None and plain.svbrdf.roughness is None
    assert sum(p.numel() for p in plain.parameters()) < 0.4 * sum(p.numel() for p in full.parameters())
    no_delta = StyleField(OptimizeSettings(width=32, normal_max_delta=0.0).field_settings())
    assert no_delta.normal_net is None


#: floors of the Mitsuba recovery test, below the figures measured on 2026-11-22
#: (measured: 21.4 dB, SSIM 0.695, albedo RMSE 0.265 after its scale, roughness MAE 0.256)
RECOVERY_MITSUBA_PSNR_DB = 20.0
RECOVERY_MITSUBA_SSIM = 0.65
RECOVERY_MITSUBA_ALBEDO_RMSE = 0.32
#: 0.32 until 2026-11-24; with the light that can sharpen the vase's roughness MAE rose from 0.28 to
#: 0.32-0.34 for every sharp-light setting measured (the light takes part of the wood's sheen) while
#: its PSNR held (21.8 to 22.1 dB) and the metal's rose by 4.7 dB (docs/measurements/light-brdf.md)
RECOVERY_MITSUBA_ROUGHNESS_MAE = 0.36

#: the tests' shorter schedule of the same fit (150 iterations; the benchmark keeps 300): measured
#: 2026-11-25 on the development machine: the representable SG case 34.27 dB (36.70 at 300), the
#: unrepresentable light 30.32 dB (33.12 at 200), Mitsuba's vase 27.36 dB in float32 and 27.37 dB
#: in bfloat16 networks, each fit 30-34 s instead of 60-70 s
SHORT = {"iterations": 150, "milestones": (90, 128)}


@pytest.mark.slow(minutes=1)
def test_image_target_recovery_representable_target(tmp_path):
    """The easy case, kept as a regression check of the optimisation: the target's light (4 SG
    lobes) and flat normals are exactly representable by the model (16 lobes, no normal network),
    and the target is rendered by our own renderer. PSNR over object pixels of the held-out
    evaluation views only, after the tests' 150 iterations (:data:`SHORT`; measured 2026-11-25:
    34.27 dB, 45 s on an idle 2-core machine)."""
    meta = recover_sg(tmp_path, threads=THREADS, **SHORT)
    assert meta["eval_psnr_db"] >= 32.0
    assert meta["eval_psnr_pixels"].startswith("object pixels")
    assert meta["weights"].startswith("image targets") and meta["origin"]["image_guided"]
    assert (tmp_path / "out" / "renders" / "target.png").is_file()


@pytest.mark.slow(minutes=1)
def test_image_target_recovery_unrepresentable_light(tmp_path):
    """A target the model cannot represent exactly: the `sky` light (a 1.5-degree sun, a graded
    sky and a ground: 97 lobes) against a model of 16 lobes, with the normal network on (free to
    tilt the normals away from the target's flat ones). Object pixels only, after the tests' 150
    iterations (measured 2026-11-25: 30.32 dB, 4 dB below the representable case, 52 s)."""
    meta = recover_sg(tmp_path, threads=THREADS, target_light="sky", normal_network=True, **SHORT)
    assert meta["eval_psnr_db"] >= 28.0
    assert "under the sky SG light" in meta["origin"]["weights"]


@pytest.mark.slow(minutes=1.5)
def test_image_target_recovery_on_mitsuba_ground_truth(tmp_path):
    """The judge nobody here wrote: Mitsuba path-traces the vase in a principled wood with a
    normal map under a sun and sky (shadows, interreflection, a disc no SG sum represents). The
    fit (normal network on) is graded on the held-out metric views over fully covered object
    pixels, and the recovered material against the ground truth. Thresholds sit below the
    figures measured 2026-11-22 (see README, "Recovery on Mitsuba targets").

    Fitted twice on the same targets, with the networks in float32 and in bfloat16 (the default
    where the CPU has it natively, ``bf16_networks: auto``): both meet every threshold and their
    held-out PSNRs differ by at most 0.3 dB (measured 2026-11-25 on this scene at 300 iterations:
    29.03 dB float32, 28.99 dB bfloat16, docs/measurements/speed.md; at the tests' 150, :data:`SHORT`:
    27.36 and 27.37 dB, SSIM 0.83, albedo RMSE 0.136 after its scale, roughness MAE 0.284). Without
    native bfloat16 the second fit is the float32 one again and only the first is checked (auto runs
    float32 there)."""
    scene = mitsuba_scene(tmp_path, target=MITSUBA_TARGET)
    runs = {"float32": fit_mitsuba(scene, "fp32", threads=THREADS, normal_network=True, bf16_networks="off", **SHORT)}
    if bf16_support(torch.device("cpu"))[0]:
        runs["bfloat16"] = fit_mitsuba(scene, "bf16", threads=THREADS, normal_network=True, bf16_networks="on", **SHORT)
        assert runs["bfloat16"]["optimize"]["network_precision"].startswith("bfloat16 autocast")
    for r in runs.values():
        it = r["metrics"]
        assert it["weights"].startswith("image targets: Mitsuba 3")
        assert r["optimize"]["origin"]["image_guided"] and "Mitsuba 3" in r["optimize"]["origin"]["label"]
        assert it["psnr_db"] >= RECOVERY_MITSUBA_PSNR_DB and it["ssim"] >= RECOVERY_MITSUBA_SSIM
        assert it["target_noise_psnr_db"] > it["psnr_db"] + 3.0  # the targets' own noise is not what limits the figure
        mat = it["material"]
        assert mat["albedo_rmse_scaled"] < RECOVERY_MITSUBA_ALBEDO_RMSE
        assert mat["roughness_mae"] < RECOVERY_MITSUBA_ROUGHNESS_MAE
        assert all(0.3 < r_ < 3.0 for r_ in mat["light_energy_ratio"])
        assert "eval_psnr_db" not in r["optimize"]  # Mitsuba targets exist for training and metric views only
        # the training light's ceiling beside the figure, on the same pixels (the targets' own environment)
        ceiling = it["ceiling"]
        assert ceiling["environment"] == "builtin:sun_sky" and ceiling["pixels"] > 1000
        assert 15.0 < ceiling["ceiling_psnr_db"] < 60.0 and 15.0 < ceiling["recovered_psnr_db"] < 60.0
    psnr = {k: r["metrics"]["psnr_db"] for k, r in runs.items()}
    assert max(psnr.values()) - min(psnr.values()) <= 0.3, psnr


@pytest.mark.slow(minutes=1)
def test_metal_recovers_its_highlight_on_mitsuba_ground_truth(tmp_path):
    """The brushed-metal candle under Mitsuba's sun and sky: the sun's highlight is in every
    target view, and the recovered views show it. Over the brightest 1% of the target's object
    pixels of the held-out views (saturated white there), the recovered render reaches at least
    0.8 on average. Measured 2026-11-24 with these settings: 0.89 with the light's defaults
    (light_init tango, light_lr 0.02; 20.9 dB), 0.51 at the networks' rate from broad lobes (the
    light as it was: every lobe ended near sharpness 2; 16.1 dB)."""
    r = recover_mitsuba(
        tmp_path, mesh="builtin:candle", material="metal", target=MITSUBA_TARGET, threads=THREADS, normal_network=True
    )
    h = r["metrics"]["highlights"]
    assert h["target"] > 0.95
    assert h["recovered_at_target"] >= 0.8, h


@pytest.mark.parametrize("limit", [4, 7, 64])
def test_the_loss_history_stays_bounded_and_evenly_spaced(limit):
    """A run of any length keeps at most ``limit`` history rows (each checkpoint stores them all):
    the rows kept are those at iterations 1 + k * stride, stride the smallest power of two that
    fits, and recording in two halves (a resumed run) keeps the same rows."""
    from stages.training.optimizer import keep_history

    for iterations in (1, limit, limit + 1, 5 * limit + 3, 1000):
        history, stride = [], 1
        for it in range(1, iterations + 1):
            stride = keep_history(history, stride, {"iteration": it}, limit)
            assert len(history) <= limit
        expected_stride = 1
        while len(range(1, iterations + 1, expected_stride)) > limit:
            expected_stride *= 2
        assert stride == expected_stride
        assert [r["iteration"] for r in history] == list(range(1, iterations + 1, expected_stride))
        halves, s2 = [], 1
        for it in range(1, iterations + 1):
            s2 = keep_history(halves, s2, {"iteration": it}, limit)
            if it == iterations // 2:
                halves, s2 = [dict(r) for r in halves], int(s2)  # a checkpoint's copy, resumed
        assert halves == history and s2 == stride
