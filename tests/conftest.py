"""Shared fixtures: seeded generators, generated meshes, the ../shared meshes (skipped when absent),
and a helper that runs Snakemake in a temporary working directory."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO.parent / "shared" / "meshes"

#: test workers running side by side (pytest -n; 1 without xdist) and the CPU threads each may use
WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
THREADS = max(1, len(os.sched_getaffinity(0)) // WORKERS)
if os.environ.get("PYTEST_XDIST_WORKER"):
    # a worker's share of the cores, for torch here and in every process it starts (torch reads
    # these when it loads, after this file); idle OpenMP threads sleep instead of spinning: two
    # workers' spinning threads on two cores made a 1-minute fit take over 20 minutes
    os.environ["OMP_NUM_THREADS"] = str(THREADS)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto`` (pyproject's addopts): one test worker more than the CPUs this process may use,
    at most 4. Many tests wait rather than compute (Snakemake's and the stages' process start-ups,
    the Slurm polls, the browser, Blender and Node subprocesses): with one worker per CPU the two
    CPUs of a CI run were busy 67% of its 22 minutes (user and system time 32 of 44 CPU-minutes,
    2026-11-25), so a third worker fills the waits; beyond four, every worker's torch, CLIP and
    Snakemake runs cost memory for little."""
    return max(1, min(4, len(os.sched_getaffinity(0)) + 1))


def _rank(item) -> int:
    """0: the cluster script's refusals, 1: the tests on the machine's Slurm cluster (both hold
    :func:`slurm_lock`), 2: the other slow tests, 3: the rest."""
    if "_no_cluster_meanwhile" in item.fixturenames:
        return 0
    if "cluster" in item.fixturenames:
        return 1
    return 2 if item.get_closest_marker("slow") is not None else 3


def _minutes(item) -> float:
    """A slow test's expected length, from ``@pytest.mark.slow(minutes=...)`` (half a minute when
    unstated; only the schedule reads it: a wrong hint costs time, never a result)."""
    mark = item.get_closest_marker("slow")
    return float(mark.kwargs.get("minutes", 0.5)) if mark is not None else 0.0


def _by_shared_fixture(items) -> list[list]:
    """The slow tests in units: those of one module that use the same module- or session-scoped
    fixture together (on two workers, each would build it: the killed-job tests' uninterrupted run
    was made twice), every other test alone."""
    units: dict[object, list] = {}
    for item in items:
        defs = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {})
        # the project's own (pytest's, such as tmp_path_factory, have no baseid), but the cheap cache
        shared = sorted(
            name for name, d in defs.items() if d and d[-1].baseid and d[-1].scope in ("module", "session") and name != "cache"
        )
        key = (item.module.__name__, tuple(shared)) if shared else item.nodeid
        units.setdefault(key, []).append(item)
    return list(units.values())


def _spread(items: list, workers: int) -> list:
    """The tests laid out for ``workers`` parallel workers under ``--dist worksteal``, which first
    hands worker ``i`` a contiguous chunk of ``len(left) // (workers - i)`` tests: each chunk starts
    with its share of the slow tests (the Slurm tests together, in their order, as one; the others
    dealt longest first to the least loaded chunk) and is filled with quick ones, which an idle
    worker then steals from the tail of a busy one's queue. Without this every slow test sat in
    the first chunk and one worker ran them all, one after the other (25 of the run's 25 minutes)."""
    cluster = [i for i in items if _rank(i) <= 1]
    units = ([cluster] if cluster else []) + list(_by_shared_fixture(i for i in items if _rank(i) == 2))
    units.sort(key=lambda unit: sum(map(_minutes, unit)), reverse=True)
    chunks: list[list] = [[] for _ in range(workers)]
    loads = [0.0] * workers
    for unit in units:
        k = loads.index(min(loads))
        chunks[k] += unit
        loads[k] += sum(map(_minutes, unit))
    quick = iter(i for i in items if _rank(i) == 3)
    out, left = [], len(items)
    for k in range(workers):
        size = left // (workers - k)
        left -= size
        if len(chunks[k]) > size:
            return items  # more slow tests than a chunk holds: keep the plain order
        out += chunks[k] + [next(quick) for _ in range(size - len(chunks[k]))]
    return out


