"""The compiled renderer decided at run time (``optimize.compile_shading``: auto, on, off): auto
compiles on a CPU with a C++ compiler, and on CUDA with Triton, for runs long enough to repay the
compilation and stays eager elsewhere; on without a compiler warns and runs eager; what ran reaches the metadata. The
machine without a C++ compiler is taken for real (an empty PATH), not only simulated. (The compiled
field's kinds and fallbacks: ``tests/model/test_compiled.py``.)"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import pytest
import torch
from conftest import REPO, TINY_OPTIMIZE

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core import device as policy
from stages.core.errors import ConfigError
from stages.model.compiled import renderer_kind, renderer_sources_digest

CPU, CUDA = torch.device("cpu"), torch.device("cuda")
GXX = (True, "C++ compiler /usr/bin/g++ (simulated)")
NONE = (False, "no C++ compiler (simulated)")
LONG, SHORT = policy.COMPILE_MIN_ITERATIONS, policy.COMPILE_MIN_ITERATIONS - 1
WARM = policy.COMPILE_MIN_ITERATIONS_WARM
GPU_LONG = policy.COMPILE_MIN_ITERATIONS_CUDA
TRITON = (True, "Triton for CUDA (simulated)")
NO_TRITON = (False, "no Triton for inductor on CUDA (simulated)")
COLD_NOTE, WARM_NOTE = "not compiled on this machine before", "compiled before on this machine"
#: the sources a compiled program is built from, as a caller digests them (the core takes them as given)
SOURCES = "sources-digest"
#: the kinds compile_plan looks up, in a caller's words: the renderer's, the one graph's, and that
#: graph's with static shapes
KINDS = ("renderer", "renderer, networks", "renderer, networks, static shapes of 35440 points")


@pytest.mark.parametrize(
    ("setting", "device", "iterations", "warm", "support", "runs", "label"),
    [
        ("auto", CPU, LONG, False, GXX, True, f"torch.compile (auto: {LONG} iterations; {COLD_NOTE}; {GXX[1]})"),
        (
            "auto",
            CPU,
            SHORT,
            False,
            GXX,
            False,
            f"eager (auto: {SHORT} iterations, fewer than the {LONG} that repay a compilation; {COLD_NOTE})",
        ),
        ("auto", CPU, WARM, True, GXX, True, f"torch.compile (auto: {WARM} iterations; {WARM_NOTE}; {GXX[1]})"),
        (
            "auto",
            CPU,
            WARM - 1,
            True,
            GXX,
            False,
            f"eager (auto: {WARM - 1} iterations, fewer than the {WARM} that repay a compilation; {WARM_NOTE})",
        ),
        ("auto", CPU, LONG, False, NONE, False, "eager (auto: no C++ compiler (simulated))"),
        ("auto", CUDA, GPU_LONG, False, TRITON, True, f"torch.compile (auto: {GPU_LONG} iterations; {COLD_NOTE}; {TRITON[1]})"),
        # on CUDA a warm cache does not lower the threshold (its compilation was not timed there)
        (
            "auto",
            CUDA,
            GPU_LONG - 1,
            True,
            TRITON,
            False,
            f"eager (auto: {GPU_LONG - 1} iterations, fewer than the {GPU_LONG} that repay a compilation; {WARM_NOTE})",
        ),
        ("auto", CUDA, GPU_LONG, False, NO_TRITON, False, f"eager (auto: {NO_TRITON[1]})"),
        (
            "auto",
            torch.device("mps"),
            GPU_LONG,
            True,
            TRITON,
            False,
            "eager (auto: compiling the renderer on mps has not been measured to pay)",
        ),
        ("on", CUDA, 1, False, NO_TRITON, False, f"eager ({NO_TRITON[1]})"),
        ("on", CPU, 1, False, GXX, True, "torch.compile (C++ compiler /usr/bin/g++ (simulated))"),
        ("on", CPU, 1, False, NONE, False, "eager (no C++ compiler (simulated))"),
        ("off", CPU, LONG, True, GXX, False, "eager"),
        (True, CPU, 1, False, GXX, True, "torch.compile (C++ compiler /usr/bin/g++ (simulated))"),
        (False, CPU, LONG, False, GXX, False, "eager"),
    ],
)
def test_each_setting_on_each_kind_of_machine(monkeypatch, caplog, setting, device, iterations, warm, support, runs, label):
    monkeypatch.setattr(policy, "compile_support", lambda d: support)
    with caplog.at_level(logging.WARNING, logger="stages.core.device"):
        assert policy.compile_choice(setting, device, iterations, warm) == (runs, label)
    warned = [r.getMessage() for r in caplog.records]
    # only an explicit "on" that cannot be honoured warns: auto's eager renderer is a decision
    assert bool(warned) == (setting in ("on", True) and not support[0]), warned
    if warned:
        assert warned[0] == f"compile_shading asked for, but {support[1]}: the renderer runs eager"


def test_a_bad_setting_is_refused_by_name():
    with pytest.raises(ValueError, match=r"compile_shading must be one of auto, on, off, got 'yes'"):
        policy.compile_choice("yes", CPU, 10)
    with pytest.raises(ConfigError, match=r"compile_shading must be one of auto, on, off, got 'fast'"):
        OptimizeSettings(compile_shading="fast")
    assert (OptimizeSettings(compile_shading=True).compile_shading, OptimizeSettings().compile_shading) == ("on", "auto")


def test_the_compiler_is_found_on_the_path_or_through_cxx(monkeypatch, tmp_path):
    fake = tmp_path / "my-c++"
    fake.write_text("#!/bin/sh\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CXX", raising=False)
    assert policy.cpp_compiler() is None
    assert policy.compile_support(CPU) == (False, "no C++ compiler ($CXX, else g++) for inductor")
    monkeypatch.setenv("CXX", "my-c++")
    assert policy.cpp_compiler() == str(fake)
    assert policy.compile_support(CPU) == (True, f"C++ compiler {fake}")


@pytest.mark.parametrize("setting", ["on", "auto"])
def test_a_real_run_without_a_compiler_runs_eager_and_says_why(monkeypatch, cache, tmp_path, setting):
    """No C++ compiler on the PATH (the fallback a user without one takes): the run finishes with
    the eager renderer, and meta.json says which and why. Under auto, a run too short to repay a
    compilation stays eager whatever the machine has."""
    monkeypatch.setenv("PATH", str(tmp_path / "nothing-here"))
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))  # a machine that never compiled
    s = OptimizeSettings(**TINY_OPTIMIZE, clip_tiny_test=True, crops=0, normal_network=False, compile_shading=setting)
    optimize.run(cache / "train.npz", cache / "eval.npz", "a vase made of wood", tmp_path, s, "cpu")
    meta = json.loads((tmp_path / "meta.json").read_text())
    expect = {
        "on": "eager (no C++ compiler ($CXX, else g++) for inductor)",
        "auto": f"eager (auto: 3 iterations, fewer than the {LONG} that repay a compilation; {COLD_NOTE})",
    }[setting]
    assert meta["shading_path"] == expect and meta["settings"]["compile_shading"] == setting
    assert meta["cpu"] == policy.cpu_isa()  # what the timings and the precision depended on


def test_the_doctor_says_which_renderer_each_run_gets(monkeypatch, tmp_path):
    """The doctor's torch line names the renderer this config's trainings get: a paper-length
    variant compiled, the 3-iteration ones eager, each with its reason."""
    from stages import doctor
    from stages.config.workflow import WorkflowConfig

    monkeypatch.setattr(policy, "compile_support", lambda d: GXX)
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    cfg = WorkflowConfig(
        {
            "device": "cpu",
            "meshes": {"vase": {"builtin": "vase"}},
            "prompts": {"wood": {"text": "a {object} made of wood"}},
            "variants": {"short": {"optimize": {"iterations": 3}}, "paper": {}, "one": {"optimize": {"compile_networks": "on"}}},
            "optimize": {"clip_tiny_test": True, "compile_networks": "off"},
        }
    )
    detail = doctor.check_torch(cfg).detail
    assert "renderer: eager (auto: 3 iterations, fewer than the 1000" in detail
    assert f"torch.compile (auto: 1500 iterations; {COLD_NOTE}; C++ compiler /usr/bin/g++ (simulated))" in detail
    one = "torch.compile, networks and renderer in one graph (auto: 1500 iterations; "
    assert (
        f"{one}{COLD_NOTE}; C++ compiler /usr/bin/g++ (simulated); compile_networks: on; compile_static auto: on a CPU "
        "static shapes were measured slower (the padded points' arithmetic))"
    ) in detail


def test_the_doctor_knows_a_mesh_without_visibility_is_shaded_without_shadows(monkeypatch, tmp_path):
    """Its ray cache traces no visibility (``raycache.visibility: off``): the run compiles the
    renderer without shadows, so the doctor looks for that one's mark, not the shadowed one's."""
    from stages import doctor
    from stages.config.workflow import WorkflowConfig

    monkeypatch.setattr(policy, "compile_support", lambda d: GXX)
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    policy.mark_compiled(renderer_kind(OptimizeSettings(), shadowed=False), CPU, renderer_sources_digest())
    raw = {
        "device": "cpu",
        "meshes": {"vase": {"builtin": "vase"}},
        "prompts": {"wood": {"text": "a {object} made of wood"}},
        "optimize": {"clip_tiny_test": True, "iterations": WARM, "compile_networks": "off"},
    }
    warm = f"torch.compile (auto: {WARM} iterations; {WARM_NOTE}"
    assert warm not in doctor.check_torch(WorkflowConfig(raw)).detail  # shadows asked for: another renderer
    assert warm in doctor.check_torch(WorkflowConfig({**raw, "raycache": {"visibility": "off"}})).detail


def test_missing_python_headers_are_named(monkeypatch):
    monkeypatch.setattr(policy, "cpp_compiler", lambda: "/usr/bin/g++")
    monkeypatch.setattr(policy, "python_headers", lambda: None)
    assert policy.compile_support(CPU) == (False, "no Python headers (Python.h; Debian: python3-dev) for inductor")


def test_a_program_compiled_before_is_known_by_its_kind_sources_and_torch(monkeypatch, tmp_path):
    """The mark a successful compilation leaves in the inductor cache: found for the same kind and
    sources, not for another kind, other sources (the code changed), another torch or another
    cache (a machine that never compiled)."""
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "one"))
    kind, other = KINDS[0], KINDS[1]
    assert not policy.compiled_before(kind, CPU, SOURCES)
    policy.mark_compiled(kind, CPU, SOURCES)
    assert policy.compiled_before(kind, CPU, SOURCES) and not policy.compiled_before(other, CPU, SOURCES)
    assert not policy.compiled_before(kind, CPU, "other-sources")
    assert list((tmp_path / "one" / f"cpu-{policy.cpu_isa()}" / "stages-renderer").iterdir())  # this CPU's folder
    monkeypatch.setattr(torch, "__version__", "0.0.0")
    assert not policy.compiled_before(kind, CPU, SOURCES)
    monkeypatch.undo()
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "two"))
    assert not policy.compiled_before(kind, CPU, SOURCES)


def test_a_cache_that_cannot_be_written_only_means_the_next_run_decides_as_if_cold(monkeypatch, tmp_path):
    """The mark cannot be written (the cache folder is a file here; a read-only cache alike): no
    error, and the renderer counts as not compiled before."""
    blocked = tmp_path / "cache-is-a-file"
    blocked.write_text("")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(blocked))
    policy.mark_compiled(KINDS[0], CPU, SOURCES)
    assert not policy.compiled_before(KINDS[0], CPU, SOURCES)


#: compiled in a process of its own under an instruction set: a reduction, a matrix product and
#: pointwise functions, with dynamic sizes as the renderer's; prints its largest error against eager
ISA_SCRIPT = """
import torch
from stages.core.device import use_inductor_cache
use_inductor_cache()
torch.manual_seed(0)
def f(x, w):
    return torch.sigmoid(x @ w).exp().sum(-1) * x.norm(dim=-1)
