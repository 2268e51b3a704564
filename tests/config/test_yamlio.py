"""The project's bounded YAML reader (stages/config/yamlio.py): a config from someone else is read
as data, in bounded time and memory, and every refusal is one line naming the file and what to do."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from conftest import REPO

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
    assert "a valid config of 1 cells (1 meshes x 1 prompts x 1 variants); no template" in capsys.readouterr().out
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
    ["bomb", "duplicate", "yte", "float"],
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
    }
    needles = {
        "bomb": "expand to more than",
        "duplicate": "key 'optimize' appears twice",
        "yte": "YTE template",
        "float": "8.0 is not an integer",
    }
    path = tmp_path / f"{case}.yaml"
    path.write_text(texts[case])
    cmd = [sys.executable, "-m", "snakemake", "-n", "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp_path)]
    t0 = time.perf_counter()
    proc = subprocess.run([*cmd, "--configfile", str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and needles[case] in proc.stdout + proc.stderr, (proc.stdout + proc.stderr)[-2000:]
    assert time.perf_counter() - t0 < 60
    if case == "yte":
        env = {**__import__("os").environ, "TANGO_ALLOW_YTE": "1"}
        ok = subprocess.run([*cmd, "--configfile", str(path)], capture_output=True, text=True, timeout=120, env=env)
        assert ok.returncode == 0, (ok.stdout + ok.stderr)[-2000:]