@pytest.hookimpl(trylast=True)  # after -m, -k and --deselect have removed what does not run
def pytest_collection_modifyitems(config, items) -> None:
    """The longest tests first, each group in its own order: those that take the machine's Slurm
    (:func:`slurm_lock`: the cluster script's refusals, then the cluster's tests, so that they run
    in a row on one worker and no other worker waits for the lock), then the other slow ones, then
    the rest; under parallel workers, spread so that each worker starts with its share of the slow
    ones (:func:`_spread`). Every worker computes the same order (xdist checks that they agree)."""
    items.sort(key=_rank)
    if os.environ.get("PYTEST_XDIST_WORKER") and WORKERS > 1:
        items[:] = _spread(items, WORKERS)


@pytest.fixture(autouse=True)
def _numpy_error_state_restored():
    """A test that changes numpy's error state (``np.seterr``) must restore it: a changed state
    leaks into every later test on the worker (an underflow that raises far from its cause)."""
    before = np.geterr()
    yield
    after = np.geterr()
    if after != before:
        np.seterr(**before)
        pytest.fail(f"this test left numpy's error state changed: {before} -> {after}")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def shared_absent(path: Path) -> None:
    """A test needs ``path`` under ``../shared``, which is absent: it skips in a developer checkout
    without ``../shared``, and fails under ``CI`` (CI clones the project beside ``../shared``, so a
    missing file there is lost coverage, not a lighter checkout)."""
    message = f"{path} is absent (only developer checkouts have ../shared)"
    if os.environ.get("CI"):
        pytest.fail(f"{message}; CI runs beside ../shared, so the test fails instead of skipping", pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session")
def shared_meshes() -> Path:
    if not SHARED_MESHES.is_dir():
        shared_absent(SHARED_MESHES)
    return SHARED_MESHES


def shared_mesh(name: str) -> Path:
    path = SHARED_MESHES / name
    if not path.is_file():
        shared_absent(path)
    return path


#: a tiny run: sizes small enough for a test, laid over the config quick writes (and its preset)
TINY = {
    "raycache": {
        "views": 4,
        "resolution": 48,
        "eval_azimuths": 4,
        "eval_elevations_deg": [0.0, 30.0],
        "eval_resolution": 32,
        "metrics_azimuths": 4,
        "metrics_elevations_deg": [0.0],
        "metrics_resolution": 48,
    },
    "target": {"spp": 4, "metric_spp": 8, "texture_size": 128},
    "bake": {"texture_size": 64, "eval_width": 32, "light_width": 64},
    "relight": {"lobes": 4, "fit_iterations": 20, "width": 32},
    "lod": {"enabled": True, "levels": [0.5], "texture_size": 64},
}
#: the optimisation's tiny settings, at the prompt's level (above the prompt's preset)
TINY_OPTIMIZE = {"iterations": 3, "milestones": [2], "image_size": 64, "width": 16, "light_lobes": 4, "eval_width": 32}


#: held by every test that starts this machine's local Slurm cluster or checks what the cluster
#: script refuses (it refuses while the cluster runs): such tests never overlap, on whichever
#: test worker they run
SLURM_LOCK = Path(os.environ.get("TMPDIR", "/tmp")) / "tango-stylize-slurm-tests.lock"


@contextlib.contextmanager
def exclusive(path: Path):
    """Hold the lock file ``path`` (waiting for any other process, test workers included)."""
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def slurm_lock():
    """Exclusive use of the machine's Slurm for the tests (:data:`SLURM_LOCK`; waits its turn)."""
    return exclusive(SLURM_LOCK)


def require_tool(available: bool, reason: str) -> None:
    """Skip a test whose external tool (Node.js, Chromium, a validator) is missing, except in CI
    (``CI`` set), where CI installs every such tool and a missing one must fail the run."""
    if available:
        return
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI must provide it (.ci/run installs it)", pytrace=False)
    pytest.skip(reason)


@contextlib.contextmanager
def dispatched_ops():
    """A region whose dispatched operations' names (forward and backward, as ``aten`` names them)
    gather in the yielded set: which kernels a path really ran."""
    from torch.utils._python_dispatch import TorchDispatchMode

    names: set[str] = set()

    class Ops(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            names.add(func.overloadpacket.__name__)
            return func(*args, **(kwargs or {}))

    with Ops():
        yield names


def require_blender() -> None:
    """:func:`require_tool` for Blender (bpy, the ``blender`` extra)."""
    from stages.reference import blender

    try:
        blender.find_blender()
        found = True
    except blender.BlenderUnavailable:
        found = False
    require_tool(found, "Blender (bpy) is not installed: bash scripts/setup.sh test,reference,blender")


def trimesh_parts(*parts):
    """trimesh meshes concatenated into one TriMesh."""
    import numpy as np
    import trimesh

    from stages.geometry.meshio import TriMesh

    m = trimesh.util.concatenate(parts)
    return TriMesh(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64))


def floor_and_ball(height: float, radius: float):
    """A 40 x 40 floor (top at z = 0) under a ball of ``radius`` centred at ``height``."""
    import trimesh

    floor = trimesh.creation.box(extents=(40.0, 40.0, 0.1))
    floor.apply_translation((0.0, 0.0, -0.05))
    ball = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    ball.apply_translation((0.0, 0.0, height))
    return trimesh_parts(floor, ball)


def icosphere(subdivisions: int):
    """Unit icosphere (all vertices on the unit sphere) as a TriMesh."""
    import trimesh

    from stages.geometry.meshio import TriMesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return TriMesh(np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64))


