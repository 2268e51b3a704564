"""A guidance mode is one row of stages.config.guidance_modes and one registered class of
stages.guidance.objective: no caller compares mode names, every row has its class and its
calibration, and a new mode needs nothing else."""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import sys
import typing
from pathlib import Path

import pytest

from stages.config import guidance_modes
from stages.config.guidance_modes import GUIDANCE_MODES, GuidanceMode, guidance_mode
from stages.config.sections import OptimizeSettings
from stages.core.errors import ConfigError
from stages.guidance import objective
from stages.guidance.objective import GUIDANCE_CLASSES, Guidance, choose_guidance, guidance_class, register
from stages.training import calibrate

STAGES = Path(__file__).resolve().parents[2] / "stages"
#: the modules that may name modes: the table and the registered classes
REGISTRY = {"config/guidance_modes.py", "guidance/objective.py"}


def _mode_names(node: ast.AST) -> list[str]:
    """The mode names a literal holds: a string, or the strings of a tuple, list or set."""
    items = node.elts if isinstance(node, ast.Tuple | ast.List | ast.Set) else [node]
    return [i.value for i in items if isinstance(i, ast.Constant) and i.value in GUIDANCE_MODES]


def _about_guidance(node: ast.AST) -> bool:
    """Whether an expression reads a guidance mode: a name or attribute with ``guidance`` in it
    (``settings.guidance``, ``opt_settings.guidance``, ``guidance``), or a ``"guidance"`` key
    (``row["guidance"]``)."""
    for n in ast.walk(node):
        if isinstance(n, ast.Name) and "guidance" in n.id.lower():
            return True
        if isinstance(n, ast.Attribute) and "guidance" in n.attr.lower():
            return True
        if isinstance(n, ast.Constant) and n.value == "guidance":
            return True
    return False


def mode_name_tests(source: str) -> list[tuple[int, str]]:
    """Where ``source`` decides by a guidance mode's name: a comparison (``==``, ``!=``, ``in``)
    of a mode-name literal with a guidance expression, a ``startswith``/``endswith`` of one by a
    mode name, a ``match`` on one with a mode-name case, or a dispatch table keyed by mode names
    indexed by one. Other uses of the words (``metrics.clip``, an ``"image"`` key) are not."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            named = [s for s in sides if _mode_names(s)]
            if named and any(_about_guidance(s) for s in sides if s not in named):
                found.append((node.lineno, ast.unparse(node)))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr in ("startswith", "endswith") and any(map(_mode_names, node.args)):
                if _about_guidance(node.func.value):
                    found.append((node.lineno, ast.unparse(node)))
        elif isinstance(node, ast.Match) and _about_guidance(node.subject):
            for case in node.cases:
                if any(isinstance(p, ast.MatchValue) and _mode_names(p.value) for p in ast.walk(case.pattern)):
                    found.append((case.pattern.lineno, f"match {ast.unparse(node.subject)}: case {ast.unparse(case.pattern)}"))
        elif isinstance(node, ast.Subscript) and isinstance(node.value, ast.Dict) and _about_guidance(node.slice):
            if any(k is not None and _mode_names(k) for k in node.value.keys):
                found.append((node.lineno, ast.unparse(node)[:80]))
    return sorted(found)


def scan(root: Path) -> list[str]:
    """Every place under the package ``root`` outside the registry that decides by a mode's name."""
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel in REGISTRY:
            continue
        out += [f"{rel}:{line}: {text}" for line, text in mode_name_tests(path.read_text())]
    return out


def test_no_caller_decides_by_a_mode_name():
    found = scan(STAGES)
    assert not found, "decide by the mode's row or class instead:\n" + "\n".join(found)


