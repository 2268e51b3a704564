"""Every bad input of the issue: one clear message naming the file and the problem, exit status 2,
and no output left behind (not even a temporary file)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from stages import normalize, raycache
from stages.core.provenance import atomic_path
from stages.geometry.meshio import TriMesh, save_ply


def write(path, text):
    path.write_text(text)
    return path


def write_bytes(path, data):
    path.write_bytes(data)
    return path


BAD_MESHES = {
    "missing": (lambda d: d / "nope.obj", "file not found"),
    "empty_file": (lambda d: write(d / "empty.obj", ""), "file is empty"),
    "garbage": (
        lambda d: write_bytes(d / "garbage.glb", b"\x00\xffnot a glb" * 50),
        "could not be read",
    ),
    "no_faces": (lambda d: write(d / "verts.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"), "has no faces"),
    "nan": (
        lambda d: write(d / "nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n"),
        "NaN or infinite",
    ),
    "inf": (
        lambda d: write(d / "inf.obj", "v 0 0 0\nv inf 0 0\nv 0 1 0\nf 1 2 3\n"),
        "NaN or infinite",
    ),
    "zero_area": (
        lambda d: write(d / "flat.obj", "v 0 0 0\nv 1 1 1\nv 2 2 2\nv 3 3 3\nf 1 2 3\nf 2 3 4\nf 1 1 2\n"),
        "zero area",
    ),
    "unsupported": (lambda d: write(d / "mesh.fbx", "whatever"), "unsupported mesh format"),
}


def point_cloud(d):
    path = d / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(100, 3))).export(path)
    return path


BAD_MESHES["point_cloud"] = (point_cloud, "no faces")


@pytest.mark.parametrize("case", sorted(BAD_MESHES))
def test_bad_mesh_fails_cleanly(tmp_path, capsys, case):
    make, needle = BAD_MESHES[case]
    src = make(tmp_path)
    out = tmp_path / "out"
    argv = [
        "--input",
        str(src),
        "--mesh",
        str(out / "mesh.ply"),
        "--transform",
        str(out / "t.json"),
    ]
    code = normalize.main([*argv, "--meta", str(out / "meta.json")])
    assert code == 2
    errors = [ln for ln in capsys.readouterr().err.splitlines() if " ERROR " in ln]
    assert len(errors) == 1, errors
    assert str(src) in errors[0] and needle in errors[0]
    assert not out.exists() or not any(out.iterdir())


def test_a_mesh_past_the_face_limit_is_refused_naming_decimation(tmp_path, capsys):
    """normalize.max_faces: a mesh with more faces fails at once, one line with its count, the
    limit and decimation as the remedy; the limit is not part of the mesh-level work's key."""
    from stages.config.workflow import WorkflowConfig

    out = tmp_path / "o"
    argv = ["--input", "builtin:candle", "--mesh", str(out / "m.ply"), "--transform", str(out / "t"), "--meta", str(out / "j")]
    assert normalize.main([*argv, "--settings", '{"max_faces": 1000}']) == 2
    errors = [ln for ln in capsys.readouterr().err.splitlines() if " ERROR " in ln]
    assert len(errors) == 1 and "builtin:candle: has 13,440 faces, more than normalize.max_faces (1,000)" in errors[0]
    assert "decimate: {enabled: true, mode: budget}" in errors[0]
    assert not out.exists() or not any(out.iterdir())
    assert normalize.main([*argv, "--settings", '{"max_faces": 13440}']) == 0
    keys = [
        WorkflowConfig({"meshes": {"c": {"builtin": "candle", "normalize": n}}, "prompts": {"p": "a"}}).mesh_work_keys("c")
        for n in ({}, {"max_faces": 5_000_000})
    ]
    assert keys[0] == keys[1]


def test_unknown_builtin(tmp_path, capsys):
    out = tmp_path / "o"
    code = normalize.main(
        [
            "--input",
            "builtin:teapot",
            "--mesh",
            str(out / "m.ply"),
            "--transform",
            str(out / "t"),
            "--meta",
            str(out / "j"),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "builtin:teapot" in err and "vase" in err


def test_bad_settings_fail_with_key_name(tmp_path, capsys):
    out = tmp_path / "o"
    code = normalize.main(
        [
            "--input",
            "builtin:vase",
            "--mesh",
            str(out / "m.ply"),
            "--transform",
            str(out / "t"),
            "--meta",
            str(out / "j"),
            "--settings",
            '{"up_axes": "+z"}',
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "'up_axes'" in err and "up_axis" in err
    assert not out.exists()


def ring_facing_camera(tmp_path):
    """A thin torus around the x axis: from (r, 0, 0) with a narrow view, every ray goes through the hole."""
    t = trimesh.creation.torus(major_radius=0.9, minor_radius=0.1)
    v = np.asarray(t.vertices)[:, [2, 1, 0]]  # torus axis z -> x
    path = tmp_path / "ring.ply"
    save_ply(path, TriMesh(v / np.linalg.norm(v, axis=1).max(), np.asarray(t.faces)))
    return path


def test_view_pool_that_sees_nothing(tmp_path, capsys):
    src = ring_facing_camera(tmp_path)
    out = tmp_path / "rc"
    settings = (
        '{"views": 3, "resolution": 32, "fov_deg": 5.0, "anchor_azimuth": 0.0, "anchor_elevation": 0.0,'
        ' "std": 1e6, "eval_resolution": 16}'
    )
    code = raycache.main(
        [
            "--input",
            str(src),
            "--train",
            str(out / "train.npz"),
            "--eval",
            str(out / "eval.npz"),
            "--meta",
            str(out / "meta.json"),
            "--settings",
            settings,
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert str(src) in err and "none of the 3 train views sees the mesh" in err
    assert not out.exists() or not any(out.iterdir())


def test_missing_raycache_input(tmp_path, capsys):
    src = tmp_path / "gone.ply"
    out = tmp_path / "rc"
    code = raycache.main(
        [
            "--input",
            str(src),
            "--train",
            str(out / "a.npz"),
            "--eval",
            str(out / "b.npz"),
            "--meta",
            str(out / "m.json"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and str(src) in err and "file not found" in err


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "sub" / "result.npz"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            assert tmp.parent == target.parent and tmp.name.startswith(".")
            raise RuntimeError("killed")
    assert not target.exists()
    assert list(target.parent.iterdir()) == []
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"whole")
    assert target.read_bytes() == b"whole"
    assert [p.name for p in target.parent.iterdir()] == ["result.npz"]