def snakemake_env(workdir: Path) -> dict[str, str]:
    """The environment of a test's Snakemake: this interpreter's bin first on PATH (so the stages'
    ``python -m`` resolves to the same environment), Snakemake's cache in ``workdir``, not $HOME."""
    env = dict(os.environ)
    env["XDG_CACHE_HOME"] = str(workdir / ".cache")
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    return env


def snakemake_command(workdir: Path, *args: str) -> list[str]:
    """This repository's workflow with ``workdir`` as working directory (results go there)."""
    return [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir), *args]


def mesh_work_dir(workdir: Path, mesh: str, stage: str) -> Path:
    """The one folder of ``mesh``'s ``stage`` work under ``workdir/results/meshes/<mesh>/<key>/``
    (the workflow's shared mesh-level work); a path that does not exist when there is none."""
    found = sorted((workdir / "results" / "meshes" / mesh).glob(f"*/{stage}"))
    assert len(found) <= 1, f"{mesh}/{stage} made under {len(found)} keys: {found}"
    return found[0] if found else workdir / "results" / "meshes" / mesh / "absent" / stage


def synthetic_results(results: Path, meshes: int, prompts: int, decimated: int = 0) -> list[tuple[str, str, str]]:
    """A synthetic results tree at ``results`` (``scripts/synthetic_results.py``: real GLBs and
    records, no optimisation, every output marked TEST ONLY); its cells."""
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "synthetic_results.py"), str(results)]
        + ["--meshes", str(meshes), "--prompts", str(prompts), "--decimated", str(decimated)],
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    return [tuple(line.split("/")) for line in proc.stdout.split()]


