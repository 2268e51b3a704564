"""The compiled renderer decided at run time (``optimize.compile_shading``: auto, on, off): auto
compiles on a CPU with a C++ compiler, and on CUDA with Triton, for runs long enough to repay the
compilation and stays eager elsewhere; on without a compiler warns and runs eager; what ran reaches the metadata. The
machine without a C++ compiler is taken for real (an empty PATH), not only simulated."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import pytest
import torch
from conftest import REPO, TINY_OPTIMIZE, require_tool

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core import device as policy
from stages.core.errors import ConfigError

CPU, CUDA = torch.device("cpu"), torch.device("cuda")
GXX = (True, "C++ compiler /usr/bin/g++ (simulated)")
NONE = (False, "no C++ compiler (simulated)")
LONG, SHORT = policy.COMPILE_MIN_ITERATIONS, policy.COMPILE_MIN_ITERATIONS - 1
WARM = policy.COMPILE_MIN_ITERATIONS_WARM
GPU_LONG = policy.COMPILE_MIN_ITERATIONS_CUDA
TRITON = (True, "Triton for CUDA (simulated)")
NO_TRITON = (False, "no Triton for inductor on CUDA (simulated)")
COLD_NOTE, WARM_NOTE = "not compiled on this machine before", "compiled before on this machine"


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
    policy.mark_compiled(policy.renderer_kind(OptimizeSettings(), shadowed=False), CPU)
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


@pytest.mark.slow(minutes=0.5)
def test_a_compiler_that_cannot_build_costs_a_warning_not_the_run(tmp_path):
    """A compiler that is there but cannot build (``CXX=false``: it exits 1), with an empty
    inductor cache so that inductor must call it: the field compiles its renderer once when asked,
    the failure is logged, and it shades eager and says why; taken for real, in a process of its
    own (the failed compilation must not touch this one's torch.compile state)."""
    script = (
        "import torch\n"
        "from stages.config.sections import OptimizeSettings\n"
        "from stages.model.field import StyleField\n"
        "f = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())\n"
        "print(f.use_compiled_shading('on', torch.device('cpu'), 1))\n"
        "print(f.compiled_shade is None)\n"
        "print(f.use_compiled_shading('on', torch.device('cpu'), 1, networks='on'))\n"
        "print(f.compiled_shade is None and f.compiled_field is None)\n"
    )
    env = dict(os.environ, CXX="false", TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "inductor"))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    path, eager, path_both, eager_both = proc.stdout.strip().splitlines()[-4:]
    assert path.startswith("eager (the compilation failed: ") and eager == "True", proc.stdout
    assert path_both.startswith("eager (the compilation failed: ") and eager_both == "True", proc.stdout
    assert "compile_shading: the renderer's compilation failed" in proc.stderr
    assert "compile_shading: the networks' and renderer's compilation failed" in proc.stderr


