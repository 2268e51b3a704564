"""The ray tracer's any-hit query and its threads: the same answers as the first-hit query and as
one thread, on a real mesh, whatever the split; the stages' ``--threads`` reaches it."""

from __future__ import annotations

import os

import numpy as np
import pytest

from stages.config.sections import NormalizeSettings
from stages.core import threads as core_threads
from stages.core.cli import stage_main
from stages.geometry import tracing
from stages.geometry.normalization import normalize_mesh
from stages.geometry.tracing import EmbreeTracer, TrimeshTracer
from stages.geometry.visibility import fibonacci_directions, sample_surface, surface_offset


@pytest.fixture
def knot_rays():
    """Shadow rays from 600 points of the built-in knot (it shadows itself) in 64 directions
    each, about 10 % of them blocked: ``(mesh, origins, directions)``."""
    mesh = normalize_mesh("builtin:knot", NormalizeSettings()).mesh
    points, face = sample_surface(mesh, 600, seed=5)
    normals = mesh.face_normals[face]
    dirs = fibonacci_directions(64)
    rows, cols = np.nonzero(normals @ dirs.T > 0)
    origins = points[rows] + surface_offset(mesh.vertices) * normals[rows]
    return mesh, origins, dirs[cols]


@pytest.fixture
def few_rays_per_thread(monkeypatch):
    """Threads split even a small batch (about 1,000 rays each) and the count is restored after."""
    monkeypatch.setattr(tracing, "RAYS_PER_THREAD", 1000)
    yield
    core_threads.set_cpu_threads(None)


def test_any_hit_query_answers_as_the_first_hit_query(knot_rays):
    mesh, origins, dirs = knot_rays
    tracer = EmbreeTracer(mesh)
    blocked = tracer.trace(origins, dirs).face >= 0
    assert 0.03 < blocked.mean() < 0.5  # both answers are well represented
    np.testing.assert_array_equal(tracer.occluded(origins, dirs), blocked)
    # the pure-Python reference on a subset (about 400 rays/s)
    ref = TrimeshTracer(mesh)
    pick = np.random.default_rng(0).choice(len(origins), 300, replace=False)
    np.testing.assert_array_equal(ref.occluded(origins[pick], dirs[pick]), blocked[pick])


@pytest.mark.parametrize("count", [1, 2, 3, 7])
def test_threads_change_nothing_but_the_time(knot_rays, few_rays_per_thread, count):
    mesh, origins, dirs = knot_rays
    tracer = EmbreeTracer(mesh)
    core_threads.set_cpu_threads(1)
    one, one_occ = tracer.trace(origins, dirs), tracer.occluded(origins, dirs)
    core_threads.set_cpu_threads(count)
    assert len(tracing._split(len(origins))) == min(count, len(origins) // 1000)
    many, many_occ = tracer.trace(origins, dirs), tracer.occluded(origins, dirs)
    for a, b in ((one.face, many.face), (one.bary, many.bary), (one.depth, many.depth), (one_occ, many_occ)):
        np.testing.assert_array_equal(a, b)
    empty = tracer.trace(origins[:0], dirs[:0])
    assert empty.face.shape == (0,) and empty.bary.shape == (0, 2) and tracer.occluded(origins[:0], dirs[:0]).shape == (0,)


def test_the_split_covers_every_ray_once_in_order(few_rays_per_thread):
    for count, total in ((1, 5), (2, 999), (2, 2000), (3, 10_001), (8, 3_000)):
        core_threads.set_cpu_threads(count)
        parts = tracing._split(total)
        assert np.concatenate([np.arange(total)[s] for s in parts]).tolist() == list(range(total))
        assert len(parts) == max(1, min(count, total // 1000))
    with pytest.raises(ValueError, match="at least 1"):
        core_threads.set_cpu_threads(0)


def test_a_stages_threads_option_reaches_the_tracer(few_rays_per_thread):
    seen = {}

    def body(args):
        seen["threads"] = core_threads.cpu_threads()

    assert stage_main("probe", "a probe", lambda p: None, body, ["--threads", "3"], threads=True) == 0
    assert seen["threads"] == 3
    core_threads.set_cpu_threads(None)
    assert stage_main("probe", "a probe", lambda p: None, body, [], threads=True) == 0
    cpus = len(os.sched_getaffinity(0))
    assert seen["threads"] == min(cpus, int(os.environ.get("OMP_NUM_THREADS") or cpus))


@pytest.mark.parametrize("omp,expected", [("1", 1), ("more", None), ("", None), ("x", None), ("0", None)])
def test_unset_the_count_follows_the_cpus_and_omp_num_threads(monkeypatch, omp, expected):
    cpus = len(os.sched_getaffinity(0))
    monkeypatch.setenv("OMP_NUM_THREADS", str(cpus + 5) if omp == "more" else omp)
    core_threads.set_cpu_threads(None)
    assert core_threads.cpu_threads() == (expected or cpus)


@pytest.mark.parametrize("value", ["0", "-1", "two"])
def test_a_threads_option_below_one_is_refused_in_one_line(capsys, value):
    with pytest.raises(SystemExit) as stop:
        stage_main("probe", "a probe", lambda p: None, lambda a: None, ["--threads", value], threads=True)
    assert stop.value.code == 2
    assert "--threads: must be a whole number of at least 1" in capsys.readouterr().err