x, w = torch.randn(1003, 37), torch.randn(37, 19)
print((torch.compile(f, dynamic=True)(x, w) - f(x, w)).abs().max().item())
"""
#: the instruction set below each one (``ATEN_CPU_CAPABILITY``), where a machine can take both
LOWER_ISA = {"AVX512": "avx2", "AVX2": "default"}


@pytest.mark.slow(minutes=0.5)
def test_code_compiled_under_one_instruction_set_is_not_read_back_under_another(tmp_path):
    """One project cache, two instruction sets (the nodes of a cluster sharing the project folder;
    here this CPU's own and the one below it, by ``ATEN_CPU_CAPABILITY``): each compiles its own
    code and gets eager's values. Inductor's cache keys neither: with one folder for both, the
    code generated for AVX-512 and read back under AVX2 gave errors of 300, the reverse a
    corrupted heap, and AVX2's under no vectors a compile error."""
    native = torch.backends.cpu.get_cpu_capability()
    if native not in LOWER_ISA:
        pytest.skip(f"no lower instruction set to take on this CPU ({native})")
    env = {k: v for k, v in os.environ.items() if k not in ("TORCHINDUCTOR_CACHE_DIR", "ATEN_CPU_CAPABILITY")}
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    for isa in (native.lower(), LOWER_ISA[native], native.lower()):
        proc = subprocess.run(
            [sys.executable, "-c", ISA_SCRIPT],
            capture_output=True,
            text=True,
            cwd=REPO,
            env={**env, "ATEN_CPU_CAPABILITY": isa},
            timeout=600,
        )
        assert proc.returncode == 0, f"{isa}: {proc.stderr[-2000:]}"
        assert float(proc.stdout.split()[-1]) < 1e-3, f"{isa}: {proc.stdout}"
    folders = sorted(p.name for p in (tmp_path / "cache" / "torchinductor").iterdir())
    assert len(folders) == 2 and all(f.startswith("cpu-") for f in folders), folders


def test_the_inductor_cache_is_the_projects_unless_the_user_names_one(monkeypatch, tmp_path):
    """``$XDG_CACHE_HOME/torchinductor`` (the project's ``.cache`` once activated), also where
    importing inductor has set ``TORCHINDUCTOR_CACHE_DIR`` to its own default (it did, and the
    renderer compiled into the temporary folder); a folder the user names is kept; each gets this
    CPU's folder inside, once."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    here = f"cpu-{policy.cpu_isa()}"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    for before in (None, default_cache_dir()):
        monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
        if before:
            monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", before)
        policy.use_inductor_cache()
        policy.use_inductor_cache()
        assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "xdg" / "torchinductor" / here)
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "mine" / "cpu-x86_64-avx2-00000000"))
    policy.use_inductor_cache()
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "mine" / here)


@pytest.mark.parametrize(
    ("setting", "device", "renderer", "bf16", "runs", "why"),
    [
        (
            "auto",
            CPU,
            True,
            True,
            False,
            "compile_networks auto: on a CPU one graph was measured no faster (bfloat16 networks here)",
        ),
        (
            "auto",
            CPU,
            True,
            False,
            False,
            "compile_networks auto: on a CPU one graph was measured no faster (float32 networks here)",
        ),
        ("auto", CUDA, True, True, True, "compile_networks auto: on CUDA one graph launches fewer kernels (measured faster)"),
        ("auto", CPU, False, True, False, "compile_networks: the renderer is not compiled"),
        ("on", CPU, True, False, True, "compile_networks: on"),
        ("on", CPU, False, True, False, "compile_networks: the renderer is not compiled"),
        ("off", CPU, True, True, False, "compile_networks: off"),
        (True, CUDA, True, False, True, "compile_networks: on"),
    ],
)
def test_the_networks_join_the_renderers_graph_only_where_asked(caplog, setting, device, renderer, bf16, runs, why):
    """``compile_networks``: auto keeps the networks out of the compiled renderer's graph on a CPU
    (measured no faster) and puts them in on CUDA (measured faster), on puts them in where the renderer is compiled,
    never without it; only an explicit on that cannot be honoured warns."""
    with caplog.at_level(logging.WARNING, logger="stages.core.device"):
        assert policy.compile_networks_choice(setting, device, renderer, bf16) == (runs, why)
    warned = [r.getMessage() for r in caplog.records]
    assert bool(warned) == (setting == "on" and not renderer), warned
    with pytest.raises(ConfigError, match=r"compile_networks must be one of auto, on, off, got 'fast'"):
        OptimizeSettings(compile_networks="fast")


def test_the_plan_looks_for_the_whole_graphs_mark_where_the_networks_join(monkeypatch, tmp_path):
    """A warm renderer alone does not make the one graph warm (its compilation is another): auto
    looks for the mark of what it would compile, and names it."""
    monkeypatch.setattr(policy, "compile_support", lambda d: GXX)
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    kind, whole = KINDS[:2]
    policy.mark_compiled(kind, CPU, SOURCES)
    plan = policy.compile_plan(("auto", "on"), CPU, WARM, KINDS, True, SOURCES)
    assert plan == (
        False,
        False,
        False,
        f"eager (auto: {WARM} iterations, fewer than the {LONG} that repay a compilation; {COLD_NOTE})",
    )
    policy.mark_compiled(whole, CPU, SOURCES)
    assert policy.compile_plan(("auto", "on"), CPU, WARM, KINDS, True, "other-sources")[0] is False  # the code changed
    assert policy.compile_plan(("auto", "on"), CPU, WARM, KINDS, True, SOURCES) == (
        True,
        True,
        False,
        f"torch.compile, networks and renderer in one graph (auto: {WARM} iterations; {WARM_NOTE}; {GXX[1]}; "
        "compile_networks: on)",
    )
    # auto: the renderer alone, whose own mark says its compilation is warm
    assert policy.compile_plan(("auto", "auto"), CPU, WARM, KINDS, True, SOURCES)[:2] == (True, False)
    assert policy.compile_plan(("auto", "off"), CPU, WARM, KINDS, True, SOURCES)[:2] == (True, False)


@pytest.mark.parametrize(
    ("setting", "device", "whole", "runs", "why"),
    [
        (
            "auto",
            CPU,
            True,
            False,
            "compile_static auto: on a CPU static shapes were measured slower (the padded points' arithmetic)",
        ),
        ("auto", CUDA, True, False, "compile_static auto: CUDA graphs have not been measured on cuda"),
        ("on", CPU, True, True, "compile_static: on, static shapes"),
        ("on", CUDA, True, True, "compile_static: on, CUDA graphs"),
        ("on", CUDA, False, False, "compile_static: no one graph"),
        ("auto", CUDA, False, False, "compile_static: no one graph"),
        ("off", CUDA, True, False, "compile_static: off"),
        (True, CPU, True, True, "compile_static: on, static shapes"),
    ],
)
def test_static_shapes_only_where_asked_and_only_in_one_graph(caplog, setting, device, whole, runs, why):
    """``compile_static``: auto leaves the one graph's shapes free (on a CPU measured no faster; on
    a GPU not measured), on fixes them (CUDA graphs on CUDA) where the networks are in the
    renderer's graph, never without it; only an explicit on that cannot be honoured warns."""
    with caplog.at_level(logging.WARNING, logger="stages.core.device"):
        assert policy.compile_static_choice(setting, device, whole) == (runs, why)
    warned = [r.getMessage() for r in caplog.records]
    assert bool(warned) == (setting == "on" and not whole), warned
    with pytest.raises(ConfigError, match=r"compile_static must be one of auto, on, off, got 'cuda'"):
        OptimizeSettings(compile_static="cuda")