def test_the_scan_finds_each_form_and_leaves_other_words_alone():
    caught = """
if settings.guidance == "clip": pass
if opt_settings.guidance != 'image': pass
if guidance not in ("clip", "image"): pass
if "image" == self.guidance: pass
ok = frame["guidance"].astype(str).str.startswith("image")
fn = {"clip": a, "image": b}[s.guidance]
match s.guidance:
    case "clip": pass
"""
    assert [line for line, _ in mode_name_tests(caught)] == [2, 3, 4, 5, 6, 7, 9]
    left = """
if settings.clip and "image" in tint: pass
if kind == "image": pass
if metrics.clip_model == "clip": pass
guidance = {"guidance": "image"}
prompt_entry["optimize"] = {"guidance": "image"}
if mode.uses_clip: pass
"""
    assert mode_name_tests(left) == []


def test_the_scan_fails_on_the_code_before_the_registry():
    """The code of dbef3c0 (before the registry) tested mode names in the callers the issue
    names; kept here as the lines that were, so the scan is seen to fail on them."""
    before = {
        "optimize.py": 'mitsuba_targets = settings.guidance == "image" and settings.target_renderer == "mitsuba"',
        "metrics.py": 'if opt_settings.guidance == "clip":\n    pass\nif opt_settings.guidance == "image":\n    pass',
        "config/workflow.py": 'if s.guidance == "clip" and not s.clip_tiny_test:\n    pass',
        "training/calibrate.py": 'if settings.guidance == "clip" and settings.clip_tiny_test:\n    pass',
        "plan.py": 'if settings.guidance != "clip":\n    pass',
        "doctor.py": 'clip = 1 if s.guidance == "clip" else None',
        "core/provenance.py": 'if guidance not in ("clip", "image"):\n    pass',
        "config/records.py": 'x = "image-guided" if self.guidance == "image" else "CLIP"',
        "results/site.py": 'image = frame["guidance"].astype(str).str.startswith("image")',
    }
    for name, text in before.items():
        assert mode_name_tests(text), name


def test_each_mode_has_its_classes_and_each_class_its_mode():
    for mode in GUIDANCE_MODES.values():
        keys = [k for k in GUIDANCE_CLASSES if k[0] == mode.name]
        assert keys, f"mode {mode.name!r} has no class"
        assert all((k[1] is not None) == mode.image_targets for k in keys)
    for (name, _), cls in GUIDANCE_CLASSES.items():
        assert cls.mode is GUIDANCE_MODES[name] and issubclass(cls, Guidance)
        assert cls.held_out_key in ("guidance", "image_target")  # fields of MetricsRecord


def test_the_setting_takes_the_table_s_names_and_its_wording():
    assert typing.get_args(guidance_modes.GuidanceName)[1] is GUIDANCE_MODES  # the names when a value is checked
    assert OptimizeSettings.kinds()["guidance"].choices is GUIDANCE_MODES
    assert OptimizeSettings.specs()["guidance"].doc == guidance_modes.GUIDANCE_DOC
    with pytest.raises(ConfigError, match="optimize.guidance"):
        OptimizeSettings(guidance="sds")
    with pytest.raises(ConfigError, match="unknown guidance mode 'sds'; choose one of clip, image"):
        guidance_mode("sds")


def test_every_mode_s_calibration_is_known_and_a_missing_one_fails_loudly(monkeypatch):
    assert {m.calibration for m in GUIDANCE_MODES.values()} <= set(calibrate.CALIBRATIONS)
    sg = OptimizeSettings(guidance="image", target_renderer="sg")
    timed, guide = calibrate.calibration(sg, "cpu")
    assert timed.target_renderer == "sg" and guide is None
    mitsuba = OptimizeSettings(guidance="image", target_renderer="mitsuba")
    assert calibrate.calibration(mitsuba, "cpu")[0].target_renderer == "sg"  # Mitsuba's are the target stage's
    odd = dataclasses.replace(GUIDANCE_MODES["image"], name="odd", calibration="diffusion")
    with GUIDANCE_MODES.temporarily("odd", odd):
        settings = OptimizeSettings(guidance="odd", target_renderer="sg")
        with pytest.raises(ConfigError, match="calibration 'diffusion', which stages.training.calibrate does not know"):
            calibrate.calibration(settings, "cpu")
    assert "odd" not in GUIDANCE_MODES


