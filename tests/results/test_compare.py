"""Like with like: which cells the report compares, how variants are sorted against the reference,
the Pareto front per group against a brute-force dominance check, and figures that are split
into small multiples or not drawn, with the reason."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from stages.results.compare import (
    Group,
    comparison_groups,
    differing_keys,
    factor_label,
    is_ablation,
    trade_off,
)
from stages.results.figures import ablation_figures, loss_figures, robustness_figure, speed_accuracy_figures

BASE = {
    "optimize.iterations": 300,
    "optimize.milestones": [180, 255],
    "optimize.seed": 0,
    "optimize.checkpoint_every": 100,
    "optimize.specular": True,
    "optimize.normal_network": True,
    "optimize.material_encoding": "nerf",
    "optimize.normal_encoding": "nerf",
    "optimize.crops": 4,
    "optimize.light_rgb": True,
    "optimize.light_init": "tango",
    "optimize.light_lr": 0.02,
    "optimize.brdf": "gltf",
    "optimize.shadows": True,
    "bake.texture_size": 512,
}
#: what switches a component of TANGO off, written out here (not read from the code under test)
OFF = {
    "specular": False,
    "normal_network": False,
    "material_encoding": "none",
    "normal_encoding": "none",
    "crops": 0,
    "light_rgb": False,
    "light_init": "broad",
    "light_lr": None,
    "brdf": "tango",
    "shadows": False,
}


def with_(**changes):
    return {**BASE, **{f"optimize.{k}" if "." not in k else k: v for k, v in changes.items()}}


def row(mesh, prompt, variant, quality, seconds=100.0, name="target PSNR (dB)", test_only=False):
    return {
        "mesh": mesh,
        "prompt": prompt,
        "variant": variant,
        "quality": quality,
        "seconds": seconds,
        "quality_name": name,
        "test_only": test_only,
    }


def test_differing_keys_set_the_seed_aside():
    assert differing_keys(BASE, with_(seed=3, checkpoint_every=7)) == []
    assert differing_keys(BASE, with_(iterations=100, milestones=[60, 85])) == ["optimize.iterations", "optimize.milestones"]
    assert differing_keys(BASE, {k: v for k, v in BASE.items() if k != "bake.texture_size"}) == ["bake.texture_size"]
    assert differing_keys(BASE, with_(**{"bake.texture_size": 256})) == ["bake.texture_size"]


def test_a_setting_newer_than_a_cell_stands_for_its_default():
    """A cell made before a setting existed has no such key in its meta: it ran as that setting's
    default does, so it is the same configuration as a newer cell at the default (and a replicate
    of it) and differs from one that sets it; a key no settings class knows differs when missing."""
    older = {k: v for k, v in BASE.items() if k != "optimize.material_smooth"}
    assert differing_keys(older, with_(material_smooth=0.0)) == []
    assert differing_keys(with_(material_smooth=0.01), older) == ["optimize.material_smooth"]
    assert differing_keys(BASE, with_(**{"optimize.not_a_setting": 0.0})) == ["optimize.not_a_setting"]
    # a setting whose default changed after it was added stands for the value it was added with
    older_tilt = {k: v for k, v in BASE.items() if k != "optimize.normal_tilt"}
    assert differing_keys(older_tilt, with_(normal_tilt=0.0)) == []
    assert differing_keys(older_tilt, with_(normal_tilt=0.01)) == ["optimize.normal_tilt"]
    rows = [row("vase", "wood", "base", 29.0), row("vase", "wood", "base_seed1", 29.2)]
    settings = {("vase", "wood", "base"): older, ("vase", "wood", "base_seed1"): with_(seed=1, material_smooth=0.0)}
    (g,) = comparison_groups(rows, settings, ["base", "base_seed1"])
    assert g.configurations() == {"base": ["base", "base_seed1"]}


@pytest.mark.parametrize("switch", list(OFF))
def test_each_switch_off_is_an_ablation(switch):
    s = with_(**{switch: OFF[switch]})
    assert is_ablation(differing_keys(BASE, s), s)
    # the same key changed to something other than "off" is a sweep, not an ablation
    other = {"specular": True, "normal_network": True, "crops": 2, "light_rgb": True, "light_init": "spread"}
    other = {**other, "light_lr": 0.01, "brdf": "gltf", "shadows": True}.get(switch, "fourier")
    if other != BASE[f"optimize.{switch}"]:
        s2 = with_(**{switch: other})
        assert not is_ablation(differing_keys(BASE, s2), s2)


def test_ablation_needs_only_switches():
    both = with_(specular=False, normal_network=False)
    assert is_ablation(differing_keys(BASE, both), both)
    mixed = with_(specular=False, iterations=100)
    assert not is_ablation(differing_keys(BASE, mixed), mixed)
    assert not is_ablation([], BASE)  # the reference itself
    baked = with_(**{"bake.texture_size": 256})
    assert not is_ablation(differing_keys(BASE, baked), baked)


def test_the_ablation_config_variants_are_ablations_of_full():
    """config/ablations.yaml: every variant but ``full`` switches components off (the diffuse-only
    one names TANGO's BRDF, since glTF's layering has no diffuse-only form), so the report shows
    each as an ablation."""
    import yaml

    from stages.config.sections import OptimizeSettings

    variants = yaml.safe_load((Path(__file__).parents[2] / "config" / "ablations.yaml").read_text())["variants"]
    assert set(variants) > {"full", "no_spec_rough", "no_sharp_light", "tango_brdf", "no_shadows"}
    for name, v in variants.items():
        changes = v.get("optimize", {})
        OptimizeSettings(**changes)  # valid on the defaults
        s = with_(**changes)
        assert is_ablation(differing_keys(BASE, s), s) == (name != "full"), name


def test_factor_label():
    assert factor_label(["optimize.iterations", "optimize.milestones"]) == "iterations, milestones"
    assert factor_label(["bake.texture_size"]) == "bake.texture_size"
    assert factor_label([f"optimize.k{i}" for i in range(5)]) == "k0, k1, k2 +2 more"


def _cells_settings(variant_settings, meshes=("vase",), prompts=("wood",)):
    return {(m, p, v): s for m in meshes for p in prompts for v, s in variant_settings.items()}


VARIANTS = {
    "base": BASE,
    "base_seed1": with_(seed=1),
    "it100": with_(iterations=100, milestones=[60, 85]),
    "no_normal": with_(normal_network=False),
}


def test_groups_compare_only_like_with_like():
    """Never across meshes, prompts, quality measures or weight kinds."""
    settings = _cells_settings(VARIANTS, ("vase", "knot"), ("wood", "metal"))
    rows = [row(m, p, v, 20.0 + i) for i, (m, p, v) in enumerate(settings)]
    rows.append({**row("vase", "wood", "it100", 0.3, name="CLIP score (ViT-B-16/openai)"), "variant": "clip_cell"})
    settings[("vase", "wood", "clip_cell")] = BASE
    rows.append({**row("knot", "metal", "no_normal", 21.0, test_only=True), "variant": "tiny"})
    settings[("knot", "metal", "tiny")] = BASE
    rows.append({**row("knot", "metal", "base", None), "variant": "unmeasured"})
    groups = comparison_groups(rows, settings, [*VARIANTS, "clip_cell", "tiny", "unmeasured"])
    keys = [(g.mesh, g.prompt, g.quality_name, g.test_only) for g in groups]
    assert len(keys) == len(set(keys)) == 4 + 2
    for g in groups:
        for r in g.rows.values():
            assert (r["mesh"], r["prompt"], r["quality_name"], r["test_only"]) == (g.mesh, g.prompt, g.quality_name, g.test_only)
    assert not any("unmeasured" in g.rows for g in groups)


def test_replicates_factors_and_ablations():
    settings = _cells_settings(VARIANTS)
    rows = [row("vase", "wood", v, q) for v, q in zip(VARIANTS, (25.0, 25.4, 23.0, 24.0), strict=True)]
    (g,) = comparison_groups(rows, settings, list(VARIANTS))
    assert g.reference == "base"
    assert g.configurations() == {"base": ["base", "base_seed1"], "it100": ["it100"], "no_normal": ["no_normal"]}
    assert g.factor == {"base": "", "it100": "iterations, milestones", "no_normal": "normal_network"}
    assert g.ablations == ["no_normal"]
    mean, std, n = g.stats("quality")["base"]
    assert n == 2 and mean == pytest.approx(25.2)
    assert std == pytest.approx(math.sqrt(((25.0 - 25.2) ** 2 + (25.4 - 25.2) ** 2) / (2 - 1)))  # sample std
    # named ablations replace the automatic choice; another reference changes the factors
    (g,) = comparison_groups(rows, settings, list(VARIANTS), ablations=["it100"])
    assert g.ablations == ["it100"]
    (g,) = comparison_groups(rows, settings, list(VARIANTS), reference="it100")
    assert g.reference == "it100" and g.factor["base"] == "iterations, milestones" and g.ablations == []
    # without the reference in the group nothing is measured against it
    (g,) = comparison_groups([r for r in rows if r["variant"] != "base"], settings, list(VARIANTS))
    assert g.reference is None and g.ablations == [] and set(g.factor.values()) == {""}


def test_the_same_run_twice_is_not_a_seed_replicate():
    """Under a preset that already switches the normal network off, a no_normal variant is the
    reference again, seed included: left out, neither a replicate nor an ablation."""
    preset = with_(normal_network=False)
    settings = _cells_settings({"full": preset, "no_normal": preset, "full_seed1": {**preset, "optimize.seed": 1}})
    rows = [row("vase", "wood", v, q) for v, q in (("full", 25.0), ("no_normal", 25.0), ("full_seed1", 24.0))]
    (g,) = comparison_groups(rows, settings, ["full", "no_normal", "full_seed1"])
    assert g.duplicates == {"no_normal": "full"} and g.ablations == []
    assert g.configurations() == {"full": ["full", "full_seed1"]}
    assert g.stats("quality")["full"][2] == 2


def dominated(p, points) -> bool:
    """Brute force: another point at most as slow and at least as good, better in one."""
    return any(q[0] <= p[0] and q[1] >= p[1] and (q[0] < p[0] or q[1] > p[1]) for q in points if q is not p)


@pytest.mark.parametrize("seed", range(20))
def test_pareto_per_group_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 9))
    settings, rows = {}, []
    for i in range(n):
        s = with_(iterations=100 * (i + 1))
        for r in range(int(rng.integers(1, 4))):  # seed replicates
            v = f"v{i}_s{r}"
            settings[("m", "p", v)] = {**s, "optimize.seed": r}
            rows.append(row("m", "p", v, float(rng.normal(25, 2)), float(rng.uniform(10, 1000))))
    (g,) = comparison_groups(rows, settings, [r["variant"] for r in rows])
    out = trade_off(g)
    assert len(out) == n
    points = []
    for variants in g.configurations().values():
        members = [r for r in rows if r["variant"] in variants]
        points.append((float(np.mean([r["seconds"] for r in members])), float(np.mean([r["quality"] for r in members]))))
    for o, p in zip(out, points, strict=True):
        assert (o["seconds"], o["quality"]) == pytest.approx(p)
        assert o["pareto"] == (not dominated(p, points)), (o, points)
    # a knee only where the front bends (three points or more), and on the front
    assert sum(o["knee"] for o in out) == (1 if sum(o["pareto"] for o in out) >= 3 else 0)
    assert all(o["pareto"] for o in out if o["knee"])


def _groups(n_groups: int, n_confs: int, ablation: bool = False) -> list[Group]:
    variants = {"base": BASE, **{f"it{k}": with_(iterations=100 * k) for k in range(1, n_confs)}}
    if ablation:
        variants["no_spec"] = with_(specular=False)
    meshes = [f"m{i}" for i in range(n_groups)]
    settings = _cells_settings(variants, meshes)
    order = list(variants)
    rows = [row(m, p, v, 20.0 + order.index(v), 10.0 * (1 + order.index(v))) for (m, p, v) in settings]
    return comparison_groups(rows, settings, list(variants))


def test_figures_with_nothing_to_compare_say_why(tmp_path):
    single = _groups(3, 1)
    (sa,) = speed_accuracy_figures(tmp_path, single, 36)
    assert "file" not in sa and "single configuration" in sa["skipped"]
    (ab,) = ablation_figures(tmp_path, _groups(3, 3), 36)
    assert "file" not in ab and "no ablation variants" in ab["skipped"]
    (loss,) = loss_figures(tmp_path, tmp_path / "none", [("m0", "wood", "base")], 36)
    assert "no cell has a loss record" in loss["skipped"]
    (rob,) = robustness_figure(tmp_path, tmp_path, [("m0", "wood", "base")], {}, {}, {}, None)
    assert "no mesh of this experiment has a decimated version" in rob["skipped"]
    assert not list(tmp_path.glob("*.png"))


def test_robustness_figure_puts_every_level_beside_its_original(tmp_path):
    """Three decimated levels of one mesh in one figure, finest first, each tile with its quality
    and its relit figure beside the ceiling; a level without a row's cell stays blank, and a mesh
    whose levels ran nothing its original ran is said so, not drawn."""
    from PIL import Image

    from stages.results.figures import relit_text

    cells = [("lamp", p, "base") for p in ("wood", "brick")] + [("lamp_50", "wood", "base"), ("lamp_50", "brick", "base")]
    cells += [("lamp_5k", "wood", "base"), ("lamp_2k", "wood", "base"), ("horse", "wood", "base"), ("horse_2k", "brick", "base")]
    faces = {"lamp": 41160, "lamp_50": 20580, "lamp_5k": 5000, "lamp_2k": 2000, "horse": 43730, "horse_2k": 2000}
    decimated = {"lamp_2k": "lamp", "lamp_50": "lamp", "lamp_5k": "lamp", "horse_2k": "horse"}
    colours = {m: (40 * i, 200 - 30 * i, 90) for i, m in enumerate(faces)}

    def tile(cell, size):
        return Image.new("RGB", (size, size), colours[cell[0]])

    rows = {c: {"relit_psnr_scaled_db": [24.371, 22.1], "relit_ceiling_psnr_db": [25.26, 23.0]} for c in cells}
    rows[("lamp_2k", "wood", "base")] = {"relit_psnr_scaled_db": None}
    relit = {c: relit_text(r) for c, r in rows.items()}
    assert relit[("lamp", "wood", "base")] == "relit 24.37 | ceiling 25.26 dB" and relit[("lamp_2k", "wood", "base")] is None
    quality = dict.fromkeys(cells, "27.01 dB")
    lamp, horse = robustness_figure(tmp_path, tmp_path, cells, decimated, faces, quality, tile, relit)
    assert lamp["title"].endswith("lamp (41,160 faces) | lamp_50 (20,580 faces) | lamp_5k (5,000 faces) | lamp_2k (2,000 faces)")
    assert "ceiling" in lamp["caption"]
    assert "file" not in horse and "no prompt x variant ran on the original and a decimated version" in horse["skipped"]
    img = np.asarray(Image.open(tmp_path / lamp["file"]).convert("RGB"))
    size, head, label_w, under = 192, 40, 180, 30
    assert img.shape[:2] == (head + 2 * (size + under), label_w + 4 * size)
    for j, m in enumerate(("lamp", "lamp_50", "lamp_5k", "lamp_2k")):  # the wood row: every level
        assert tuple(img[head + size // 2, label_w + j * size + size // 2]) == colours[m]
    brick = head + size + under + size // 2  # the brick row: only the original and 50%
    assert tuple(img[brick, label_w + 2 * size + size // 2]) == (255, 255, 255)
    assert tuple(img[brick, label_w + size + size // 2]) == colours["lamp_50"]


def test_small_multiples_split_over_files(tmp_path):
    entries = speed_accuracy_figures(tmp_path, _groups(5, 3), panels=2)
    assert [e["file"] for e in entries] == ["speed_accuracy_1.png", "speed_accuracy_2.png", "speed_accuracy_3.png"]
    assert entries[0]["title"].endswith("(1 of 3)") and all((tmp_path / e["file"]).is_file() for e in entries)
    entries = ablation_figures(tmp_path, _groups(3, 2, ablation=True), panels=36)
    assert [e["file"] for e in entries] == ["ablations.png", "ablations_mean.png"]
    from PIL import Image

    w, h = Image.open(tmp_path / "ablations.png").size
    assert w > h  # three panels side by side, one row


def test_loss_curves_one_panel_per_mesh_and_prompt(tmp_path):
    cells = [(m, p, v) for m in ("a", "b") for p in ("wood",) for v in ("x", "y")]
    for m, p, v in cells:
        f = tmp_path / m / p / v / "optimize" / "loss.csv"
        f.parent.mkdir(parents=True)
        f.write_text("iteration,loss\n0,1.0\n10,0.5\n")
    (e,) = loss_figures(tmp_path / "out", tmp_path, cells, panels=36)
    assert e["file"] == "loss_curves.png" and (tmp_path / "out" / "loss_curves.png").is_file()
    entries = loss_figures(tmp_path / "out2", tmp_path, cells, panels=1)
    assert len(entries) == 2
    json.dumps(entries)  # figures.json material


def test_long_ids_wrap_in_panel_titles(tmp_path):
    from stages.results.figures import PANEL_TITLE_CHARS, panel_title

    long = "m" * 64 + " / " + "p" * 64 + " (variant_with_a_long_name)"
    lines = panel_title(long).split("\n")
    assert len(lines) >= 4 and all(len(line) <= PANEL_TITLE_CHARS for line in lines)
    assert "".join(lines).replace(" ", "") == long.replace(" ", "")
    assert panel_title("vase / wood") == "vase / wood"