def test_a_renderer_dynamo_gave_up_on_runs_eager_and_says_so():
    """Once a compiled function has run under a dispatch mode (a FLOP counter's, as a benchmark
    counts a step), dynamo skips its code for good (torch 2.13): a renderer compiled again in the
    same process would run eager while the metadata said compiled. Compiled as one graph or an
    error (``fullgraph``), the field's first pass fails instead: it shades eager and says so, the
    renderer alone and in one graph with the networks. In a process of its own (the skip is
    process-wide); it needs the C++ compiler that the compilation would use."""
    require_tool(policy.compile_support(CPU)[0], "no C++ compiler for inductor")
    script = (
        "import torch\n"
        "from torch.utils.flop_counter import FlopCounterMode\n"
        "from stages.config.sections import OptimizeSettings\n"
        "from stages.model.field import StyleField\n"
        "settings = OptimizeSettings(width=16, light_lobes=4).field_settings()\n"
        "f = StyleField(settings)\n"
        "with FlopCounterMode(display=False):\n"
        "    print(f.use_compiled_shading('on', torch.device('cpu'), 1))\n"
        "    print(f.use_compiled_shading('on', torch.device('cpu'), 1, networks='on'))\n"
        "g = StyleField(settings)\n"
        "print(g.use_compiled_shading('on', torch.device('cpu'), 1))\n"
        "print(g.compiled_shade is None)\n"
        "print(g.use_compiled_shading('on', torch.device('cpu'), 1, networks='on'))\n"
        "print(g.compiled_shade is None and g.compiled_field is None)\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    path, eager, path_both, eager_both = proc.stdout.strip().splitlines()[-4:]
    assert path.startswith("eager (the compilation failed: ") and "no compiled frames" in path and eager == "True", path
    assert path_both.startswith("eager (the compilation failed: ") and eager_both == "True", path_both
    assert "compile_shading: the renderer's compilation failed" in proc.stderr


def _doubled_sine(x):
    return 2.0 * torch.sin(x)


def test_a_graph_dynamo_refuses_during_training_runs_eager_from_there_and_says_so(caplog):
    """A compiled graph whose later call dynamo refuses (here: its code skipped once a call ran
    under a dispatch mode; in training, a recompilation past dynamo's limit or with a graph break)
    runs that call and the rest eager, warned once, and the field's ``shading_path`` says so; a
    first call's refusal is raised (the field then falls back before training and says why)."""
    from torch.utils.flop_counter import FlopCounterMode

    from stages.model.field import StyleField, compiled

    x = torch.linspace(-1.0, 1.0, 7)
    graph = compiled(_doubled_sine, "gltf", CPU)
    assert torch.allclose(graph(x), 2.0 * torch.sin(x)) and graph.ran and graph.gave_up is None
    with caplog.at_level(logging.WARNING, logger="stages.model.field"), FlopCounterMode(display=False):
        assert torch.allclose(graph(x + 1.0), 2.0 * torch.sin(x + 1.0))
    assert graph.gave_up is not None and "no compiled frames" in graph.gave_up
    assert torch.allclose(graph(x), 2.0 * torch.sin(x))
    assert sum("gave up on _doubled_sine" in r.getMessage() for r in caplog.records) == 1
    f = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    f._shading_path, f.compiled_shade = "torch.compile (on)", graph
    assert f.shading_path.startswith("torch.compile (on); eager since torch.compile gave up (RuntimeError: ")
    fresh = compiled(lambda v: 3.0 * torch.cos(v), "gltf", CPU)
    with FlopCounterMode(display=False), pytest.raises(RuntimeError, match="no compiled frames"):
        fresh(x)


def test_a_renderer_compiled_before_is_known_by_its_kind_code_and_torch(monkeypatch, tmp_path):
    """The mark a successful compilation leaves in the inductor cache: found for the same kind of
    renderer, not for another kind, another torch or another cache (a machine that never compiled)."""
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "one"))
    kind = policy.renderer_kind(OptimizeSettings().field_settings())
    other = policy.renderer_kind(OptimizeSettings(brdf="tango").field_settings())
    assert kind != other and "gltf BRDF, fitted lobe" in kind
    # the fast preset has no normal network: its normal takes no gradient, another backward (a
    # cold compilation of 67 s where the paper's renderer was marked)
    fixed = policy.renderer_kind(OptimizeSettings(normal_network=False).field_settings())
    assert fixed != kind and fixed.endswith("fixed normals") and kind.endswith("learned normals")
    assert not policy.compiled_before(kind, CPU)
    policy.mark_compiled(kind, CPU)
    assert policy.compiled_before(kind, CPU) and not policy.compiled_before(other, CPU)
    assert list((tmp_path / "one" / f"cpu-{policy.cpu_isa()}" / "stages-renderer").iterdir())  # this CPU's folder
    monkeypatch.setattr(torch, "__version__", "0.0.0")
    assert not policy.compiled_before(kind, CPU)
    monkeypatch.undo()
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "two"))
    assert not policy.compiled_before(kind, CPU)


