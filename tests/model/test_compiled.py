"""The compiled field (:mod:`stages.model.compiled`): what a compiled graph's kind depends on (the
settings marked as changing the compiled renderer, the light, the networks' settings, static
shapes) and the sources its marks are keyed by; the field's fallbacks where torch.compile cannot
build, refuses a graph or is not supported, and the metadata's words for each."""

from __future__ import annotations

import dataclasses
import logging
import subprocess
import sys

import pytest
import torch
from conftest import REPO, require_tool

from stages.config.sections import COMPILED_RENDERER, FieldSettings, OptimizeSettings
from stages.core import device as policy
from stages.model.compiled import (
    RENDERER_SOURCES,
    CompiledField,
    compile_kinds,
    compiled,
    networks_kind,
    renderer_kind,
    renderer_sources_digest,
    static_kind,
)
from stages.model.field import StyleField

CPU = torch.device("cpu")
GXX = (True, "C++ compiler /usr/bin/g++ (simulated)")


def _another_value(settings: FieldSettings, name: str):
    """Settings with ``name`` changed to another value they accept (None where none of the
    candidates is accepted: a relation or limit refuses them all)."""
    value, kind = getattr(settings, name), type(settings).kinds()[name]
    if kind.choices is not None:
        candidates = [c for c in kind.choices if c != value]
    elif kind.base is bool:
        candidates = [not value]
    elif kind.base in (int, float) and value is not None:
        candidates = [value + 1, value * 2, value - 1, value / 2 if kind.base is float else value // 2]
    elif kind.base in (int, float):
        candidates = [kind.base(1), kind.base(2)]
    else:
        candidates = []
    if kind.nullable and value is not None:
        candidates.append(None)
    for candidate in candidates:
        try:
            return dataclasses.replace(settings, **{name: candidate})
        except Exception:  # noqa: BLE001 - a value the settings refuse: try the next
            continue
    return None


def test_the_renderers_kind_changes_when_and_only_when_a_marked_setting_does():
    """Each field setting changed alone changes the compiled renderer's kind exactly where the
    setting is marked as changing the compiled renderer; the marks are the settings the renderer's
    graph was found to depend on, and the kind is the same for the optimisation's settings."""
    base = OptimizeSettings().field_settings()
    marked = FieldSettings.marked(COMPILED_RENDERER)
    assert set(marked) == {"brdf", "specular_lobe", "shadows", "light_rgb", "normal_network", "suns", "sun_samples", "bounces"}
    assert renderer_kind(base) == renderer_kind(OptimizeSettings())
    tried = set()
    for field in dataclasses.fields(FieldSettings):
        other = _another_value(base, field.name)
        if other is None:
            continue
        tried.add(field.name)
        changed = renderer_kind(other) != renderer_kind(base)
        assert changed == (field.name in marked), field.name
    assert set(marked) <= tried and len(tried) > 20, tried


def test_the_renderers_kind_follows_the_ray_cache_and_the_light():
    """Shadows as the ray cache allows (None: as the settings ask) and a fixed light (no gradient:
    another backward) are other kinds; the fast preset's fixed normals too (a cold compilation of
    67 s where the paper's renderer was marked)."""
    s = OptimizeSettings().field_settings()
    kind = renderer_kind(s)
    assert "brdf=gltf" in kind and "specular_lobe=fitted" in kind and kind.endswith("light=learned")
    assert renderer_kind(s, shadowed=True) == kind != renderer_kind(s, shadowed=False)
    assert renderer_kind(s, light_learns=False) != kind
    fixed = renderer_kind(OptimizeSettings(normal_network=False).field_settings())
    assert fixed != kind and "normal_network=False" in fixed and "normal_network=True" in kind


def test_the_one_graphs_kinds_add_the_networks_and_static_shapes():
    """The one graph's kind adds the networks' settings (all but the seed) and precision; with
    static shapes, its sizes (another size, another compilation)."""
    s = OptimizeSettings().field_settings()
    kind, whole, static = compile_kinds(s, None, True, True, (35440, 32))
    assert kind == renderer_kind(s) and whole == f"{kind}, {networks_kind(s, True)}"
    assert static == whole + static_kind(35440, 32)
    # another size is another compilation (and the doctor's, of sizes not yet known, one never made)
    for other in ((35441, 32), (35440, 31), (0, 0)):
        assert compile_kinds(s, None, True, True, other)[2] != static
    assert compile_kinds(s, None, True, True)[2] == whole + static_kind(0, 0)
    assert networks_kind(s, True) != networks_kind(s, False)
    assert networks_kind(s, True) != networks_kind(OptimizeSettings(width=128).field_settings(), True)
    assert networks_kind(s, True) == networks_kind(OptimizeSettings(seed=5).field_settings(), True)


def test_the_sources_digest_reads_the_renderers_code_and_tables():
    """Every file the compiled graphs are built from is in the digest: the renderer's modules and
    tables (in subpackages too), the field, its networks and this wrapper."""
    package = REPO / "stages"
    files = {p.relative_to(package).as_posix() for pattern in RENDERER_SOURCES for p in package.glob(pattern)}
    assert {"model/field.py", "model/networks.py", "model/compiled.py", "render/shading.py"} <= files
    assert any(f.startswith("render/data/") and f.endswith(".npz") for f in files)
    assert renderer_sources_digest() == renderer_sources_digest() and len(renderer_sources_digest()) == 64


def test_a_renderer_compiled_before_is_known_by_its_kind(monkeypatch, tmp_path):
    """The mark a successful compilation leaves: found for the same kind of renderer, not for
    another BRDF (the core's marks take the kind and the sources as given)."""
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "one"))
    sources = renderer_sources_digest()
    kind = renderer_kind(OptimizeSettings().field_settings())
    other = renderer_kind(OptimizeSettings(brdf="tango").field_settings())
    policy.mark_compiled(kind, CPU, sources)
    assert policy.compiled_before(kind, CPU, sources) and not policy.compiled_before(other, CPU, sources)


