"""One bounce while training (optimize.bounces): decided by the training views' measured
self-occlusion, the table refreshed from the field, kept in its state and files, and what a
loaded field renders; the component module's place among the light's kinds."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from stages import optimize
from stages.config.sections import NormalizeSettings, OptimizeSettings, RaycacheSettings
from stages.geometry.meshio import save_ply
from stages.geometry.normalization import normalize_mesh
from stages.geometry.normals import NormalSpec
from stages.geometry.raycache import RayCache
from stages.imaging.views import ViewStore
from stages.model.bounce import FaceSides, bounce_table, field_shading, resolve_bounces
from stages.model.checkpoint import load_field
from stages.model.field import StyleField
from stages.model.lights import BounceModule, LightModule, SGLightModule
from stages.raycache import run as raycache_run

TINY = dict(clip_tiny_test=True, image_size=64, width=32, crops=2, light_lobes=8, eval_width=32, material_frequencies=4)


@pytest.fixture(scope="module")
def knot(tmp_path_factory):
    """The built-in knot (it shades itself), normalised, with a small ray cache with visibility."""
    d = tmp_path_factory.mktemp("knot")
    save_ply(d / "knot.ply", normalize_mesh("builtin:knot", NormalizeSettings()).mesh)
    rc = RaycacheSettings(
        views=4, resolution=64, eval_azimuths=4, eval_elevations_deg=(0.0, 30.0), eval_resolution=48, visibility="on"
    )
    raycache_run(d / "knot.ply", d / "train.npz", d / "eval.npz", d / "meta.json", rc)
    return d


def _views(path, shadows: bool = True) -> ViewStore:
    return ViewStore(RayCache(path), torch.device("cpu"), NormalSpec("flat"), shadows=shadows)


def test_auto_models_a_bounce_where_the_mesh_blocks_its_own_light(knot, cache):
    """The knot: half its training hits see more than 5% of their hemisphere blocked (auto: 1);
    the vase, seen mostly from outside: the median is 0 (auto: 0); no shadows: 0, and 1 asked for
    without them says what to set."""
    count, record = resolve_bounces("auto", _views(knot / "train.npz"), 0.05)
    assert count == 1 and record["blocked_median"] > 0.05 and "median" in record["why"]
    count, record = resolve_bounces("auto", _views(cache / "train.npz"), 0.05)
    assert count == 0 and record["blocked_median"] < 0.05
    assert resolve_bounces("auto", _views(knot / "train.npz", shadows=False), 0.05)[0] == 0
    with pytest.raises(ValueError, match="optimize.shadows: true and raycache.visibility: on"):
        resolve_bounces(1, _views(knot / "train.npz", shadows=False), 0.05)
    off = resolve_bounces(0, _views(knot / "train.npz", shadows=False), 0.05)
    assert off == (0, {"setting": 0, "bounces": 0, "blocked_median": None})


def test_the_bounce_adds_light_where_the_knot_sees_itself(knot):
    """A field's render of the knot's training views with its bounce refreshed: at least as
    bright everywhere, brighter where the mesh blocks part of the hemisphere; the table holds
    every face side, none negative; nothing added before the first refresh."""
    s = OptimizeSettings(bounces=1, **TINY).field_settings()
    field = StyleField(s).eval()
    views = _views(knot / "train.npz")
    v = views[0]
    before = v.shade(field).shading.rgb
    senders = FaceSides(views.cache.mesh(), views.cache.visibility_directions)
    field.light.bounce.set_table(bounce_table(senders, field_shading(field, senders, "cpu"), field.light(), 16).table)
    table = field.light.bounce.table
    assert table.shape == (2 * len(views.cache.mesh().faces), 3) and bool((table >= 0).all()) and float(table.max()) > 0
    after = v.shade(field).shading.rgb
    gain = (after - before).sum(-1)
    blocked = torch.from_numpy(v.shadows.blocked_share())
    assert bool((gain >= -1e-6).all())
    assert float(gain[blocked > 0.2].mean()) > 10 * float(gain[blocked == 0].mean() + 1e-9)


def test_an_optimisation_with_a_bounce_writes_and_reloads_it(knot, tmp_path):
    """optimize with ``bounces: 1``: the table refreshed at the first step (and every
    bounce_every, and once more at the end: the field is saved with its last material's), recorded in
    meta.json; the field file holds it and a loaded field renders
    with it; light.npz carries it."""
    s = OptimizeSettings(iterations=3, bounces=1, bounce_every=2, **TINY)
    meta = optimize.run(knot / "train.npz", knot / "eval.npz", "a knot", tmp_path, s, "cpu")
    assert [c["kind"] for c in meta["light_components"]] == ["sg", "bounce"]
    written = json.loads((tmp_path / "meta.json").read_text())
    assert written["bounces"]["bounces"] == 1 and written["bounces"]["refreshes"] == 3  # steps 0 and 2, and the end
    field, settings = load_field(tmp_path / "field.pt")
    assert settings.bounces == 1
    table = field.light.bounce.table
    mesh = RayCache(knot / "train.npz").mesh()
    assert table.shape == (2 * len(mesh.faces), 3) and float(table.max()) > 0
    with np.load(tmp_path / "light.npz") as z:
        np.testing.assert_array_equal(z["bounce_table"], table.numpy())


def test_a_known_light_fits_around_the_bounce():
    """A light with a bounce holds a map as one without: the same SG lobes (the bounce fits
    nothing and takes nothing of the map), its table still empty, its energy none."""
    torch.manual_seed(0)
    plain = LightModule([SGLightModule(4)])
    torch.manual_seed(0)
    bounced = LightModule([SGLightModule(4), BounceModule(8)])
    assert plain.hold("builtin:sunset", iterations=20) == bounced.hold("builtin:sunset", iterations=20)
    for (name, a), b in zip(plain.sg.named_parameters(), bounced.sg.parameters(), strict=True):
        torch.testing.assert_close(a, b, msg=name)
    assert bounced.bounce.table.shape == (0, 3)
    assert torch.equal(bounced().components[1].energy(), torch.zeros(3))


def test_a_resumed_run_takes_its_table(knot):
    """A checkpoint holds the bounce's table (its size the mesh's face sides): a run resumed from
    it renders with it before its next refresh."""
    from stages.core.provenance import Timer
    from stages.training.optimizer import Optimizer

    s = OptimizeSettings(iterations=4, bounces=1, bounce_every=3, **TINY)
    first = Optimizer(s, RayCache(knot / "train.npz"), "a knot", "cpu")
    first.step(Timer())
    state = first.state()
    again = Optimizer(s, RayCache(knot / "train.npz"), "a knot", "cpu")
    again.load(state)
    torch.testing.assert_close(again.field.light.bounce.table, first.field.light.bounce.table)
    assert again.field.light.bounce.table.shape[0] == 2 * len(RayCache(knot / "train.npz").mesh().faces)
