"""decimate: target face count, Hausdorff recorded, shared frame with the normalised mesh; seam-split
meshes welded first, and a target that cannot be reached is reported loudly."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from conftest import icosphere, shared_mesh

from stages import decimate
from stages.config.sections import DecimateSettings, NormalizeSettings, RaycacheSettings
from stages.core.errors import ConfigError
from stages.geometry.cameras import camera_space_directions
from stages.geometry.decimation import decimate_mesh, edge_counts, face_budget, pixel_footprint, weld_vertices
from stages.geometry.meshio import TriMesh, load_ply, save_ply
from stages.geometry.normalization import normalize_mesh


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
    assert s["target_reached"] is True and s["target_shortfall_reason"] is None
    assert s["boundary_edges_before_weld"] == s["boundary_edges_after_weld"] == 0
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


# --- welding: meshes split at UV/normal seams -------------------------------------------------


def unweld(mesh: TriMesh) -> TriMesh:
    """Every face gets its own three vertices (the extreme case of a seam-split export)."""
    return TriMesh(mesh.vertices[mesh.faces].reshape(-1, 3), np.arange(3 * len(mesh.faces)).reshape(-1, 3))


def split_charts(mesh: TriMesh, chart: np.ndarray) -> TriMesh:
    """Split ``mesh`` along the borders of the face labels ``chart (F,)``, as UV charts are: every
    chart gets its own copies of the vertices it uses, so chart borders become seams."""
    keys = np.stack([np.repeat(chart, 3), mesh.faces.reshape(-1)], axis=1)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    return TriMesh(mesh.vertices[unique[:, 1]], inverse.reshape(-1, 3))


def grid(n: int) -> TriMesh:
    """An open height field of ``2 (n - 1)^2`` faces in the unit ball (one boundary loop of 4 (n - 1) edges)."""
    x, y = np.meshgrid(np.linspace(-0.7, 0.7, n), np.linspace(-0.7, 0.7, n))
    v = np.stack([x, 0.15 * np.sin(3 * x) * np.cos(2 * y), y], -1).reshape(-1, 3)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    return TriMesh(v, np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]))


def test_weld_vertices_exact_near_and_far():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1 + 1e-9, 0], [1, 1, 0], [0.5, 0.5, 1e-3]], float)
    f = np.array([[0, 1, 2], [3, 5, 4], [1, 3, 6]])  # the last face is degenerate once 1 and 3 are welded
    w = weld_vertices(TriMesh(v, f), 1e-6)
    assert w.exact_merged == 1 and w.near_merged == 1 and w.faces_dropped == 1
    assert len(w.mesh.vertices) == 4 and len(w.mesh.faces) == 2  # (0.5, 0.5, 1e-3) is unused and far: dropped
    assert edge_counts(w.mesh.faces) == {"boundary_edges": 4, "nonmanifold_edges": 0, "components": 1}
    assert w.tolerance == pytest.approx(1e-6 * np.linalg.norm([1, 1 + 1e-9, 1e-3]))  # of the bounding-box diagonal
    exact = weld_vertices(TriMesh(v, f), 0.0)
    assert exact.near_merged == 0 and len(exact.mesh.vertices) == 5
    # a mesh without duplicates comes back unchanged (same order), so welding changes nothing for it
    vase = normalize_mesh("builtin:vase", NormalizeSettings()).mesh
    same = weld_vertices(vase).mesh
    assert np.array_equal(same.vertices, vase.vertices) and np.array_equal(same.faces, vase.faces)


def test_unwelded_mesh_reaches_target_like_the_welded_one():
    """Every face with its own three vertices: all edges are boundary edges, so the boundary-preserving
    collapse could not remove a single face; welded first, it reaches the target and the same
    surface as decimating the welded original."""
    sphere = icosphere(5)  # 20480 faces, 10242 vertices, closed
    soup = unweld(sphere)
    settings = DecimateSettings(target_faces=2000, hausdorff_samples=20000)
    result = decimate_mesh(soup, settings)
    s = result.stats
    assert s["target_reached"] and s["target_shortfall_reason"] is None
    assert abs(s["faces_after"] - 2000) <= 20 and len(result.mesh.faces) == s["faces_after"]
    assert s["vertices_before_weld"] == 3 * 20480 and s["vertices_after_weld"] == 10242
    assert s["boundary_edges_before_weld"] == 3 * 20480 and s["boundary_edges_after_weld"] == 0
    assert s["weld"]["exact_duplicates_merged"] == 3 * 20480 - 10242 and not s["boundary_relaxed"]
    reference = decimate_mesh(sphere, settings).stats
    assert s["hausdorff_max"] == pytest.approx(reference["hausdorff_max"], rel=0.25)
    assert 0 < s["hausdorff_max"] < 0.01
    check_shared_frame(soup, result.mesh, s)


def test_without_welding_the_unwelded_mesh_stops_far_above_target(caplog):
    """What the stage did before welding (weld off): no collapse at all, now reported loudly."""
    soup = unweld(icosphere(4))  # 5120 faces
    with caplog.at_level(logging.WARNING, logger="stages.decimate"):
        s = decimate_mesh(soup, DecimateSettings(target_faces=500, hausdorff_samples=5000, weld=False), name="soup.ply").stats
    assert s["faces_after"] == 5120 and not s["target_reached"]
    assert s["vertices_after_weld"] == s["vertices_before_weld"] == 3 * 5120
    assert "weld: true" in s["target_shortfall_reason"] and "leave 0 boundary edges" in s["target_shortfall_reason"]
    [record] = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "soup.ply" in record.getMessage() and "5120 faces reached for a target of 500" in record.getMessage()


def test_partially_seam_split_mesh_with_rounded_copies():
    """Only some seams split (three charts), one chart's copies rounded to float32 as exporters do:
    exact and near duplicates are welded, the mesh is closed again and reaches the target."""
    knot = normalize_mesh("builtin:knot", NormalizeSettings()).mesh
    centroids = knot.vertices[knot.faces].mean(axis=1)
    chart = (centroids[:, 0] > 0).astype(int) + 2 * (centroids[:, 1] > 0.3)
    split = split_charts(knot, chart)
    v = split.vertices.copy()
    in_chart3 = np.unique(split.faces[chart == 3])
    v[in_chart3] = v[in_chart3].astype(np.float32).astype(np.float64)
    split = TriMesh(v, split.faces)
    seams = edge_counts(split.faces)["boundary_edges"]
    assert 0 < seams < len(split.faces) // 10  # a seam-split mesh, not a triangle soup
    settings = DecimateSettings(target_faces=1500, hausdorff_samples=20000)
    result = decimate_mesh(split, settings)
    s = result.stats
    assert s["boundary_edges_before_weld"] == seams and s["boundary_edges_after_weld"] == 0
    assert s["vertices_after_weld"] == len(knot.vertices)
    assert s["weld"]["exact_duplicates_merged"] > 0 and s["weld"]["near_duplicates_merged"] > 0
    assert s["target_reached"] and abs(s["faces_after"] - 1500) <= 15
    reference = decimate_mesh(knot, settings).stats
    assert s["hausdorff_max"] == pytest.approx(reference["hausdorff_max"], rel=0.25)
    # exact duplicates only: the rounded chart stays cut off by a seam
    exact = decimate_mesh(split, DecimateSettings(target_faces=1500, hausdorff_samples=2000, weld_tolerance=0.0)).stats
    assert exact["boundary_edges_after_weld"] > 0 and exact["weld"]["near_duplicates_merged"] == 0


def test_open_mesh_relaxes_boundary_to_reach_target(caplog):
    """An open mesh whose boundary ring alone holds more faces than the target: with boundaries
    preserved the collapse stops at about one face per boundary edge (396); relaxed (topology kept),
    it reaches 300."""
    mesh = grid(100)  # 19602 faces, 396 boundary edges
    s = decimate_mesh(mesh, DecimateSettings(target_faces=300, hausdorff_samples=20000)).stats
    assert s["collapse_passes"][-1] >= 390 and s["boundary_relaxed"]
    assert "396 boundary edges remain after welding" in s["boundary_relaxation_reason"]
    assert s["target_reached"] and abs(s["faces_after"] - 300) <= 3
    assert s["hausdorff_max"] < 0.03
    with caplog.at_level(logging.WARNING, logger="stages.decimate"):
        strict = decimate_mesh(mesh, DecimateSettings(target_faces=300, hausdorff_samples=2000, relax_boundary=False)).stats
    assert not strict["target_reached"] and "relax_boundary: true" in strict["target_shortfall_reason"]
    assert strict["faces_after"] == s["collapse_passes"][-1] and caplog.records[-1].levelno == logging.WARNING


def test_unreachable_target_warns_and_is_recorded(tmp_path, caplog):
    """A soup of disjoint triangles cannot lose a face without deleting a component: the stage
    says so as a WARNING naming the file, target and faces reached, and in the meta."""
    rng = np.random.default_rng(7)
    n = 1000
    corners = rng.normal(size=(n, 1, 3)) * 0.25 + rng.normal(size=(n, 3, 3)) * 0.02
    src = tmp_path / "soup.ply"
    save_ply(src, TriMesh(corners.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3)))
    out = tmp_path / "dec"
    out.mkdir()
    settings = DecimateSettings(target_faces=200, hausdorff_samples=2000)
    with caplog.at_level(logging.WARNING, logger="stages.decimate"):
        decimate.run(src, out / "mesh.ply", out / "meta.json", settings)
    s = json.loads((out / "meta.json").read_text())["stats"]
    assert s["target_reached"] is False and s["faces_after"] == n
    reason = s["target_shortfall_reason"]
    assert f"{n} connected components" in reason and "no component deleted" in reason
    [record] = [r for r in caplog.records if r.levelno == logging.WARNING]
    message = record.getMessage()
    assert str(src) in message and f"{n} faces reached for a target of 200" in message and reason in message


@pytest.mark.slow
def test_unwelded_shared_mesh_reaches_target():
    """The lamp of TANGO's robustness figure with every face split off (41,160 faces -> 5,000)."""
    mesh = unweld(normalize_mesh(shared_mesh("lamp.obj"), NormalizeSettings()).mesh)
    result = decimate_mesh(mesh, DecimateSettings(target_faces=5000, hausdorff_samples=20000))
    s = result.stats
    assert s["faces_before"] == 41160 and s["boundary_edges_before_weld"] == 3 * 41160
    assert s["boundary_edges_after_weld"] == 0 and s["target_reached"]
    assert abs(s["faces_after"] - 5000) <= 50
    assert 0 < s["hausdorff_max"] < 0.05
    check_shared_frame(mesh, result.mesh, s)


