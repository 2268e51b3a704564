"""Hostile input through the workflow: prompts are data from the config to every stage's command
line (leading dashes, quotes, shell syntax, mathtext), and the loss plot draws any of them."""

from __future__ import annotations

import shlex

import pytest
import yaml
from conftest import run_snakemake

#: prompts that broke (or would break) a command line, a shell or a plot title
HOSTILE_PROMPTS = {
    "dash": "-glossy",
    "double_dash": "--out-dir=/tmp/elsewhere",
    "quotes": "a \"wooden\" vase's 'lid'",
    "shell": "a vase $(touch pwned) `id` ; rm -rf ~ && echo | cat > x",
    "mathtext": r"a $\wood$ vase $x^2$",
    "unicode": "a vase of \u05e2\u05e5 (wood) with e\u0301\u0301 accents",
}


def stage_argv(dry_run_output: str, module: str) -> list[str]:
    """The arguments the printed shell line passes to ``python -m <module>`` (before its ``2>``)."""
    lines = [line for line in dry_run_output.splitlines() if f"-m {module} " in line]
    assert lines, f"no {module} command in the dry run"
    words = shlex.split(lines[0].split(" 2> ")[0])
    return words[words.index(module) + 1 :]


@pytest.mark.parametrize("kind", sorted(HOSTILE_PROMPTS))
def test_a_hostile_prompt_reaches_the_stages_as_data(tmp_path, monkeypatch, kind):
    """The rules' shell lines, as Snakemake prints them, give the optimize and metrics stages the
    prompt unchanged (a leading dash is not an option, a ``$(...)`` is not run)."""
    from stages import metrics, optimize

    prompt = HOSTILE_PROMPTS[kind]
    config = {
        "experiment": "hostile",
        "meshes": {"vase": {"builtin": "vase"}},
        "prompts": {"p": prompt},
        "optimize": {"clip_tiny_test": True, "iterations": 3, "milestones": [2]},
        "metrics": {"clip_tiny_test": True},
    }
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(config))
    dry = run_snakemake(tmp_path, "-n", "-p", "--cores", "1", "--configfile", str(tmp_path / "c.yaml"))
    assert dry.returncode == 0, dry.stderr[-3000:]
    seen = {}
    monkeypatch.setattr(optimize, "run", lambda train, eval_, text, *a, **k: seen.setdefault("optimize", text))
    monkeypatch.setattr(metrics, "run", lambda field, cache, text, candidates, *a: seen.setdefault("metrics", (text, candidates)))
    assert optimize.main(stage_argv(dry.stdout, "stages.optimize")) == 0
    assert metrics.main(stage_argv(dry.stdout, "stages.metrics")) == 0
    assert seen == {"optimize": prompt, "metrics": (prompt, [prompt])}
    assert not (tmp_path / "pwned").exists()


@pytest.mark.parametrize("kind", sorted(HOSTILE_PROMPTS))
def test_the_loss_plot_draws_any_prompt_as_its_title(tmp_path, kind):
    """matplotlib parsed the title as mathtext: ``a $\\wood$ vase`` raised at savefig, after the
    whole optimisation, and every resumed retry crashed again."""
    from stages.training.optimizer import TITLE_CHARS, plot_loss

    history = [{"iteration": i, "loss": 1.0 / (i + 1)} for i in range(5)]
    for title in (HOSTILE_PROMPTS[kind], HOSTILE_PROMPTS[kind] * 500):
        plot_loss(tmp_path / "loss.png", history, title)
        assert (tmp_path / "loss.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert TITLE_CHARS <= 120
