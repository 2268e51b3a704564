"""decimate: target face count, Hausdorff recorded, shared frame with the normalised mesh."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import shared_mesh

from stages import decimate
from stages.decimate import DecimateSettings, decimate_mesh
from stages.meshio import TriMesh, load_ply, save_ply
from stages.normalize import NormalizeSettings, normalize_mesh


def check_shared_frame(before: TriMesh, after: TriMesh, stats: dict) -> None:
    """Both levels share the normalised frame: the decimated surface is within the Hausdorff
    distance h of the original, so its radius is at most 1 + h (and at least 1 - h, since the
    farthest original vertex has a decimated point within h), and its area-weighted centroid
    moves by less than h (the vertex centroid is density-dependent and may move much more)."""
    h = stats["hausdorff_max"]
    r = np.linalg.norm(after.vertices, axis=1).max()
    # Hausdorff is estimated from samples: allow 1% of h on top
    assert 1 - 1.01 * h - 1e-9 <= r <= 1 + 1.01 * h + 1e-9
    assert stats["surface_centroid_shift"] < h
    assert stats["radius_after"] == pytest.approx(r)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["lamp.obj", "candle.obj"])
def test_shared_mesh_reaches_target(name, tmp_path):
    mesh = normalize_mesh(shared_mesh(name), NormalizeSettings()).mesh
    result = decimate_mesh(mesh, DecimateSettings(target_faces=5000, hausdorff_samples=20000))
    s = result.stats
    assert s["faces_before"] == len(mesh.faces) > 30000
    assert abs(s["faces_after"] - 5000) <= 50  # within 1%
    assert len(result.mesh.faces) == s["faces_after"]
    assert 0 < s["hausdorff_max"] < 0.05
    assert s["hausdorff_original_to_decimated"]["mean"] < s["hausdorff_max"]
    check_shared_frame(mesh, result.mesh, s)


def test_builtin_vase_cli(tmp_path):
    src = tmp_path / "vase.ply"
    save_ply(src, normalize_mesh("builtin:vase", NormalizeSettings()).mesh)
    out = tmp_path / "dec"
    code = decimate.main(
        [
            "--input",
            str(src),
            "--mesh",
            str(out / "mesh.ply"),
            "--meta",
            str(out / "meta.json"),
            "--settings",
            json.dumps({"target_faces": 2000, "hausdorff_samples": 20000}),
        ]
    )
    assert code == 0
    meta = json.loads((out / "meta.json").read_text())
    s = meta["stats"]
    assert s["faces_before"] == 20352 and abs(s["faces_after"] - 2000) <= 20
    assert len(load_ply(out / "mesh.ply").faces) == s["faces_after"]
    assert meta["settings"]["target_faces"] == 2000 and meta["versions"]["pymeshlab"]
    check_shared_frame(load_ply(src), load_ply(out / "mesh.ply"), s)
    assert s["degenerate_faces_after"] == 0


def test_below_target_is_kept(tmp_path):
    mesh = normalize_mesh("builtin:knot", NormalizeSettings()).mesh
    result = decimate_mesh(mesh, DecimateSettings(target_faces=50000, hausdorff_samples=2000))
    assert result.stats["skipped"] and result.stats["faces_after"] == len(mesh.faces)
    assert result.stats["hausdorff_max"] == pytest.approx(0.0, abs=1e-9)


def test_open_non_manifold_input_survives():
    """Boundaries and non-manifold edges (normal in real data) must not break the collapse."""
    mesh = normalize_mesh("builtin:vase", NormalizeSettings()).mesh
    keep = np.ones(len(mesh.faces), bool)
    keep[::7] = False  # punch holes: many boundary edges
    faces = np.concatenate([mesh.faces[keep], mesh.faces[:30]])  # and duplicate faces
    holed = TriMesh(mesh.vertices, faces)
    result = decimate_mesh(holed, DecimateSettings(target_faces=4000, hausdorff_samples=5000))
    assert np.isfinite(result.mesh.vertices).all()
    assert result.stats["faces_after"] <= len(faces)
