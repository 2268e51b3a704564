"""Lighting as the scene requires (``light_prune_after``, the issue's ``light_lobes: auto``):
negligible lobes are found by their energy, dropping them removes exactly their radiance, the
optimiser's moments follow the kept lobes, a killed run resumes to the same field whether its last
checkpoint was before or after the pruning, and the later stages load the pruned field."""

from __future__ import annotations

import json
import math

import pytest
import torch
from test_optimize import TINY

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core.provenance import Timer
from stages.geometry.raycache import RayCache
from stages.model.checkpoint import load_field
from stages.model.lights.sg import LIGHT_PARAMETERS, SGLightModule
from stages.render.sg import sg_integral
from stages.render.shading import SGLight, diffuse_radiance
from stages.training.optimizer import Optimizer


def _light_with_dim_lobes() -> SGLightModule:
    """8 lobes; lobes 1, 4 and 6 carry 1e-4 of the others' energy."""
    light = SGLightModule(8)
    with torch.no_grad():
        light.log_energy[[1, 4, 6]] += math.log(1e-4)
    return light


def test_negligible_lobes_by_energy_and_dropping_removes_exactly_their_radiance():
    light = _light_with_dim_lobes()
    small = light.negligible(0.01)
    assert small.tolist() == [False, True, False, False, True, False, True, False]
    # energy share written out from the SG integral 2 pi a / lam (1 - exp(-2 lam))
    full = light()
    e = 2 * torch.pi * full.amplitude / full.sharpness * (1 - torch.exp(-2 * full.sharpness))
    torch.testing.assert_close(e, sg_integral(full.sharpness, full.amplitude))
    assert ((e / e.sum(0))[small] < 0.01).all() and ((e / e.sum(0))[~small] > 0.01).all()
    # shading is linear in the lobes: all = kept + dropped, so the change is the dropped lobes' radiance
    n = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    albedo = torch.full((500, 3), 0.8)
    before = diffuse_radiance(n, albedo, full)
    dropped = SGLight(full.axis[small], full.sharpness[small], full.amplitude[small])
    kept_index = torch.nonzero(~small).flatten()
    pairs = light.keep(kept_index)
    assert light.lobes == 5 and all(old is not new for old, new in pairs)
    torch.testing.assert_close(
        before - diffuse_radiance(n, albedo, light()), diffuse_radiance(n, albedo, dropped), rtol=1e-5, atol=1e-7
    )
    # the brightest lobe always stays, even when every lobe is below the share
    equal = SGLightModule(8)
    assert int((~equal.negligible(0.5)).sum()) == 1


def test_pruning_carries_the_optimiser_moments(cache):
    """Lobes 1, 4 and 6 dimmed after two steps: pruning keeps 0, 2, 3, 5 and 7, and each kept
    lobe keeps its own AdamW moments (not a prefix of the old ones); the run goes on."""
    s = OptimizeSettings(iterations=4, **TINY)
    opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase made of wood", "cpu")
    for _ in range(2):
        opt.step(Timer())
    light = opt.field.light.sg
    with torch.no_grad():
        light.log_energy[[1, 4, 6]] += math.log(1e-4)
    before = {name: {k: v.clone() for k, v in opt.adamw.state[getattr(light, name)].items()} for name in LIGHT_PARAMETERS}
    assert opt.prune_light() == 3
    assert opt.light_pruned == {"iteration": 2, "kept": 5, "dropped": 3} and light.lobes == 5
    kept = torch.tensor([0, 2, 3, 5, 7])
    for name, moments in before.items():
        new = opt.adamw.state[getattr(light, name)]
        for k in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(new[k], moments[k][kept], rtol=0, atol=0, msg=f"{name} {k}")
        torch.testing.assert_close(new["step"], moments["step"])
    params = list(opt.field.parameters())
    grouped = opt.adamw.param_groups[0]["params"] + opt.adamw.param_groups[1]["params"]
    assert all(any(p is q for q in grouped) for p in params)
    assert len(grouped) == len(params)
    assert all(any(p is q for q in opt.adamw.param_groups[1]["params"]) for p in light.parameters())
    row = opt.step(Timer())
    assert row["light_lobes"] == 5 and torch.isfinite(torch.tensor(row["loss"]))


@pytest.mark.parametrize("killed_at", [5, 7])
def test_kill_and_resume_across_the_pruning(cache, tmp_path, killed_at):
    """Pruning at 4, checkpoints every 3: killed at 5 the resumed run starts before the pruning
    (from 3), killed at 7 after it (from 6, a checkpoint with fewer lobes); both end equal to an
    uninterrupted run, and every later file has the pruned light."""
    s = OptimizeSettings(iterations=8, checkpoint_every=3, light_prune_after=4, light_prune_share=0.2, **TINY)
    args = (cache / "train.npz", cache / "eval.npz", "a vase")
    ref = optimize.run(*args, tmp_path / "ref", s, "cpu")
    assert ref["light_lobes"] == 1 and ref["light_pruned"] == {"iteration": 4, "kept": 1, "dropped": 7}
    out = tmp_path / "killed"
    optimize.run(*args, out, s, "cpu", stop_after=killed_at)
    resumed = optimize.run(*args, out, s, "cpu")
    assert resumed["resumed_from_iteration"] == 3 * (killed_at // 3)
    assert resumed["light_pruned"] == ref["light_pruned"]
    a = torch.load(tmp_path / "ref" / "field.pt", weights_only=True)["state_dict"]
    b = torch.load(out / "field.pt", weights_only=True)["state_dict"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    field, _ = load_field(out / "field.pt")  # what bake, relight, metrics and lod do
    assert field.light.lobes == 1
    meta = json.loads((out / "meta.json").read_text())
    assert meta["light_lobes"] == 1
    rows = (out / "loss.csv").read_text().splitlines()
    header = rows[0].split(",")
    lobes = [int(r.split(",")[header.index("light_lobes")]) for r in rows[1:]]
    assert lobes == [8, 8, 8, 8, 1, 1, 1, 1]
