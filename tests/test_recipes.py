"""CONTRIBUTING.md's recipes, each followed for a toy: a constant BRDF, a constant light, a
guidance whose loss is zero and an export format that writes a text file, each added in a
temporary registry in only the files its recipe names, then run through the stages of the
smallest workflow (ray cache, optimise, bake, export) in this process."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from stages import bake, export, optimize
from stages.config.brdfs import BRDFS
from stages.config.guidance_modes import GUIDANCE_MODES
from stages.config.sections import BakeSettings, ExportSettings, NormalizeSettings, OptimizeSettings, RaycacheSettings
from stages.geometry.meshio import save_ply
from stages.geometry.normalization import normalize_mesh
from stages.guidance import objective
from stages.model.checkpoint import load_field
from stages.raycache import run as raycache_run
from stages.render import brdf as brdfs
from stages.render.shading import Shading, diffuse_radiance

REPO = Path(__file__).resolve().parents[1]
SMALL = {"iterations": 2, "clip_tiny_test": True, "image_size": 64, "width": 16, "crops": 1, "light_lobes": 8, "eval_width": 32}


@pytest.fixture(scope="module")
def cell(tmp_path_factory) -> Path:
    """The built-in vase and a small ray cache of it: ``mesh.ply``, ``transform.json``, ``train.npz``, ``eval.npz``."""
    d = tmp_path_factory.mktemp("recipe")
    res = normalize_mesh("builtin:vase", NormalizeSettings())
    save_ply(d / "mesh.ply", res.mesh)
    (d / "transform.json").write_text(json.dumps(res.transform.to_json()))
    rc = RaycacheSettings(views=4, resolution=48, eval_azimuths=4, eval_elevations_deg=(0.0, 30.0), eval_resolution=32)
    raycache_run(d / "mesh.ply", d / "train.npz", d / "eval.npz", d / "rc.json", rc)
    return d


def workflow(cell: Path, out: Path, settings: OptimizeSettings) -> dict:
    """Optimise, bake and export one cell into ``out``; the export's metadata."""
    optimize.run(cell / "train.npz", cell / "eval.npz", "a vase", out / "opt", settings, "cpu")
    bake.run(
        cell / "mesh.ply", out / "opt" / "field.pt", cell / "eval.npz", out / "bake", BakeSettings(texture_size=64, eval_width=32)
    )
    export.run(
        cell / "mesh.ply", cell / "transform.json", out / "bake", out / "bake" / "preview.png", out / "export", ExportSettings()
    )
    return json.loads((out / "export" / "meta.json").read_text())


def test_the_recipes_name_files_that_exist():
    """The files CONTRIBUTING.md's recipes send a contributor to are named there and exist (a
    recipe whose files moved fails here)."""
    text = (REPO / "CONTRIBUTING.md").read_text()
    named = (
        *("stages/config/brdfs.py", "stages/render/brdf/", "stages/config/guidance_modes.py", "stages/guidance/objective.py"),
        *("stages/model/lights/", "stages/assets/formats/", "stages/config/layout.py", "stages/config/sections.py"),
        *("stages/config/records.py", "workflow/rules/", "stages/training/calibrate.py", "benchmarks/common.py"),
        *("tests/test_recipes.py", "tests/model/test_light_components.py", "tests/assets/test_export_formats.py"),
    )
    for path in named:
        assert path in text and (REPO / path).exists(), path


# ------------------------------------------------------------------------------------ a BRDF
class Constant(type(brdfs.TANGO)):
    """A constant BRDF: Lambert's ``albedo / pi``, nothing specular (TANGO's parameters and assets)."""

    name = "constant"

    def radiance(self, normal, view, material, light, lobe, visibility):
        diffuse = diffuse_radiance(normal, material.albedo, light, visibility)
        return Shading(diffuse, torch.zeros_like(diffuse))


def test_a_constant_brdf_is_one_row_and_one_object(cell, tmp_path):
    spec = dataclasses.replace(BRDFS["tango"], name="constant", lobes=("isotropic",))
    with brdfs.temporarily(spec, Constant()) as model:
        s = OptimizeSettings(brdf="constant", specular_lobe="isotropic", **SMALL)
        meta = workflow(cell, tmp_path, s)
        field, _ = load_field(tmp_path / "opt" / "field.pt")[:2]
        assert field.brdf is model
        n = torch.nn.functional.normalize(torch.randn(32, 3), dim=-1)
        shading = field.shade(*field.surface(torch.rand(32, 3) - 0.5, n), n)
        assert torch.equal(shading.specular, torch.zeros_like(shading.specular))
    assert "constant" not in BRDFS and "constant" not in brdfs.names()
    assert (tmp_path / "export" / "model.glb").stat().st_size > 0 and meta["stats"]["brdf"] == "constant"


# --------------------------------------------------------------------------- a guidance mode
class Zero(objective.Guidance):
    """A guidance whose loss is zero: nothing changes the field."""

    held_out_key = "guidance"
    weights_id = "nothing"

    @classmethod
    def build(cls, settings, prompt, device, guide, targets):
        return cls(settings, prompt)

    def loss(self, rendered, target):
        return sum(img.sum() for img in rendered.globals) * 0.0, {}

    def eval_score(self, renders, views, width, out_width):
        return objective.EvalScore({"zero": 0.0})

    def held_out(self, renders, store, candidates, background):
        return objective.HeldOut({"zero": 0.0})


def test_a_zero_guidance_is_one_row_and_one_class(cell, tmp_path):
    clip = GUIDANCE_MODES["clip"]
    row = dataclasses.replace(clip, name="zero", description="nothing", label="zero", origin="ZERO: {weights}", uses_clip=False)
    with GUIDANCE_MODES.temporarily("zero", row):
        objective.register("zero")(Zero)
        try:
            s = OptimizeSettings(guidance="zero", **SMALL)
            meta = optimize.run(cell / "train.npz", cell / "eval.npz", "a vase", tmp_path, s, "cpu")
            field, *_ = load_field(tmp_path / "field.pt")
        finally:
            del objective.GUIDANCE_CLASSES[("zero", None)]
    assert "zero" not in GUIDANCE_MODES
    assert meta["origin"]["guidance"] == "zero" and meta["origin"]["label"] == "ZERO: nothing"
    assert field is not None
    losses = [line.split(",") for line in (tmp_path / "loss.csv").read_text().splitlines()]
    column = losses[0].index("loss")
    # the guidance's part is zero: what is left is the normal network's small regulariser
    assert len(losses) == 1 + SMALL["iterations"] and all(abs(float(row[column])) < 1e-6 for row in losses[1:])
