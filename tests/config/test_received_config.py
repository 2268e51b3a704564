"""A config from someone else, read as the workflow reads it: every path it names is refused when
Snakemake would read it otherwise than the stage does or when it looks other than it is, a prompt
that shows nothing is blank, and ``python -m stages.config --check`` refuses what the workflow's
start refuses, by the same code. Each refusal is one line naming the key."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
import yaml
from conftest import REPO

from stages.config.sections import SECTIONS, OptimizeSettings
from stages.config.workflow import ConfigError, WorkflowConfig, main

BASE = {"meshes": {"vase": {"builtin": "vase"}}, "prompts": {"wood": "a {object} made of wood"}}
#: every setting that holds a file path: (section, key)
PATH_KEYS = {
    ("target", "environment"),
    ("target", "relight_environments"),
    ("optimize", "light_map"),
    ("optimize", "clip_checkpoint"),
    ("relight", "envmap"),
    ("metrics", "clip_checkpoint"),
}
#: what no path may hold, in a file name or in a folder's: braces (a Snakemake wildcard), control
#: characters, line and paragraph separators, bidirectional overrides and isolates
BAD_PATHS = {
    "wildcard": "env{mesh}.hdr",
    "brace_in_a_folder": "maps/{x}/sky.hdr",
    "bell": "sky\x07.hdr",
    "next_line": "maps\x85/sky.hdr",
    "trailing_newline": "sky.hdr\n",
    "line_separator": "sky\u2028.hdr",
    "paragraph_separator": "maps\u2029/sky.hdr",
    "right_to_left_override": "rdh.\u202eyks.exr",
    "left_to_right_embedding": "\u202asky.hdr",
    "first_strong_isolate": "maps/\u2068sky\u2069.hdr",
    "pop_directional_isolate": "sky.hdr\u2069",
}


def path_keys() -> set[tuple[str, str]]:
    """The (section, key) of every setting declared as a path (``path_setting``)."""
    from stages.config.sections import is_path

    return {(name, key) for name, cls in SECTIONS.items() for key, spec in cls.specs().items() if is_path(spec)}


def one_line_error(config: dict) -> str:
    with pytest.raises(ConfigError) as err:
        WorkflowConfig(config)
    message = str(err.value)
    assert "\n" not in message and len(message) < 600, message
    return message


def test_path_keys_are_the_settings_that_name_files():
    """One definition of a path key (``path_setting``), and it covers every setting that names a
    file: a new such setting that is not declared as one fails here."""
    assert path_keys() == PATH_KEYS
    words = ("path", "file", "map", "environment", "checkpoint", "dir", "folder")
    for name, cls in SECTIONS.items():
        for field in dataclasses.fields(cls):
            kind = cls.kinds()[field.name]
            text = kind.base is str or (kind.item is not None and kind.item.base is str)
            if text and any(w in field.name for w in words):
                assert (name, field.name) in PATH_KEYS, f"{name}.{field.name} names a file: declare it with path_setting"


@pytest.mark.parametrize("case", sorted(BAD_PATHS))
@pytest.mark.parametrize(("section", "key"), sorted(PATH_KEYS) + [("meshes", "path")])
def test_every_path_key_refuses_braces_and_characters_that_disguise_a_name(section, key, case):
    bad = BAD_PATHS[case]
    if section == "meshes":
        config, where = {**BASE, "meshes": {"vase": {"path": bad}}}, "meshes -> vase -> path"
    elif key == "relight_environments":
        config, where = {**BASE, section: {key: ["builtin:sunset", bad]}}, f"{section} -> {key} -> 1"
    else:
        config, where = {**BASE, section: {key: bad}}, f"{section} -> {key}"
    message = one_line_error(config)
    assert f"path at {where}: " in message, message
    if "{" in bad:
        assert "Snakemake reads {...} in a file name as a wildcard" in message
    else:
        odd = next(c for c in bad if not (c.isprintable() and c.isascii()) or c == "\n")
        assert f"U+{ord(odd):04X}" in message and "makes a file name look other than it is" in message, message


def test_plain_paths_and_builtins_pass():
    config = {
        **BASE,
        "relight": {"envmap": "maps/studio lights (2).hdr"},
        "target": {"environment": "maps/ciel étoilé.exr", "relight_environments": ["builtin:night", "a-b_c.hdr"]},
        "metrics": {"clip_checkpoint": "weights/open_clip_pytorch_model.bin", "clip_model": "ViT-B-16-quickgelu"},
    }
    assert WorkflowConfig(config).cell_stage_settings("relight", "wood", "base").envmap == "maps/studio lights (2).hdr"


def test_the_check_command_refuses_a_path_that_snakemake_would_expand(tmp_path, capsys):
    path = tmp_path / "received.yaml"
    path.write_text(yaml.safe_dump({**BASE, "relight": {"envmap": "env{mesh}.hdr"}}))
    assert main(["--configfile", str(path), "--check"]) == 2
    err = capsys.readouterr().err
    assert "invalid path at relight -> envmap: 'env{mesh}.hdr' holds a brace" in err and str(path) in err


INVISIBLE = {
    "zero_width_space": "\u200b",
    "zero_width_non_joiner": "\u200c",
    "zero_width_joiner": "\u200d",
    "word_joiner": "\u2060",
    "byte_order_mark": "\ufeff",
    "no_break_spaces": "\u00a0\u00a0",
    "mixed": " \u200b\u3000\u2060\u00a0\u200d ",
    "soft_hyphen": "\u00ad",
}


@pytest.mark.parametrize("case", sorted(INVISIBLE))
def test_a_prompt_or_object_noun_that_shows_nothing_is_blank(case):
    text = INVISIBLE[case]
    for prompts in ({"wood": text}, {"wood": {"text": text, "optimize": {"iterations": 5}}}):
        message = one_line_error({**BASE, "prompts": prompts})
        assert "prompt 'wood' is blank" in message, message
    noun = {**BASE, "meshes": {"vase": {"builtin": "vase", "object": text}}}
    assert "meshes -> vase -> object: " in one_line_error(noun) and "is blank" in one_line_error(noun)


@pytest.mark.parametrize("char", ["\u202e", "\u202a", "\u2066", "\u2069", "\x85", "\x1b"])
def test_a_prompt_or_object_noun_with_a_control_is_refused_naming_it(char):
    """A prompt and an object noun are one line shown as written: a bidirectional override or
    isolate (which shows the text in another order than it is stored) is refused like a control
    character, the message naming its code point."""
    code = f"U+{ord(char):04X}"
    message = one_line_error({**BASE, "prompts": {"wood": f"a vase of {char}doow"}})
    assert "prompt 'wood' holds a " in message and code in message, message
    noun = one_line_error({**BASE, "meshes": {"vase": {"builtin": "vase", "object": f"jar{char}"}}})
    assert "meshes -> vase -> object: " in noun and code in noun, noun


def test_visible_text_with_joiners_is_not_blank():
    config = {
        **BASE,
        "meshes": {"vase": {"builtin": "vase", "object": "\u200bjar"}},
        "prompts": {"wood": "a {object} made of wood", "lab": "a scientist \U0001f469\u200d\U0001f52c"},
    }
    assert WorkflowConfig(config).prompt_text("vase", "lab").endswith("\u200d\U0001f52c")


def test_image_size_is_the_guidance_clips_unless_given():
    """``image_size`` left out is the size the guidance CLIP takes (the tiny test CLIP's 64); a
    different size is refused when the settings are read, by the config check, the workflow and the
    optimize stage alike (one check, in the settings)."""
    assert OptimizeSettings().image_size == 224
    assert OptimizeSettings(clip_tiny_test=True).image_size == 64
    assert OptimizeSettings(guidance="image", clip_tiny_test=True).image_size == 224
    assert OptimizeSettings(clip_model="ViT-L-14-336").image_size == 336
    cfg = WorkflowConfig({**BASE, "optimize": {"clip_tiny_test": True}})
    assert cfg.optimize_settings("wood", "base").image_size == 64
    message = one_line_error({**BASE, "optimize": {"clip_tiny_test": True, "image_size": 32}})
    want = "optimize.image_size is 32 but the guidance CLIP, the tiny test CLIP, takes 64 x 64 images: set image_size: 64"
    assert want in message
    with pytest.raises(ConfigError, match="set image_size: 64"):  # the optimize stage's settings, as the rule passes them
        OptimizeSettings.from_json('{"clip_tiny_test": true, "image_size": 32}')
    assert "set image_size: 224" in one_line_error({**BASE, "optimize": {"image_size": 128}})


#: configs the workflow's start refuses, and the words of the refusal
REFUSED = {
    "experiment_meshes": ({**BASE, "experiment": "meshes"}, "experiment name 'meshes' (from the key `experiment`)"),
    "experiment_of_the_file_name": (BASE, "experiment name 'meshes' (from the config file name)"),
    "image_size_of_the_test_clip": (
        {**BASE, "optimize": {"clip_tiny_test": True, "image_size": 32}},
        "optimize.image_size is 32 but the guidance CLIP, the tiny test CLIP, takes 64 x 64 images",
    ),
}


def write_refused(case: str, folder) -> tuple:
    config, needle = REFUSED[case]
    path = folder / ("meshes.yaml" if case == "experiment_of_the_file_name" else f"{case}.yaml")
    path.write_text(yaml.safe_dump(config))
    return path, needle


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_the_check_refuses_what_the_workflow_refuses(case, tmp_path, capsys):
    path, needle = write_refused(case, tmp_path)
    assert main(["--configfile", str(path), "--check"]) == 2
    err = capsys.readouterr().err
    assert needle in err and str(path) in err and err.count("\n") == 1, err


def test_the_check_reads_overlays_as_the_workflow_merges_them(tmp_path, capsys):
    base, overlay = tmp_path / "base.yaml", tmp_path / "overlay.yaml"
    base.write_text(yaml.safe_dump({**BASE, "optimize": {"clip_tiny_test": True}}))
    overlay.write_text(yaml.safe_dump({"optimize": {"image_size": 32}}))
    assert main(["--configfile", str(base), "--check"]) == 0
    out = capsys.readouterr().out
    assert (
        "a valid config of 1 mesh x 1 prompt x 1 variant = 1 cell" in out
        and "experiment 'base'" in out
        and "python -m stages.doctor" in out
    )
    assert main(["--configfile", str(base), str(overlay), "--check"]) == 2
    assert "set image_size: 64" in capsys.readouterr().err


@pytest.mark.slow
def test_the_workflow_refuses_them_with_the_same_words(tmp_path):
    """The same configs under ``snakemake -n``: refused when the DAG is built, in the words of the
    check (the image size before any job, where the optimize job used to stop)."""
    cmd = [sys.executable, "-m", "snakemake", "-n", "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp_path)]
    for case in REFUSED:
        path, needle = write_refused(case, tmp_path)
        proc = subprocess.run([*cmd, "--configfile", str(path)], capture_output=True, text=True, timeout=120)
        assert proc.returncode != 0 and needle in proc.stdout + proc.stderr, (case, (proc.stdout + proc.stderr)[-2000:])


@pytest.mark.parametrize("section", ["meshes", "prompts", "variants", "experiment"])
def test_no_id_and_no_experiment_may_be_named_results(section):
    """A folder named ``results`` inside the results folder would be taken for a second root
    (which alone may be a link): no mesh, prompt, variant or experiment takes that name."""
    from stages.config.workflow import WorkflowConfig, experiment_name
    from stages.core.errors import ConfigError

    config = {"meshes": {"v": {"builtin": "vase"}}, "prompts": {"p": "a vase"}}
    if section == "experiment":
        with pytest.raises(ConfigError, match="nor 'results'"):
            experiment_name({**config, "experiment": "results"}, [])
        return
    config[section] = {"Results": {"builtin": "vase"} if section == "meshes" else "a vase" if section == "prompts" else {}}
    with pytest.raises(ConfigError, match=f"{section} -> Results: the id 'Results' is reserved") as err:
        WorkflowConfig(config)
    assert "\n" not in str(err.value)