def test_a_platform_torch_compile_does_not_support_runs_eager(monkeypatch):
    """dynamo's own check says no (Windows and new Pythons in some releases): the renderer runs
    eager under on and auto, and the field says why, without trying to compile."""
    import torch._dynamo

    from stages.model.field import StyleField

    monkeypatch.setattr(torch._dynamo, "is_dynamo_supported", lambda: False)
    assert policy.compile_support(CPU) == (False, "torch.compile does not support this platform or Python")
    f = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    monkeypatch.setattr(torch, "compile", lambda *a, **k: pytest.fail("compiled where torch.compile is not supported"))
    assert f.use_compiled_shading("on", CPU, 1) == "eager (torch.compile does not support this platform or Python)"
    assert f.use_compiled_shading("auto", CPU, 10_000) == "eager (auto: torch.compile does not support this platform or Python)"
    assert f.compiled_shade is None


def test_a_cache_that_cannot_be_written_only_means_the_next_run_decides_as_if_cold(monkeypatch, tmp_path):
    """The mark cannot be written (the cache folder is a file here; a read-only cache alike): no
    error, and the renderer counts as not compiled before."""
    blocked = tmp_path / "cache-is-a-file"
    blocked.write_text("")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(blocked))
    kind = policy.renderer_kind(OptimizeSettings().field_settings())
    policy.mark_compiled(kind, CPU)
    assert not policy.compiled_before(kind, CPU)


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
        ("auto", CUDA, True, True, False, "compile_networks auto: one graph has not been measured on cuda"),
        ("auto", CPU, False, True, False, "compile_networks: the renderer is not compiled"),
        ("on", CPU, True, False, True, "compile_networks: on"),
        ("on", CPU, False, True, False, "compile_networks: the renderer is not compiled"),
        ("off", CPU, True, True, False, "compile_networks: off"),
        (True, CUDA, True, False, True, "compile_networks: on"),
    ],
)
def test_the_networks_join_the_renderers_graph_only_where_asked(caplog, setting, device, renderer, bf16, runs, why):
    """``compile_networks``: auto keeps the networks out of the compiled renderer's graph (on a CPU
    measured no faster; on a GPU not measured), on puts them in where the renderer is compiled,
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
    s = OptimizeSettings()
    kind = policy.renderer_kind(s.field_settings())
    whole = f"{kind}, {policy.networks_kind(s.field_settings(), True)}"
    assert whole != f"{kind}, {policy.networks_kind(s.field_settings(), False)}"
    assert whole != f"{kind}, {policy.networks_kind(OptimizeSettings(width=128).field_settings(), True)}"
    assert whole == f"{kind}, {policy.networks_kind(OptimizeSettings(seed=5).field_settings(), True)}"
    policy.mark_compiled(kind, CPU)
    plan = policy.compile_plan(("auto", "on"), CPU, WARM, (kind, whole), True)
    assert plan == (
        False,
        False,
        False,
        f"eager (auto: {WARM} iterations, fewer than the {LONG} that repay a compilation; {COLD_NOTE})",
    )
    policy.mark_compiled(whole, CPU)
    assert policy.compile_plan(("auto", "on"), CPU, WARM, (kind, whole), True) == (
        True,
        True,
        False,
        f"torch.compile, networks and renderer in one graph (auto: {WARM} iterations; {WARM_NOTE}; {GXX[1]}; "
        "compile_networks: on)",
    )
    # auto: the renderer alone, whose own mark says its compilation is warm
    assert policy.compile_plan(("auto", "auto"), CPU, WARM, (kind, whole), True)[:2] == (True, False)
    assert policy.compile_plan(("auto", "off"), CPU, WARM, (kind, whole), True)[:2] == (True, False)


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
    s = OptimizeSettings()
    kind = policy.renderer_kind(s.field_settings())
    whole = f"{kind}, {policy.networks_kind(s.field_settings(), True)}"
    policy.mark_compiled(whole, CPU)
    shape = (35440, 32)
    assert policy.compile_plan(("auto", "on", "off"), CPU, WARM, (kind, whole), True, shape)[:3] == (True, True, False)
    assert policy.compile_plan(("auto", "on", "on"), CPU, WARM, (kind, whole), True, shape)[:3] == (False, False, False)
    policy.mark_compiled(whole + policy.static_kind(*shape), CPU)
    # another size is another compilation: cold (and the doctor's, of sizes not yet known)
    for other in ((35441, 32), (35440, 31), (0, 0)):
        assert policy.compile_plan(("auto", "on", "on"), CPU, WARM, (kind, whole), True, other)[:3] == (False, False, False)
    assert policy.compile_plan(("auto", "on", "on"), CPU, WARM, (kind, whole), True, shape) == (
        True,
        True,
        True,
        f"torch.compile, networks and renderer in one graph, static shapes (auto: {WARM} iterations; {WARM_NOTE}; "
        f"{GXX[1]}; compile_networks: on; compile_static: on, static shapes)",
    )
    assert policy.compile_plan(("on", "on", "on"), CUDA, 1, (kind, whole), True) == (
        True,
        True,
        True,
        f"torch.compile, networks and renderer in one graph as CUDA graphs ({GXX[1]}; compile_networks: on; "
        "compile_static: on, CUDA graphs)",
    )
    assert policy.compile_plan(("on", "on", "auto"), CUDA, 1, (kind, whole), True) == (
        True,
        True,
        False,
        f"torch.compile, networks and renderer in one graph ({GXX[1]}; compile_networks: on; "
        "compile_static auto: CUDA graphs have not been measured on cuda)",
    )


def test_a_pool_without_points_compiles_free_shapes(monkeypatch, caplog, tmp_path):
    """``compile_static: on`` with nothing to pad to (a training pool without hits) warns and
    compiles the one graph with free shapes, and the metadata's words do not say static."""
    from stages.model.field import StyleField

    sizes = []
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))  # (its mark goes there)
    monkeypatch.setattr(policy, "compile_support", lambda d: GXX)

    def one_graph(self, device, shadowed, size):  # built (no compilation needed to see the size asked for)
        sizes.append(size)
        self.compiled_field = lambda *args: None

    monkeypatch.setattr(StyleField, "_compile_one_graph", one_graph)
    f = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    with caplog.at_level(logging.WARNING, logger="stages.model.field"):
        path = f.use_compiled_shading("on", CPU, 1, networks="on", static="on", points=0)
    assert sizes == [0] and "static" not in path and path.startswith("torch.compile, networks and renderer in one graph (")
    assert any("no points to pad to: free shapes" in r.getMessage() for r in caplog.records)