def run_snakemake(workdir: Path, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    """Run the workflow in ``workdir`` (see :func:`snakemake_command`, :func:`snakemake_env`)."""
    return subprocess.run(
        snakemake_command(workdir, *args), cwd=REPO, env=snakemake_env(workdir), capture_output=True, text=True, timeout=timeout
    )


SMOKE = REPO / "tests" / "smoke" / "config.yaml"


@dataclass(frozen=True)
class SmokeRun:
    """The smoke grid's run (tests/smoke/config.yaml) in ``workdir``: Snakemake's exit status and
    output."""

    workdir: Path
    returncode: int
    stdout: str
    stderr: str


def smoke_run(tmp_path_factory) -> SmokeRun:
    """The smoke grid run once per test session and shared by every test worker: the first test
    that asks runs it under an exclusive lock in the session's common temporary folder; any other
    (in its own worker, meanwhile or later) waits for the lock and reads the same run. The smoke
    test checks it; the Slurm grid test compares its Slurm run's files with it instead of running
    the same cells again. Its files must be read, not changed."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the workers' folders are popen-gw<N> inside the session's
    work, done = root / "smoke-run", root / "smoke-run.json"
    with exclusive(root / "smoke-run.lock"):
        if not done.is_file():
            shutil.rmtree(work, ignore_errors=True)  # a run that did not finish (its worker killed)
            work.mkdir()
            try:
                proc = run_snakemake(work, "--cores", "2", "--configfile", str(SMOKE), timeout=1500)
                run = {"returncode": proc.returncode, "stdout": proc.stdout, "stderr": proc.stderr}
            except subprocess.TimeoutExpired as err:  # recorded: the next test fails at once, not after 25 minutes
                run = {"returncode": -1, "stdout": "", "stderr": f"the smoke run did not finish in {err.timeout} s"}
            tmp = done.with_suffix(".tmp")
            tmp.write_text(json.dumps(run))
            tmp.replace(done)
    return SmokeRun(work, **json.loads(done.read_text()))


def make_cell(d: Path, **optimize) -> Path:
    """A cell trained for two steps with the tiny test CLIP on the built-in candle (``optimize``:
    its settings beyond the small ones here), baked and exported into ``d``:
    ``mesh.ply, transform.json, train/eval.npz, opt/, bake/, export/``."""
    from stages import bake, export
    from stages import optimize as optimize_stage
    from stages.config.sections import BakeSettings, ExportSettings, NormalizeSettings, OptimizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.raycache import run as raycache_run

    res = normalize_mesh("builtin:candle", NormalizeSettings())
    save_ply(d / "mesh.ply", res.mesh)
    (d / "transform.json").write_text(json.dumps(res.transform.to_json()))
    raycache_run(
        d / "mesh.ply",
        d / "train.npz",
        d / "eval.npz",
        d / "rc.json",
        RaycacheSettings(views=4, resolution=64, eval_azimuths=4, eval_elevations_deg=(0.0, 30.0), eval_resolution=48),
    )
    small = dict(iterations=2, clip_tiny_test=True, image_size=64, width=16, crops=1, light_lobes=8, eval_width=32)
    s = OptimizeSettings(**{**small, **optimize})
    optimize_stage.run(d / "train.npz", d / "eval.npz", "a candle made of wax", d / "opt", s, "cpu")
    bake.run(d / "mesh.ply", d / "opt" / "field.pt", d / "eval.npz", d / "bake", BakeSettings(texture_size=256, eval_width=48))
    export.run(d / "mesh.ply", d / "transform.json", d / "bake", d / "bake" / "preview.png", d / "export", ExportSettings())
    return d


@pytest.fixture(scope="session")
def trained_cell(tmp_path_factory):
    """A cell of TANGO's BRDF (smooth shading normals: its creases and MikkTSpace frames reach the
    assets) from :func:`make_cell`."""
    return make_cell(
        tmp_path_factory.mktemp("cell"),
        shading_normals="smooth",
        # broad lobes: after two steps the light is its initialisation, and TANGO's sharp lobes
        # (the default) made Blender's diffuse pass agree with ours at 30.4 dB instead of above 33
        # (32 spp over 3 views; tests/reference/test_blender_assets.py), a gap in the judge's
        # sampling of small bright lights or in the clamped cosine's fit, not yet told apart
        light_init="broad",
        # TANGO's BRDF: its export maps a coloured F0 (KHR_materials_specular, USD's specular
        # workflow), the longer path; the default glTF BRDF's cell is tests/assets/test_gltf_assets.py's,
        # and the workflow tests run the defaults end to end, Blender's round trip included
        brdf="tango",
    )


@pytest.fixture(scope="session")
def sun_cell(tmp_path_factory):
    """A cell lit by ``builtin:sun_sky`` as a known light with its sun found (``suns: auto``: one
    sun and the SG lobes for the rest), of the default glTF BRDF, from :func:`make_cell`."""
    return make_cell(tmp_path_factory.mktemp("suncell"), light="fixed", light_map="builtin:sun_sky", suns="auto")


def run_lod(cell: Path, out: Path, settings, bake=None):
    """The lod stage on a trained cell's files (see :func:`trained_cell`), writing into ``out``."""
    from stages import lod
    from stages.config.sections import BakeSettings, ExportSettings

    d = cell
    return lod.run(
        lod.CellFiles(
            d / "mesh.ply", d / "opt" / "field.pt", d / "eval.npz", d / "transform.json", d / "bake", d / "export" / "meta.json"
        ),
        out,
        settings,
        bake or BakeSettings(texture_size=256, eval_width=48),
        ExportSettings(),
        "candle",
    )