def test_what_the_callers_read_from_a_mode():
    clip, image = GUIDANCE_MODES["clip"], GUIDANCE_MODES["image"]
    tiny = OptimizeSettings(clip_tiny_test=True)
    assert clip.plan_label(tiny) == "the tiny test CLIP" and clip.plan_label(OptimizeSettings()) == "ViT-B-32"
    assert image.plan_label(OptimizeSettings(guidance="image")) == "image targets"
    assert image.weights_label("w", False, {"target_material": "wood"}) == "image-guided (wood target)"
    assert clip.weights_label("ViT-B-32 openai", False, {}) == "ViT-B-32 openai"
    assert clip.weights_label("tiny", True, {}) == "test-only random"
    assert OptimizeSettings(guidance="image").mitsuba_targets()
    assert not OptimizeSettings(guidance="image", target_renderer="sg").mitsuba_targets()
    assert not OptimizeSettings(target_renderer="mitsuba").mitsuba_targets()  # CLIP has no targets
    origin = image.origin_record("targets t", False, "p")
    assert origin["image_guided"] and origin["label"].startswith("IMAGE-GUIDED") and origin["guidance"] == "image"
    assert clip.origin_record("w", True)["label"].startswith("TEST ONLY")
    assert clip.origin_record("w", False)["label"] == "CLIP-guided (w)"


def test_a_new_mode_is_one_row_and_one_class(monkeypatch):
    """A mode added as a row and a class: chosen by the settings, labelled, planned and timed
    with nothing else changed."""
    row = GuidanceMode(
        name="flat",
        description="squared error against a flat grey",
        label="flat grey",
        weights="flat grey",
        origin="FLAT: fitted to a flat grey ({weights})",
        plan="a flat grey",
        table="Flat grey",
        banner="FLAT: {n} of {total} cells were fitted to a flat grey.",
        calibration="own_targets",
        uses_clip=False,
        image_targets=False,
        image_guided=True,
        cpu_threads=1,
    )
    stack = contextlib.ExitStack()
    monkeypatch.setattr(objective, "GUIDANCE_CLASSES", dict(GUIDANCE_CLASSES))
    with stack:  # the setting takes the rows' names at once (the registry's choices are read when checked)
        stack.enter_context(GUIDANCE_MODES.temporarily("flat", row))
        stack.enter_context(GUIDANCE_MODES.temporarily("lonely", dataclasses.replace(row, name="lonely")))  # no class
        _new_mode_runs(row)
    assert "flat" not in GUIDANCE_MODES and "lonely" not in GUIDANCE_MODES


def _new_mode_runs(row: GuidanceMode) -> None:
    """:func:`test_a_new_mode_is_one_row_and_one_class` with its rows registered."""

    @register("flat")
    class FlatGuidance(Guidance):
        held_out_key = "image_target"
        weights_id = "grey 0.5"

        @classmethod
        def build(cls, settings, prompt, device, guide, targets):
            return cls(settings, prompt)

        def loss(self, rendered, target):
            raise NotImplementedError

        def eval_score(self, renders, views, width, out_width):
            raise NotImplementedError

        def held_out(self, renders, store, candidates, background):
            raise NotImplementedError

    settings = OptimizeSettings(guidance="flat")
    assert guidance_class(settings) is FlatGuidance
    g = choose_guidance(settings, "a vase", "cpu")
    assert g.origin["label"] == "FLAT: fitted to a flat grey (grey 0.5)" and g.origin["image_guided"]
    assert settings.guidance_mode().plan_label(settings) == "a flat grey"
    assert calibrate.calibration(settings, "cpu")[1] is None
    with pytest.raises(TypeError, match="already registered"):
        register("flat")(FlatGuidance)
    with pytest.raises(TypeError, match="names its target renderer"):
        register("image")
    # a row without a class fails loudly when chosen
    with pytest.raises(ConfigError, match="guidance 'lonely' has no class"):
        guidance_class(OptimizeSettings(guidance="lonely"))


if __name__ == "__main__":  # scan another checkout: python tests/guidance/test_mode_registry.py <repo>/stages
    problems = scan(Path(sys.argv[1]))
    print("\n".join(problems) or "no mode-name tests")
    raise SystemExit(1 if problems else 0)