@pytest.mark.slow(minutes=0.5)
def test_a_graph_of_the_networks_that_fails_leaves_the_renderer_compiled(monkeypatch, caplog):
    """Where the networks' and renderer's graph cannot be built, the renderer is compiled alone,
    with a warning, and the metadata's words say so."""
    from stages.model.field import StyleField

    def fails(*args):
        raise RuntimeError("simulated")

    monkeypatch.setattr(StyleField, "_first_field_pass", fails)
    f = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    with caplog.at_level(logging.WARNING, logger="stages.model.field"):
        path = f.use_compiled_shading("on", CPU, 1, networks="on")
    assert f.compiled_field is None and f.compiled_shade is not None
    assert path.startswith("torch.compile (C++ compiler ") and path.endswith(
        "; the networks' graph failed: RuntimeError: simulated)"
    )
    assert any("the networks' and renderer's compilation failed" in r.getMessage() for r in caplog.records)


def test_the_settings_description_quotes_the_thresholds_auto_uses():
    """The configuration reference (generated from compile_shading's description) says the
    iterations from which auto compiles: the same numbers as the constants the choice reads."""
    import dataclasses

    from stages.core.settings import spec_of

    field = next(f for f in dataclasses.fields(OptimizeSettings) if f.name == "compile_shading")
    doc = spec_of(field).doc
    for n in (LONG, WARM, GPU_LONG):
        assert f"at least {n:,}" in doc or f"or {n:,} where" in doc, (n, doc)