@pytest.fixture(scope="session")
def lod_cell(trained_cell):
    """The trained cell's levels of detail (50% and 10% of the candle's faces), in ``lod/``."""
    from stages.config.sections import LodSettings

    run_lod(trained_cell, trained_cell / "lod", LodSettings(enabled=True, levels=(0.5, 0.1)))
    return trained_cell


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """The built-in vase, normalised, and a small ray cache of it (6 views at 64 pixels, 8
    evaluation views at 48): ``vase.ply``, ``train.npz``, ``eval.npz``, ``meta.json``."""
    from stages.config.sections import NormalizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.raycache import run as raycache_run

    d = tmp_path_factory.mktemp("rc")
    save_ply(d / "vase.ply", normalize_mesh("builtin:vase", NormalizeSettings()).mesh)
    raycache_run(
        d / "vase.ply",
        d / "train.npz",
        d / "eval.npz",
        d / "meta.json",
        RaycacheSettings(views=6, resolution=64, eval_azimuths=4, eval_elevations_deg=(0.0, 30.0), eval_resolution=48),
    )
    return d


def browser_check(mode: str, page, shot, *args: str) -> dict:
    """``scripts/check_report.mjs`` on a page: what headless Chromium met there."""
    node, chromium = shutil.which("node"), shutil.which("chromium")
    require_tool(
        node is not None and chromium is not None and (REPO / "node_modules" / "playwright-core").is_dir(),
        "Node.js, Debian's chromium or playwright-core missing (.ci/run installs them)",
    )
    out = subprocess.run(
        [node, str(REPO / "scripts" / "check_report.mjs"), mode, str(page), str(shot), *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def assert_not_blank(shot) -> None:
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB")).astype(float)
    background = np.median(img.reshape(-1, 3), axis=0)
    differs = np.abs(img - background).sum(-1) > 30
    assert differs.mean() > 0.05, "the 3D canvas is blank"


def page_references(text: str) -> list[str]:
    """Every ``src``, ``href``, ``poster`` and ``data-*`` URL attribute of an HTML page's
    elements (what the page loads or links; script bodies are not parsed)."""
    from html.parser import HTMLParser

    found: list[str] = []

    class Parser(HTMLParser):
        def handle_starttag(self, tag, attrs):
            for name, value in attrs:
                if value and name in ("src", "href", "poster", "data-glb", "data-hdr", "data-packed"):
                    found.append(value)

    Parser().feed(text)
    return found


def job_counts(stdout: str) -> dict[str, int]:
    """Jobs per rule from the table ``snakemake -n`` prints (``Job stats:``; with ``total``)."""
    import re

    table = stdout[stdout.index("Job stats:") :]
    return {m[1]: int(m[2]) for m in re.finditer(r"^(\w+)\s+(\d+)$", table, re.M)}
