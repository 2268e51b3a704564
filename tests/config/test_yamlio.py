"""The project's bounded YAML reader (stages/config/yamlio.py): a config from someone else is read
as data, in bounded time and memory, and every refusal is one line naming the file and what to do."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from conftest import REPO

from stages.config import yamlio
from stages.config.workflow import ConfigError, WorkflowConfig, read_yaml
from stages.config.yamlio import MAX_DEPTH, MAX_VALUES, expanded_values, load_yaml

BASE = "meshes:\n  vase: {builtin: vase}\nprompts:\n  wood: 'a {object} made of wood'\n"


def alias_bomb(levels: int = 8) -> str:
    """A 521-byte-class "billion laughs": 10^(levels + 1) values under unknown keys."""
    lines = ['a0: &a0 ["x","x","x","x","x","x","x","x","x","x"]']
    lines += [f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n" + BASE


def one_line_error(text: str, path=None) -> str:
    with pytest.raises(ConfigError) as err:
        if path is None:
            load_yaml(text, "c.yaml")
        else:
            path.write_text(text)
            read_yaml(path)
    message = str(err.value)
    assert "\n" not in message and len(message) < 400, message
    return message


def test_an_alias_bomb_is_refused_at_once():
    t0 = time.perf_counter()
    message = one_line_error(alias_bomb())
    assert time.perf_counter() - t0 < 2.0
    assert "expand to more than 200,000 values" in message and message.startswith("c.yaml: ")
    # the count is that of the expanded document, each shared node visited once
    import yaml

    def values(x) -> int:  # the expanded document, walked as any later reader walks it
        if isinstance(x, dict):
            return 1 + sum(values(k) + values(v) for k, v in x.items())
        if isinstance(x, list):
            return 1 + sum(values(v) for v in x)
        return 1

    small = alias_bomb(2)
    assert expanded_values(yaml.compose(small)) == values(yaml.safe_load(small)) > 1000
    assert expanded_values(yaml.compose(alias_bomb())) == MAX_VALUES + 1  # stops counting past the limit


def test_aliases_within_the_bound_are_data():
    text = "shared: &s {iterations: 50, lr: 0.01}\n" + BASE + "optimize: *s\n"
    data = load_yaml(text, "c.yaml")
    assert data["optimize"] == {"iterations": 50, "lr": 0.01}


def test_deep_nesting_is_one_line():
    for depth in (MAX_DEPTH + 1, 20_000):
        message = one_line_error("a: " + "[" * depth + "]" * depth + "\n")
        assert f"nested deeper than {MAX_DEPTH} levels" in message
    assert load_yaml("a: " + "[" * (MAX_DEPTH - 2) + "]" * (MAX_DEPTH - 2), "c.yaml")


def test_a_duplicate_key_names_both_lines(tmp_path):
    text = BASE + "optimize:\n  iterations: 10\nraycache: {views: 8}\noptimize:\n  lr: 0.01\n"
    message = one_line_error(text, tmp_path / "dup.yaml")
    assert "key 'optimize' appears twice in one mapping (lines 5 and 8)" in message and "dup.yaml" in message
    nested = BASE + "optimize: {iterations: 10, iterations: 20}\n"
    assert "key 'iterations' appears twice" in one_line_error(nested)
    # a merge key is YAML's own way of overriding: not a duplicate
    assert load_yaml("a: &a {x: 1}\nb:\n  <<: *a\n  x: 2\n", "c.yaml")["b"] == {"x": 2}


def test_a_yte_template_is_refused_by_the_projects_loaders(tmp_path, monkeypatch):
    path = tmp_path / "yte.yaml"
    path.write_text("__use_yte__: true\n" + BASE)
    monkeypatch.delenv("TANGO_ALLOW_YTE", raising=False)
    with pytest.raises(ConfigError, match="evaluates such a file as a YTE template") as err:
        read_yaml(path)
    assert "TANGO_ALLOW_YTE=1" in str(err.value)


def test_the_check_command_reads_a_received_config_as_data(tmp_path, capsys, monkeypatch):
    from stages.config.workflow import main

    monkeypatch.delenv("TANGO_ALLOW_YTE", raising=False)
    good = tmp_path / "good.yaml"
    good.write_text(BASE)
    assert main(["--configfile", str(good), "--check"]) == 0
    assert "a valid config of 1 mesh x 1 prompt x 1 variant = 1 cell; no template" in capsys.readouterr().out
    bad = tmp_path / "yte.yaml"
    bad.write_text("__use_yte__: true\n" + BASE)
    assert main(["--configfile", str(bad), "--check"]) == 2


def test_integers_given_as_floats_are_refused_naming_the_key():
    for section, key in (("raycache", "views"), ("optimize", "iterations"), ("raycache", "resolution")):
        with pytest.raises(ConfigError) as err:
            WorkflowConfig({**load_yaml(BASE, "c"), section: {key: 8.0}})
        assert f"{section} -> {key}: 8.0 is not an integer: write 8" in str(err.value)
    with pytest.raises(ConfigError, match="is not of type integer"):
        WorkflowConfig({**load_yaml(BASE, "c"), "optimize": {"iterations": 8.5}})
    with pytest.raises(ConfigError, match="is not of type integer"):
        WorkflowConfig({**load_yaml(BASE, "c"), "optimize": {"checkpoint_every": True}})


def test_not_a_config_file_is_one_line(tmp_path):
    assert "not a file" in one_line_error_path(tmp_path)
    (tmp_path / "bin.yaml").write_bytes(b"a: \xff\xfe\n")
    with pytest.raises(ConfigError, match="not UTF-8 text"):
        read_yaml(tmp_path / "bin.yaml")


def one_line_error_path(path) -> str:
    with pytest.raises(ConfigError) as err:
        read_yaml(path)
    assert "\n" not in str(err.value)
    return str(err.value)


@pytest.mark.slow
@pytest.mark.parametrize(
    "case",
    ["bomb", "duplicate", "yte", "float", "hexadecimal", "alias_in_itself", "alias_chain", "deep"],
)
def test_the_workflow_refuses_before_it_walks_the_values(case, tmp_path):
    """Under Snakemake (which loads the file itself first, and evaluates a YTE template before any
    project code runs) the workflow reads each config file again through the bounded reader and
    stops with one line; a YTE config goes on only with TANGO_ALLOW_YTE=1 set by the user."""
    texts = {
        "bomb": alias_bomb(),
        "duplicate": BASE + "optimize: {iterations: 10}\noptimize: {lr: 0.01}\n",
        "yte": "__use_yte__: true\n" + BASE,
        "float": BASE + "raycache: {views: 8.0}\n",
        "hexadecimal": BASE + "raycache: {views: 0x10}\n",
        "alias_in_itself": "a: &a [*a]\n" + BASE,
        "alias_chain": "a0: &a0 [1]\n" + "".join(f"a{i}: &a{i} [*a{i - 1}]\n" for i in range(1, 600)) + BASE,
        "deep": BASE + "x: " + "[" * 400 + "]" * 400 + "\n",  # within what Snakemake's reader holds
    }
    needles = {
        "bomb": "expand to more than",
        "duplicate": "key 'optimize' appears twice",
        "yte": "YTE template",
        "float": "8.0 is not an integer",
        "hexadecimal": "0x10 is a hexadecimal number, which YAML 1.1 reads as 16: write 16",
        "alias_in_itself": "an alias (*name) of the value it stands in",
        "alias_chain": "through its aliases",
        "deep": f"nested deeper than {MAX_DEPTH} levels",
    }
    path = tmp_path / f"{case}.yaml"
    path.write_text(texts[case])
    cmd = [sys.executable, "-m", "snakemake", "-n", "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp_path)]
    t0 = time.perf_counter()
    proc = subprocess.run([*cmd, "--configfile", str(path)], capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and needles[case] in out and "Traceback" not in out, out[-2000:]
    assert time.perf_counter() - t0 < 60
    if case == "yte":
        env = {**__import__("os").environ, "TANGO_ALLOW_YTE": "1"}
        ok = subprocess.run([*cmd, "--configfile", str(path)], capture_output=True, text=True, timeout=120, env=env)
        assert ok.returncode == 0, (ok.stdout + ok.stderr)[-2000:]


#: YAML 1.1's other forms of a number, and the number each stands for
NUMBER_FORMS = {
    "hexadecimal": ("0x10", "0x10 is a hexadecimal number, which YAML 1.1 reads as 16: write 16"),
    "octal": ("020", "020 is an octal number (a leading zero), which YAML 1.1 reads as 16: write 16 (or 20 if that was meant)"),
    "sexagesimal": ("1:30", "1:30 is a base-60 number, which YAML 1.1 reads as 90: write 90"),
    "binary": ("0b10000", "0b10000 is a binary number, which YAML 1.1 reads as 16: write 16"),
    "separators": ("1_6", "1_6 is a number with digit separators (_), which YAML 1.1 reads as 16: write 16"),
    "explicit_tag": ("!!int '0x10'", "0x10 is a hexadecimal number, which YAML 1.1 reads as 16: write 16"),
    "sexagesimal_float": ("0:0.5", "0:0.5 is a base-60 number, which YAML 1.1 reads as 0.5: write 0.5"),
    "float_separators": (
        "0.000_5",
        "0.000_5 is a number with digit separators (_), which YAML 1.1 reads as 0.0005: write 0.0005",
    ),
}


@pytest.mark.parametrize("case", sorted(NUMBER_FORMS))
def test_yaml_1_1_number_forms_are_refused_naming_the_key(case, tmp_path):
    text, want = NUMBER_FORMS[case]
    key = "lr" if "float" in case else "iterations"
    message = one_line_error(BASE + f"optimize:\n  {key}: {text}\n", tmp_path / "forms.yaml")
    assert f"forms.yaml: invalid value at optimize -> {key} (line 6): {want}" in message, message
    # in a list, a mapping's key, a mesh entry: wherever a value is read
    assert "raycache -> eval_elevations_deg -> 1 (line 2)" in one_line_error(f"raycache:\n  eval_elevations_deg: [0, {text}]\n")
    assert "invalid value at 0x20 (line 1)" in one_line_error("0x20: 1\n" + BASE)


def test_decimal_numbers_and_quoted_texts_pass():
    data = load_yaml(BASE + "optimize: {iterations: +16, seed: 0, lr: .5e-3, gamma: 0.7, weight_decay: -0.0, lr2: 5.0e+3}\n", "c")
    assert data["optimize"] == {"iterations": 16, "seed": 0, "lr": 0.5e-3, "gamma": 0.7, "weight_decay": 0.0, "lr2": 5000.0}
    assert load_yaml("a: '0x10'\nb: \"1:30\"\nc: 08\nd: 1e3\n", "c") == {"a": "0x10", "b": "1:30", "c": "08", "d": "1e3"}


def test_numbers_yaml_1_1_leaves_texts_say_which_number_to_write():
    """``0o20`` (YAML 1.2's octal) and ``1e-3`` (no point) are texts to YAML 1.1: the key is named
    with the number to write."""
    for section, key, text, want in (
        ("raycache", "views", "0o20", "write 16"),
        ("optimize", "lr", "1e-3", "write 0.001"),
        ("optimize", "iterations", "1e3", "write 1000"),
    ):
        with pytest.raises(ConfigError) as err:
            WorkflowConfig(load_yaml(BASE + f"{section}:\n  {key}: {text}\n", "c.yaml"))
        assert f"invalid value at {section} -> {key}: '{text}' is a text to YAML 1.1, not " in str(err.value)
        assert str(err.value).endswith(want), str(err.value)


def test_aliases_that_hold_themselves_or_nest_deep_are_one_line():
    assert "an alias (*name) of the value it stands in" in one_line_error("a: &a [*a]\n" + BASE)
    assert "optimize -> lr (line 1): an alias" in one_line_error("optimize: &o {lr: *o}\n" + BASE)
    chain = "a0: &a0 [1]\n" + "".join(f"a{i}: &a{i} [*a{i - 1}]\n" for i in range(1, 600))
    assert f"nested deeper than {MAX_DEPTH} levels through its aliases" in one_line_error(chain + BASE)
    shared = "a: &a [1, 2]\nb: [*a, *a, [*a]]\n" + BASE  # used twice, not inside itself
    assert load_yaml(shared, "c.yaml")["b"] == [[1, 2], [1, 2], [[1, 2]]]


def test_allow_yte_is_read_from_the_environment_the_process_started_with(tmp_path, monkeypatch):
    """A template runs while Snakemake loads it, in the process that then checks it: a change it
    makes to ``os.environ`` is not the environment the run was started with."""
    if not yamlio.INITIAL_ENVIRON.is_file():
        pytest.skip(f"{yamlio.INITIAL_ENVIRON} is absent here (not Linux)")
    if yamlio.initial_environment().get("TANGO_ALLOW_YTE") == "1":
        pytest.skip("this test process was started with TANGO_ALLOW_YTE=1")
    path = tmp_path / "yte.yaml"
    path.write_text("__use_yte__: true\n" + BASE)
    monkeypatch.setenv("TANGO_ALLOW_YTE", "1")  # what a template could do while it is evaluated
    with pytest.raises(ConfigError, match="evaluates such a file as a YTE template"):
        read_yaml(path)


def test_without_proc_the_current_environment_decides(tmp_path, monkeypatch):
    """Where the system has no ``/proc/self/environ`` (macOS), ``os.environ`` is what there is."""
    monkeypatch.setattr(yamlio, "INITIAL_ENVIRON", tmp_path / "absent")
    path = tmp_path / "yte.yaml"
    path.write_text("__use_yte__: true\n" + BASE)
    monkeypatch.delenv("TANGO_ALLOW_YTE", raising=False)
    with pytest.raises(ConfigError, match="YTE template"):
        read_yaml(path)
    monkeypatch.setenv("TANGO_ALLOW_YTE", "1")
    assert read_yaml(path)["meshes"] == {"vase": {"builtin": "vase"}}
    assert yamlio.initial_environment() is os.environ


#: a template that sets the switch while Snakemake evaluates it (the experiment's name is its cover)
SETS_THE_SWITCH = (
    "__use_yte__: true\n" + BASE + 'experiment: ?__import__("os").environ.setdefault("TANGO_ALLOW_YTE", "1") and "yte"\n'
)


def snakemake_dry_run(folder, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-n", "--snakefile", str(REPO / "Snakefile"), "--directory", str(folder)]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=120, env=env)


@pytest.mark.slow
def test_a_template_that_sets_the_switch_does_not_let_the_workflow_go_on(tmp_path):
    path = tmp_path / "sets.yaml"
    path.write_text(SETS_THE_SWITCH)
    env = {k: v for k, v in os.environ.items() if k != "TANGO_ALLOW_YTE"}
    proc = snakemake_dry_run(tmp_path, "--configfile", str(path), env=env)
    assert proc.returncode != 0 and "YTE template" in proc.stdout + proc.stderr, (proc.stdout + proc.stderr)[-2000:]
    allowed = snakemake_dry_run(tmp_path, "--configfile", str(path), env={**env, "TANGO_ALLOW_YTE": "1"})
    assert allowed.returncode == 0, (allowed.stdout + allowed.stderr)[-2000:]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["deep", "template"])
def test_the_default_config_is_read_as_data_before_snakemake_reads_it(case, tmp_path):
    """Without --configfile the workflow reads config/config.yaml through the bounded reader before
    Snakemake's own reader: a file nested 5,000 deep (which Snakemake's reader cannot hold) is one
    line, and a template is refused before Snakemake evaluates it (it would write a file)."""
    (tmp_path / "config").mkdir()
    texts = {
        "deep": BASE + "x: " + "[" * 5000 + "]" * 5000 + "\n",
        "template": "__use_yte__: true\n" + BASE + 'experiment: ?open("ran", "w").write("x") and "yte"\n',
    }
    (tmp_path / "config" / "config.yaml").write_text(texts[case])
    env = {k: v for k, v in os.environ.items() if k != "TANGO_ALLOW_YTE"}
    proc = snakemake_dry_run(tmp_path, env=env)
    out = proc.stdout + proc.stderr
    want = f"nested deeper than {MAX_DEPTH} levels" if case == "deep" else "YTE template"
    assert proc.returncode != 0 and want in out and "Traceback" not in out, out[-2000:]
    assert not (tmp_path / "ran").exists()