@pytest.mark.slow(minutes=0.5)
def test_a_compiler_that_cannot_build_costs_a_warning_not_the_run(tmp_path):
    """A compiler that is there but cannot build (``CXX=false``: it exits 1), with an empty
    inductor cache so that inductor must call it: the field compiles its renderer once when asked,
    the failure is logged, and it shades eager and says why; taken for real, in a process of its
    own (the failed compilation must not touch this one's torch.compile state)."""
    import os

    script = (
        "import torch\n"
        "from stages.config.sections import OptimizeSettings\n"
        "from stages.model.compiled import CompiledField\n"
        "from stages.model.field import StyleField\n"
        "f = CompiledField(StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings()))\n"
        "print(f.use_compiled_shading('on', torch.device('cpu'), 1))\n"
        "print(f.shade_graph is None)\n"
        "print(f.use_compiled_shading('on', torch.device('cpu'), 1, networks='on'))\n"
        "print(f.shade_graph is None and f.field_graph is None)\n"
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
        "from stages.model.compiled import CompiledField\n"
        "from stages.model.field import StyleField\n"
        "settings = OptimizeSettings(width=16, light_lobes=4).field_settings()\n"
        "f = CompiledField(StyleField(settings))\n"
        "with FlopCounterMode(display=False):\n"
        "    print(f.use_compiled_shading('on', torch.device('cpu'), 1))\n"
        "    print(f.use_compiled_shading('on', torch.device('cpu'), 1, networks='on'))\n"
        "g = CompiledField(StyleField(settings))\n"
        "print(g.use_compiled_shading('on', torch.device('cpu'), 1))\n"
        "print(g.shade_graph is None)\n"
        "print(g.use_compiled_shading('on', torch.device('cpu'), 1, networks='on'))\n"
        "print(g.shade_graph is None and g.field_graph is None)\n"
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

    x = torch.linspace(-1.0, 1.0, 7)
    graph = compiled(_doubled_sine, "gltf", CPU)
    assert torch.allclose(graph(x), 2.0 * torch.sin(x)) and graph.ran and graph.gave_up is None
    with caplog.at_level(logging.WARNING, logger="stages.model.compiled"), FlopCounterMode(display=False):
        assert torch.allclose(graph(x + 1.0), 2.0 * torch.sin(x + 1.0))
    assert graph.gave_up is not None and "no compiled frames" in graph.gave_up
    assert torch.allclose(graph(x), 2.0 * torch.sin(x))
    assert sum("gave up on _doubled_sine" in r.getMessage() for r in caplog.records) == 1
    f = CompiledField(StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings()))
    f._shading_path, f.shade_graph = "torch.compile (on)", graph
    assert f.shading_path.startswith("torch.compile (on); eager since torch.compile gave up (RuntimeError: ")
    fresh = compiled(lambda v: 3.0 * torch.cos(v), "gltf", CPU)
    with FlopCounterMode(display=False), pytest.raises(RuntimeError, match="no compiled frames"):
        fresh(x)