def test_the_plan_of_a_graph_with_static_shapes(monkeypatch, tmp_path):
    """``compile_static: on`` names static shapes (CUDA graphs on CUDA) in what runs, and its
    compilation has its own mark: a warm one graph of free shapes does not make it warm."""
    monkeypatch.setattr(policy, "compile_support", lambda d: GXX)
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    policy.mark_compiled(KINDS[1], CPU, SOURCES)
    assert policy.compile_plan(("auto", "on", "off"), CPU, WARM, KINDS, True, SOURCES)[:3] == (True, True, False)
    assert policy.compile_plan(("auto", "on", "on"), CPU, WARM, KINDS, True, SOURCES)[:3] == (False, False, False)
    policy.mark_compiled(KINDS[2], CPU, SOURCES)
    # (another size is another kind: tests/model/test_compiled.py)
    assert policy.compile_plan(("auto", "on", "on"), CPU, WARM, KINDS, True, SOURCES) == (
        True,
        True,
        True,
        f"torch.compile, networks and renderer in one graph, static shapes (auto: {WARM} iterations; {WARM_NOTE}; "
        f"{GXX[1]}; compile_networks: on; compile_static: on, static shapes)",
    )
    assert policy.compile_plan(("on", "on", "on"), CUDA, 1, KINDS, True, SOURCES) == (
        True,
        True,
        True,
        f"torch.compile, networks and renderer in one graph as CUDA graphs ({GXX[1]}; compile_networks: on; "
        "compile_static: on, CUDA graphs)",
    )
    assert policy.compile_plan(("on", "on", "auto"), CUDA, 1, KINDS, True, SOURCES) == (
        True,
        True,
        False,
        f"torch.compile, networks and renderer in one graph ({GXX[1]}; compile_networks: on; "
        "compile_static auto: CUDA graphs have not been measured on cuda)",
    )


def test_the_settings_description_quotes_the_thresholds_auto_uses():
    """The configuration reference (generated from compile_shading's description) says the
    iterations from which auto compiles: the same numbers as the constants the choice reads."""
    import dataclasses

    from stages.core.settings import spec_of

    field = next(f for f in dataclasses.fields(OptimizeSettings) if f.name == "compile_shading")
    doc = spec_of(field).doc
    for n in (LONG, WARM, GPU_LONG):
        assert f"at least {n:,}" in doc or f"or {n:,} where" in doc, (n, doc)
