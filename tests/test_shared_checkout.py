"""Tests that read ../shared skip in a checkout without it and fail under CI, which has it."""

from __future__ import annotations

import conftest
import pytest


@pytest.mark.parametrize("ci", ["", "1"])
def test_a_missing_shared_mesh_skips_outside_ci_and_fails_under_ci(monkeypatch, tmp_path, ci):
    monkeypatch.setattr(conftest, "SHARED_MESHES", tmp_path / "shared" / "meshes")
    monkeypatch.setenv("CI", ci)
    expected = pytest.fail.Exception if ci else pytest.skip.Exception
    with pytest.raises(expected, match="absent"):
        conftest.shared_mesh("horse.obj")
    # and present, the mesh is found whatever CI says
    (tmp_path / "shared" / "meshes").mkdir(parents=True)
    (tmp_path / "shared" / "meshes" / "horse.obj").write_text("v 0 0 0\n")
    assert conftest.shared_mesh("horse.obj").name == "horse.obj"