def test_a_platform_torch_compile_does_not_support_runs_eager(monkeypatch):
    """dynamo's own check says no (Windows and new Pythons in some releases): the renderer runs
    eager under on and auto, and the field says why, without trying to compile."""
    import torch._dynamo

    monkeypatch.setattr(torch._dynamo, "is_dynamo_supported", lambda: False)
    assert policy.compile_support(CPU) == (False, "torch.compile does not support this platform or Python")
    f = CompiledField(StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings()))
    monkeypatch.setattr(torch, "compile", lambda *a, **k: pytest.fail("compiled where torch.compile is not supported"))
    assert f.use_compiled_shading("on", CPU, 1) == "eager (torch.compile does not support this platform or Python)"
    assert f.use_compiled_shading("auto", CPU, 10_000) == "eager (auto: torch.compile does not support this platform or Python)"
    assert f.shade_graph is None


def test_a_pool_without_points_compiles_free_shapes(monkeypatch, caplog, tmp_path):
    """``compile_static: on`` with nothing to pad to (a training pool without hits) warns and
    compiles the one graph with free shapes, and the metadata's words do not say static."""
    sizes = []
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))  # (its mark goes there)
    monkeypatch.setattr(policy, "compile_support", lambda d: GXX)

    def one_graph(self, device, shadowed, size):  # built (no compilation needed to see the size asked for)
        sizes.append(size)
        self.field_graph = lambda *args: None

    monkeypatch.setattr(CompiledField, "_compile_one_graph", one_graph)
    f = CompiledField(StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings()))
    with caplog.at_level(logging.WARNING, logger="stages.model.compiled"):
        path = f.use_compiled_shading("on", CPU, 1, networks="on", static="on", points=0)
    assert sizes == [0] and "static" not in path and path.startswith("torch.compile, networks and renderer in one graph (")
    assert any("no points to pad to: free shapes" in r.getMessage() for r in caplog.records)


@pytest.mark.slow(minutes=0.5)
def test_a_graph_of_the_networks_that_fails_leaves_the_renderer_compiled(monkeypatch, caplog):
    """Where the networks' and renderer's graph cannot be built, the renderer is compiled alone,
    with a warning, and the metadata's words say so."""

    def fails(*args):
        raise RuntimeError("simulated")

    monkeypatch.setattr(CompiledField, "_first_field_pass", fails)
    f = CompiledField(StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings()))
    with caplog.at_level(logging.WARNING, logger="stages.model.compiled"):
        path = f.use_compiled_shading("on", CPU, 1, networks="on")
    assert f.field_graph is None and f.shade_graph is not None
    assert path.startswith("torch.compile (C++ compiler ") and path.endswith(
        "; the networks' graph failed: RuntimeError: simulated)"
    )
    assert any("the networks' and renderer's compilation failed" in r.getMessage() for r in caplog.records)


def test_the_compiled_field_is_the_fields_own_pass_until_a_graph_is_compiled():
    """Nothing compiled (``compile_shading: off``), or outside training: the wrapper's calls are
    the field's own, bit for bit, and the field keeps no compiled state of its own."""
    field = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    run = CompiledField(field)
    assert run.use_compiled_shading("off", CPU, 1) == "eager" == run.shading_path
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(50, 3, generator=g) * 2 - 1
    nrm = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    view = torch.nn.functional.normalize(nrm + 0.3 * torch.randn(50, 3, generator=g), dim=-1)
    for training in (True, False):
        field.train(training)
        torch.testing.assert_close(run(pts, nrm, view).shading.rgb, field(pts, nrm, view).shading.rgb, rtol=0, atol=0)
    assert not any(hasattr(field, name) for name in ("compiled_shade", "compiled_field", "static_points", "use_bf16"))