def test_pixel_footprint_is_the_cameras_pixel():
    """Against the ray cache's own cameras (``camera_space_directions``): the rays through
    neighbouring pixel centres meet a plane at ``depth`` in front of the camera ``footprint``
    apart, at the image centre and at its corner alike (a pinhole maps a parallel plane
    uniformly)."""
    for res, fov, depth in ((512, 60.0, 1.0), (96, 45.0, 1.5), (1000, 10.0, 7.0)):
        dirs = camera_space_directions(res, fov).reshape(res, res, 3)
        hits = dirs * (depth / -dirs[..., 2:])  # on the plane z = -depth
        for r, c in ((res // 2, res // 2 - 1), (0, 0)):
            assert pixel_footprint(res, fov, depth) == pytest.approx(hits[r, c + 1, 0] - hits[r, c, 0], rel=1e-9)
            assert pixel_footprint(res, fov, depth) == pytest.approx(hits[r, c, 1] - hits[r + 1, c, 1], rel=1e-9)


def test_face_budget_of_a_sphere():
    """Unit sphere (area 4 pi, extent 1) under the default cache: the nearest its surface comes to
    the training cameras (radius 2) is depth 1, where a 512-pixel, 60-degree pixel is
    ``2 tan(30 deg) / 512`` wide (the evaluation views are the same; the metric views, 224
    pixels at 45 degrees from 2.5, are coarser), so the budget is ``ceil(4 pi / s^2)`` faces of
    one pixel each; four pixels per face quarter it; finer metric views set it when they are the
    finest; cameras within the mesh's extent have no budget."""
    s = 2 * 1.0 * np.tan(np.radians(30.0)) / 512
    b = face_budget(4 * np.pi, RaycacheSettings())
    assert b.view_set == "training" and b.depth == 1.0 and b.faces == int(np.ceil(4 * np.pi / s**2))
    assert face_budget(4 * np.pi, RaycacheSettings(), 4.0).faces == int(np.ceil(np.pi / s**2))
    fine = face_budget(4 * np.pi, RaycacheSettings(resolution=64, eval_resolution=64, metrics_resolution=512))
    assert fine.view_set == "metrics" and fine.depth == 1.5
    assert fine.footprint == pytest.approx(2 * 1.5 * np.tan(np.radians(22.5)) / 512)
    # a mesh reaching out to 1.2 is seen from nearer: depth 0.8
    assert face_budget(4 * np.pi, RaycacheSettings(), extent=1.2).depth == pytest.approx(0.8)
    assert face_budget(1e-9, RaycacheSettings()).faces == 4
    with pytest.raises(ValueError, match="training cameras are within"):
        face_budget(4 * np.pi, RaycacheSettings(radius=0.9))


def _budget_stage(tmp_path, mesh, cache, **settings):
    src = tmp_path / "in.ply"
    save_ply(src, mesh)
    args = ["--input", str(src), "--mesh", str(tmp_path / "out.ply"), "--meta", str(tmp_path / "meta.json")]
    args += ["--settings", json.dumps({"mode": "budget", "hausdorff_samples": 5000, **settings})]
    args += ["--raycache-settings", json.dumps(cache.to_dict())]
    assert decimate.main(args) == 0
    return load_ply(tmp_path / "out.ply"), json.loads((tmp_path / "meta.json").read_text())


def test_budget_mode_decimates_a_mesh_finer_than_its_views(tmp_path):
    sphere = icosphere(5)  # 20,480 faces
    cache = RaycacheSettings(resolution=24, eval_resolution=24, metrics_resolution=16)
    out, meta = _budget_stage(tmp_path, sphere, cache)
    budget = meta["face_budget"]
    area = float(sphere.face_areas.sum())
    s = 2 * (2.0 - np.linalg.norm(sphere.vertices, axis=1).max()) * np.tan(np.radians(30.0)) / 24
    assert budget["faces"] == int(np.ceil(area / s**2)) and budget["view_set"] in ("training", "evaluation")
    assert len(sphere.faces) > budget["faces"] >= len(out.faces) * 0.98  # reached (MeshLab lands within 1%)
    assert meta["stats"]["target_reached"] and meta["settings"]["target_faces"] == budget["faces"]
    assert meta["settings"]["raycache"]["resolution"] == 24
    # the surface stays where it was: well under a pixel of the views that set the budget
    assert meta["stats"]["hausdorff_max"] < s


def test_budget_mode_keeps_a_mesh_within_its_budget(tmp_path):
    sphere = icosphere(3)  # 1,280 faces, far below the default cache's budget
    out, meta = _budget_stage(tmp_path, sphere, RaycacheSettings())
    assert meta["face_budget"]["faces"] > len(sphere.faces) and meta["stats"]["skipped"]
    np.testing.assert_array_equal(out.faces, sphere.faces)
    np.testing.assert_allclose(out.vertices, sphere.vertices, rtol=0, atol=0)


def test_budget_mode_needs_the_cache_settings(tmp_path):
    src = tmp_path / "in.ply"
    save_ply(src, icosphere(2))
    with pytest.raises(Exception, match="no ray-cache settings"):
        decimate.run(src, tmp_path / "o.ply", tmp_path / "m.json", DecimateSettings(mode="budget"))
    assert not (tmp_path / "o.ply").exists()
    with pytest.raises(ConfigError, match="decimate.mode"):
        DecimateSettings(mode="auto")


def test_share_mode_keeps_that_share_of_the_faces(tmp_path):
    sphere = icosphere(4)  # 5,120 faces
    src = tmp_path / "in.ply"
    save_ply(src, sphere)
    args = ["--input", str(src), "--mesh", str(tmp_path / "out.ply"), "--meta", str(tmp_path / "meta.json")]
    assert (
        decimate.main(args + ["--settings", json.dumps({"mode": "share", "target_share": 0.25, "hausdorff_samples": 5000})]) == 0
    )
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["settings"]["target_faces"] == 1280 and meta["stats"]["target_reached"]
    assert 1280 * 0.98 <= len(load_ply(tmp_path / "out.ply").faces) <= 1280
    for bad in (0.0, 1.0, 1.5):
        with pytest.raises(ConfigError, match="target_share must be in"):
            DecimateSettings(mode="share", target_share=bad)


def test_shape_quality_counts_slivers_and_folds():
    from stages.geometry.decimation import shape_quality

    q = shape_quality(icosphere(3))  # near-equilateral faces, every dihedral small
    assert q == {"slivers": 0.0, "folds": 0.0, "min_angle_deg_p1": pytest.approx(q["min_angle_deg_p1"])}
    assert 50.0 < q["min_angle_deg_p1"] <= 60.0
    # a strip of two faces: one with a 5-degree corner; folded about the shared edge (0, 1) by 150
    # degrees (a fold) or 60 (not)
    for fold_deg, folds in ((150.0, 1.0), (60.0, 0.0)):
        t = np.radians(fold_deg)
        v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -np.cos(t), np.sin(t)]], float)
        sliver = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.tan(np.radians(5.0)) * 0.5, 0]], float)
        mesh = TriMesh(np.vstack([v, sliver + 5.0]), np.array([[0, 1, 2], [1, 0, 3], [4, 5, 6]]))
        q = shape_quality(mesh)
        assert q["slivers"] == pytest.approx(1 / 3) and q["folds"] == folds, (fold_deg, q)
