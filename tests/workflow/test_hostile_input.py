"""Hostile input through the workflow: prompts are data from the config to every stage's command
line (leading dashes, quotes, shell syntax, mathtext), and the loss plot draws any of them."""

from __future__ import annotations

import json
import re
import shlex
import shutil
from pathlib import Path

import pytest
import yaml
from conftest import run_snakemake, synthetic_results
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from markupsafe import escape

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


@pytest.mark.parametrize(
    ("prompt", "needle"),
    [
        ("a" * 1_000_000, "prompt 'p': 1000000 characters, at most 1000"),
        ("a vase\nrm -rf ~", "prompt 'p' holds a control character"),
        ("a vase\n", "prompt 'p' holds a control character"),
        ({"text": "tab\there"}, "prompt 'p' holds a control character"),
    ],
)
def test_a_prompt_too_long_or_on_several_lines_is_one_line_naming_it(prompt, needle):
    from stages.config.workflow import ConfigError, WorkflowConfig

    with pytest.raises(ConfigError) as err:
        WorkflowConfig({"meshes": {"vase": {"builtin": "vase"}}, "prompts": {"p": prompt}})
    text = str(err.value)
    assert needle in text and "\n" not in text and len(text) < 300, text[:500]


BAD_CONFIGS = {
    "prompt_not_text": ({"prompts": {"p": 5}}, "prompt 'p' must be a text or"),
    "override_past_limit": (
        {"prompts": {"p": {"text": "a", "optimize": {"iterations": 10**9}}}},
        "prompts -> p -> optimize -> iterations: 1000000000",
    ),
    "override_of_wrong_type": (
        {"prompts": {"p": {"text": "a", "optimize": {"iterations": "x"}}}},
        "iterations: 'x' is not of type integer",
    ),
    "long_after_object": (
        {"meshes": {"v": {"builtin": "vase", "object": "x" * 200}}, "prompts": {"p": "{object} " * 6}},
        "1206 characters with {object}",
    ),
    "object_on_two_lines": (
        {"meshes": {"v": {"builtin": "vase", "object": "jar\n=1+1"}}},
        "meshes -> v -> object: 'jar\\n=1+1' holds a control",
    ),
    "line_separator": ({"prompts": {"p": "a vase\u2028=1+1"}}, "prompt 'p' holds a control character"),
    "reserved_any_case": ({"meshes": {"Report": {"builtin": "vase"}}}, "the mesh id 'Report' is reserved"),
    "blank_prompt": ({"prompts": {"p": "   "}}, "prompt 'p' is blank"),
    "blank_prompt_text": ({"prompts": {"p": {"text": " \u3000 "}}}, "prompt 'p' is blank"),
    "lone_surrogate_prompt": ({"prompts": {"p": "a \ud800 vase"}}, "prompts -> p: it holds a lone surrogate (a \\ud800 vase)"),
    "lone_surrogate_object": (
        {"meshes": {"v": {"builtin": "vase", "object": "jar\udc00"}}},
        "meshes -> v -> object: it holds a lone surrogate",
    ),
    "anchor_azimuth_huge": ({"raycache": {"anchor_azimuth": 1e300}}, "anchor_azimuth: 1e+300 is not an angle of the anchor view"),
    "anchor_elevation_past_pole": ({"raycache": {"anchor_elevation": 1.6}}, "anchor_elevation: 1.6 is not an angle"),
    "anchor_deg_huge": ({"raycache": {"anchor_deg": [1e300, 10.0]}}, "anchor_deg -> 0: 1e+300 is not an angle"),
    "mesh_path_with_braces": (
        {"meshes": {"v": {"path": "chair {v2}.obj"}}},
        "invalid mesh path at meshes -> v -> path: 'chair {v2}.obj'",
    ),
    "mesh_path_naming_a_wildcard": ({"meshes": {"v": {"path": "x{mesh}.obj"}}}, "reads {...} in a file name as a wildcard"),
    "views_as_float": ({"raycache": {"views": 8.0}}, "raycache -> views: 8.0 is not an integer: write 8"),
    "iterations_as_float": ({"optimize": {"iterations": 100.0}}, "optimize -> iterations: 100.0 is not an integer: write 100"),
    "image_size_as_float": ({"optimize": {"image_size": 224.0}}, "image_size: 224.0 is not an integer"),
    "checkpoint_every_as_float": ({"optimize": {"checkpoint_every": 50.0}}, "checkpoint_every: 50.0 is not an integer"),
}


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
def test_bad_config_values_are_one_line_naming_the_key(case):
    from stages.config.workflow import ConfigError, WorkflowConfig

    config, needle = BAD_CONFIGS[case]
    full = {"meshes": {"v": {"builtin": "vase"}}, "prompts": {"p": "a {object}"}, **config}
    with pytest.raises(ConfigError) as err:
        WorkflowConfig(full)
    assert needle in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_every_bad_id_is_named_not_only_the_first():
    from stages.config.workflow import ConfigError, WorkflowConfig

    with pytest.raises(ConfigError) as err:
        WorkflowConfig({"meshes": {"a b": {"builtin": "vase"}, "c d": {"builtin": "vase"}}, "prompts": {"p": "a"}})
    assert "'a b'" in str(err.value) and "'c d'" in str(err.value)


# ---- ids -------------------------------------------------------------------------------------
@given(st.text(alphabet=st.sampled_from("ab0_.-/\n '\"<>\u05e2Z"), max_size=70))
@settings(max_examples=300, deadline=None)
def test_the_schemas_id_pattern_is_the_codes(text):
    """One rule for ids in the config's schema and in the code (cells handed to the report and
    pack): a folder name, at most 64 characters, no trailing newline (Python's ``$`` allowed one)."""
    from stages.config.schema import schema as load_schema
    from stages.config.workflow import ID_RE

    node = load_schema()["$defs"]["id"]
    by_schema = re.search(node["pattern"], text) is not None and len(text) <= node["maxLength"]
    assert by_schema == (ID_RE.fullmatch(text) is not None)


@pytest.mark.parametrize("bad", ["vase\n", "../vase", ".vase", "vase/x", "a" * 65, "va se", "vase'"])
def test_a_bad_id_is_one_line_naming_it(bad):
    from stages.config.workflow import ConfigError, WorkflowConfig

    with pytest.raises(ConfigError) as err:
        WorkflowConfig({"meshes": {bad: {"builtin": "vase"}}, "prompts": {"p": "a vase"}})
    assert "\n" not in str(err.value).replace(repr(bad), "") and repr(bad) in str(err.value)


def test_the_mesh_id_report_is_reserved():
    """results/<experiment>/report/ is the report's folder: a mesh called so would share it (and a
    single-file report removes its cells/ folder)."""
    from stages.config.workflow import ConfigError, WorkflowConfig

    with pytest.raises(ConfigError, match=r"meshes -> report: the mesh id 'report' is reserved .* rename the mesh"):
        WorkflowConfig({"meshes": {"report": {"builtin": "vase"}}, "prompts": {"p": "a vase"}})


@pytest.mark.parametrize("item", ["a/../b", "a/b/c\n", "a/b/c'><script>", "/etc/passwd/x", "a/b/.."])
def test_cells_handed_to_the_report_are_ids(item):
    from stages.core.errors import StageInputError
    from stages.results.cells import parse_cells

    with pytest.raises(StageInputError, match="is not"):
        parse_cells([item])


# ---- spreadsheets ------------------------------------------------------------------------------
@given(st.text(max_size=40))
@settings(deadline=None)  # the first example imports pandas: 350 ms on a busy machine
def test_spreadsheet_cells_never_start_a_formula_and_read_back_exactly(text):
    from stages.results.spreadsheet import FORMULA_START, from_spreadsheet, to_spreadsheet

    cell = to_spreadsheet(text)
    assert from_spreadsheet(cell) == text
    assert not cell.startswith(tuple(c for c in FORMULA_START if c != "'"))
    assert to_spreadsheet(-0.5) == -0.5


@pytest.mark.parametrize("text", [" =1+1", "\u3000=cmd|' /C calc'!A0", "\uff1d1+1", "  \uff0bSUM(A1)", "\t =1", "\uff20x"])
def test_a_formula_behind_spaces_or_in_full_width_gets_its_apostrophe(text):
    from stages.results.spreadsheet import from_spreadsheet, to_spreadsheet

    assert to_spreadsheet(text) == "'" + text and from_spreadsheet(to_spreadsheet(text)) == text
    assert to_spreadsheet(" a vase ") == " a vase "


FORMULA = '=HYPERLINK("http://example.com/x","open")'
MARKUP = "<script>alert(1)</script> a 'vase' & \"jar\""


@pytest.fixture(scope="module")
def hostile_report(tmp_path_factory):
    """A two-cell synthetic results tree whose prompts are a spreadsheet formula and markup, with
    a texture file whose name would break out of an HTML attribute, through report and html_report."""
    from stages import html_report, report

    results = tmp_path_factory.mktemp("hostile") / "results"
    cells = synthetic_results(results, meshes=2, prompts=1)[:2]
    for cell, prompt in zip(cells, (FORMULA, MARKUP), strict=True):
        meta_path = results.joinpath(*cell, "optimize", "meta.json")
        meta = json.loads(meta_path.read_text())
        meta_path.write_text(json.dumps({**meta, "prompt": prompt}))
    textures = results.joinpath(*cells[1], "export", "textures")
    shutil.copyfile(next(textures.glob("*.png")), textures / "x' onerror='alert(1).png")
    # links that point out of the results folder: a file, and a whole textures folder
    secret = results.parent / "private"
    secret.mkdir()
    (secret / "key.png").write_bytes(b"PRIVATE KEY")
    preview = results.joinpath(*cells[0], "export", "preview.png")
    preview.unlink()
    preview.symlink_to(secret / "key.png")
    linked = results.joinpath(*cells[0], "export", "textures")
    for tex in linked.glob("*.png"):
        shutil.move(tex, secret / tex.name)
    linked.rmdir()
    linked.symlink_to(secret, target_is_directory=True)
    report.run(results, cells, results / "report")
    html_report.run(results, results / "report", cells)
    return results, cells


def test_summary_csv_quotes_a_formula_and_the_report_reads_it_back(hostile_report):
    import csv

    from stages.results.site import read_summary

    results, cells = hostile_report
    with open(results / "report" / "summary.csv", newline="") as fh:
        texts = [row["prompt_text"] for row in csv.DictReader(fh)]
    assert texts == ["'" + FORMULA, MARKUP]  # a spreadsheet shows the first as text
    assert list(read_summary(results / "report")["prompt_text"]) == [FORMULA, MARKUP]
    summary = json.loads((results / "report" / "summary.json").read_text())
    assert [r["prompt_text"] for r in summary] == [FORMULA, MARKUP]


def test_the_report_pages_show_hostile_text_as_text(hostile_report):
    results, cells = hostile_report
    pages = [results / "report" / "index.html", *(results / "report" / "cells").rglob("index.html")]
    for page in pages:
        text = page.read_text()
        assert "<script>alert(1)" not in text and "onerror=" not in text, page
    index = (results / "report" / "index.html").read_text()
    # the templates' escaping (markupsafe: ' as &#39;, " as &#34;)
    assert str(escape(MARKUP)) in index and str(escape(FORMULA)) in index
    assert not list((results / "report" / "cells").rglob("*onerror*"))


def test_the_report_copies_nothing_reached_through_a_link(hostile_report):
    results, cells = hostile_report
    folder = results / "report" / "cells" / "/".join(cells[0])
    assert not (folder / "preview.png").exists() and not list(folder.glob("texture_*"))
    assert list((results / "report" / "cells" / "/".join(cells[1])).glob("texture_*"))  # plain ones are
    for path in (results / "report").rglob("*"):
        assert not path.is_file() or b"PRIVATE KEY" not in path.read_bytes(), path


# ---- generated configs: accepted and usable, or one line naming the key -------------------------
_IDS = st.one_of(
    st.sampled_from(["vase", "p0", "a.b-c_1", "Z9"]),
    st.text(alphabet=st.sampled_from("ab0_.-/\n '{}\u05e2Z\ud800"), min_size=0, max_size=12),
)
_TEXTS = st.one_of(
    st.sampled_from(["a {object} made of wood", "=1+1 vase", "a 'vase' <b>", "ваза"]),
    st.text(alphabet=st.sampled_from("a {object}=+-@\t\n\u3000\u2028'\"<>\ud800\uff1dZ"), max_size=30),
)
_NUMBERS = st.one_of(
    st.sampled_from([8, 64, 100, 0.5, 0.3, 1]),  # within most keys' bounds
    st.sampled_from([8, 64, 100, 0.5, 0.3, 1]),
    st.integers(-(10**12), 10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.sampled_from([0, 1, 8, 8.0, 64, 0.5, -1, "8", None, [], {}]),
)
_KEYS = {
    "raycache": ["views", "resolution", "anchor_azimuth", "anchor_elevation", "std", "seed"],
    "optimize": ["iterations", "lr", "width", "image_size", "checkpoint_every", "light_lobes"],
    "decimate": ["target_faces", "target_share", "quality_threshold", "mode"],
    "target": ["spp", "texture_size", "bump_slope"],
}


@st.composite
def generated_configs(draw) -> dict:
    mesh_id, prompt_id = draw(_IDS), draw(_IDS)
    mesh = draw(st.one_of(st.just({"builtin": "vase"}), st.builds(lambda p: {"path": p}, _TEXTS)))
    if draw(st.booleans()):
        mesh["object"] = draw(_TEXTS)
    prompt = draw(st.one_of(_TEXTS, st.builds(lambda t: {"text": t}, _TEXTS)))
    config = {"meshes": {mesh_id: mesh}, "prompts": {prompt_id: prompt}}
    for section, keys in _KEYS.items():
        if draw(st.integers(0, 3)) == 0:
            chosen = draw(st.lists(st.sampled_from(keys), min_size=1, max_size=3, unique=True))
            config[section] = {k: draw(_NUMBERS) for k in chosen}
    return config


def _names(node, path=()) -> set[str]:
    """Every key of a config as an error message may name it: its path (``a -> b -> c``, a key that
    is not a plain word escaped) or, for an id, its repr (``prompt '0'``)."""
    out = set()
    if path:
        out.add(" -> ".join(str(p) if re.fullmatch(r"[A-Za-z0-9_.-]+", str(p)) else ascii(p) for p in path))
        out.add(repr(path[-1]))
    if isinstance(node, dict):
        for k, v in node.items():
            out |= _names(v, (*path, k))
    return out


@given(generated_configs())
@settings(max_examples=400, deadline=None)
def test_a_generated_config_is_usable_or_refused_in_one_line_naming_the_key(config):
    """Configs generated from ids, prompts, mesh paths and numbers of every kind (floats for
    integers, NaN, booleans, strings, surrogates, braces, control characters, formula signs): each
    is either accepted, and then every cell's settings of every stage resolve as the workflow
    resolves them when it builds its jobs, or refused with one ConfigError line that names a key the
    config holds (or the top level)."""
    from stages.config.sections import SECTIONS
    from stages.config.workflow import ConfigError, WorkflowConfig

    try:
        cfg = WorkflowConfig(config)
    except ConfigError as err:
        message = str(err)
        assert "\n" not in message and len(message) < 2000, message[:300]
        named = [p for p in _names(config) if p and p in message]
        assert named or "top level" in message or "experiment name" in message, message[:300]
        return
    for mesh in cfg.grid_meshes:
        cfg.mesh_work_keys(mesh)
        for stage in ("normalize", "raycache", "target") + (("decimate",) if cfg.decimated(mesh) else ()):
            cfg.stage_settings(mesh, stage)
    for cell in cfg.cells:
        cfg.optimize_settings(cell.prompt, cell.variant)
        for stage in ("bake", "relight", "metrics", "export"):
            assert stage in SECTIONS
            cfg.cell_stage_settings(stage, cell.prompt, cell.variant)
        assert "\n" not in cfg.prompt_text(cell.mesh, cell.prompt)


# ---- the corpus's index: every probe of the second hardening pass and the test that holds it ----
#: each probe (what a hostile or careless user tried) -> the tests that hold it (module, function);
#: the probes live beside the code they exercise, and this index keeps them one corpus
PROBES = {
    "a config that is a YTE template": [
        ("config/test_yamlio.py", "test_a_yte_template_is_refused_by_the_projects_loaders"),
        ("config/test_yamlio.py", "test_the_workflow_refuses_before_it_walks_the_values"),
        ("config/test_yamlio.py", "test_the_check_command_reads_a_received_config_as_data"),
    ],
    "figures.json naming a file outside the report, a linked or FIFO figure": [
        ("core/test_safefiles.py", "test_a_received_figures_json_cannot_inline_a_file_from_outside"),
        ("core/test_safefiles.py", "test_a_received_record_that_is_not_json_or_not_the_reports_is_one_line_or_ignored"),
    ],
    "a YAML alias bomb, a 20,000-deep YAML, --overlay given a folder": [
        ("config/test_yamlio.py", "test_an_alias_bomb_is_refused_at_once"),
        ("config/test_yamlio.py", "test_deep_nesting_is_one_line"),
        ("config/test_yamlio.py", "test_not_a_config_file_is_one_line"),
    ],
    "a stage folder that is a link": [
        ("core/test_safefiles.py", "test_a_stage_folder_that_links_elsewhere_is_not_written_through")
    ],
    "a render, field, cache or record that is a link or a FIFO; a sheet outside its render": [
        ("core/test_safefiles.py", "test_a_render_that_is_a_link_a_fifo_or_a_bad_sheet_is_one_line"),
        ("core/test_safefiles.py", "test_a_ray_cache_target_or_meta_that_is_a_link_or_a_fifo_is_one_line"),
        ("model/test_untrusted_files.py", "test_a_field_that_is_a_link_or_a_fifo_inside_a_results_folder_is_one_line"),
    ],
    "integers given as floats, duplicate keys": [
        ("config/test_yamlio.py", "test_integers_given_as_floats_are_refused_naming_the_key"),
        ("config/test_yamlio.py", "test_a_duplicate_key_names_both_lines"),
        ("workflow/test_hostile_input.py", "test_bad_config_values_are_one_line_naming_the_key"),
    ],
    "malformed HDR and EXR maps": [
        ("render/test_envmaps.py", "test_a_malformed_hdr_is_one_line"),
        ("render/test_envmaps.py", "test_a_malformed_exr_is_one_line"),
    ],
    "crafted field.pt and checkpoint.pt": [
        ("model/test_untrusted_files.py", "test_a_crafted_field_of_the_right_container_is_one_line"),
        ("model/test_untrusted_files.py", "test_a_wrongly_shaped_weight_is_one_line"),
        ("model/test_untrusted_files.py", "test_a_compressed_archive_is_refused_from_its_directory"),
        ("model/test_untrusted_files.py", "test_a_checkpoint_without_its_parts_stops_the_resume_in_one_line"),
    ],
    "a local path in a pack's meta": [
        ("assets/test_formats_validator.py", "test_a_missing_validator_is_named_without_a_local_path")
    ],
    "a foreign Slurm configuration": [
        ("workflow/test_slurm_cluster_script.py", "test_a_foreign_slurm_conf_holding_the_marker_in_a_comment_is_refused"),
        ("workflow/test_slurm_cluster_script.py", "test_a_source_built_slurms_configuration_is_refused"),
    ],
    "the quick command: a mesh past the face limit, Report.obj, a folder with spaces": [
        ("workflow/test_quick.py", "test_a_mesh_past_the_face_limit_a_reserved_name_and_a_folder_with_spaces")
    ],
    "formulas behind spaces or in full width; long titles": [
        ("workflow/test_hostile_input.py", "test_a_formula_behind_spaces_or_in_full_width_gets_its_apostrophe"),
        ("results/test_compare.py", "test_long_ids_wrap_in_panel_titles"),
    ],
    "generated configs": [
        ("workflow/test_hostile_input.py", "test_a_generated_config_is_usable_or_refused_in_one_line_naming_the_key")
    ],
    "a folder name holding U+2028, U+2029 or U+0085 and template keys, given to the quick command": [
        ("workflow/test_quick.py", "test_a_folder_name_cannot_write_config_keys"),
        ("workflow/test_quick.py", "test_the_written_config_loads_to_exactly_its_keys"),
    ],
    "a received summary.json, summary.csv, speed_accuracy.csv or loss.csv that links outside": [
        ("results/test_received_folder.py", "test_a_linked_record_is_one_line_and_never_inlined"),
        ("results/test_received_folder.py", "test_a_linked_summary_csv_is_neither_read_nor_offered"),
        ("results/test_received_folder.py", "test_a_linked_or_malformed_loss_record_is_one_line"),
    ],
    "report/figures or report itself a link": [
        ("results/test_received_folder.py", "test_a_linked_figures_folder_keeps_the_pictures_it_points_to"),
        ("results/test_received_folder.py", "test_a_linked_report_folder_is_refused_before_anything_in_it_changes"),
        ("core/test_gate.py", "test_deletes_refuse_a_linked_folder_and_delete_only_entries"),
    ],
    "a FIFO or /dev/zero at an earlier run's meta.json": [
        ("results/test_received_folder.py", "test_a_fifo_or_endless_meta_json_does_not_stop_the_plan"),
        ("core/test_gate.py", "test_open_read_refuses_a_link_a_link_on_the_way_a_fifo_a_device_and_a_large_file"),
        ("core/test_gate.py", "test_open_read_checks_the_handle_it_opened"),
    ],
    "every file operation outside the gate": [
        ("core/test_gate.py", "test_every_file_operation_in_stages_goes_through_the_gate"),
        ("core/test_gate.py", "test_the_scanner_finds_each_kind_of_direct_file_operation"),
    ],
    "a figures.json entry with a NUL byte": [("core/test_gate.py", "test_a_name_with_a_nul_or_control_character_is_one_line")],
    "an EXR of many channels, parts, deep data or huge tiles": [
        ("render/test_envmaps.py", "test_an_exr_with_too_many_channels_is_refused_from_its_header"),
        ("render/test_envmaps.py", "test_an_exr_of_parts_deep_data_or_huge_tiles_is_refused_from_its_header"),
    ],
    "a YTE template that sets TANGO_ALLOW_YTE while Snakemake evaluates it": [
        ("config/test_yamlio.py", "test_allow_yte_is_read_from_the_environment_the_process_started_with"),
        ("config/test_yamlio.py", "test_a_template_that_sets_the_switch_does_not_let_the_workflow_go_on"),
    ],
    "braces and disguising characters in relight.envmap, optimize.light_map, target.environment": [
        ("config/test_received_config.py", "test_every_path_key_refuses_braces_and_characters_that_disguise_a_name"),
        ("config/test_received_config.py", "test_the_check_command_refuses_a_path_that_snakemake_would_expand"),
    ],
    "views: 0x10, views: 1:30 (YAML 1.1 numbers); aliases holding themselves": [
        ("config/test_yamlio.py", "test_yaml_1_1_number_forms_are_refused_naming_the_key"),
        ("config/test_yamlio.py", "test_aliases_that_hold_themselves_or_nest_deep_are_one_line"),
    ],
    "a field.pt whose settings nest 200,000 deep; a clip_checkpoint that is a pickle payload": [
        ("model/test_untrusted_files.py", "test_a_field_whose_settings_nest_200000_deep_is_one_line"),
        ("guidance/test_weights_messages.py", "test_a_clip_checkpoint_that_is_a_pickle_payload_is_refused_in_one_line"),
    ],
    "a zero-width blank prompt": [("config/test_received_config.py", "test_a_prompt_or_object_noun_that_shows_nothing_is_blank")],
    "experiment: meshes and image_size 32 with the test CLIP under --check": [
        ("config/test_received_config.py", "test_the_check_refuses_what_the_workflow_refuses"),
        ("config/test_received_config.py", "test_image_size_is_the_guidance_clips_unless_given"),
    ],
    "the doctor asking the model hub without saying so": [
        ("guidance/test_weights_messages.py", "test_the_doctor_offline_opens_no_connection"),
        ("guidance/test_weights_messages.py", "test_the_doctor_says_it_asks_the_model_hub_before_it_does"),
    ],
    "a GLB with two JSON chunks or a negative byteStride; accessors and views past their buffers": [
        ("geometry/test_gltf_checks.py", "test_a_malformed_glb_is_refused_in_one_line_by_both_readers"),
        ("geometry/test_gltf_checks.py", "test_the_reader_copies_no_bytes_outside_a_view_even_unchecked"),
        ("geometry/test_gltf_checks.py", "test_quick_refuses_a_glb_with_two_json_chunks_before_writing_anything"),
    ],
    "a kept GLB with <script> names, local paths in extras and a remote image URI; the validator's failure": [
        ("assets/test_input_document.py", "test_a_kept_glb_embeds_or_drops_every_image_uri_and_says_so"),
        ("assets/test_input_document.py", "test_a_kept_glb_keeps_names_and_extras_but_no_local_path"),
        ("assets/test_input_document.py", "test_a_validator_that_fails_says_so_in_one_line"),
        ("results/test_report_policy.py", "test_every_page_states_its_policy_first"),
        ("results/test_report_policy.py", "test_chromium_refuses_what_is_not_the_pages_own"),
    ],
    "a folder named results, a .., a read's memory, a number past Python's digit limit": [
        ("core/test_gate.py", "test_a_folder_named_results_inside_the_results_folder_is_no_second_root"),
        ("core/test_gate.py", "test_a_dotdot_is_resolved_by_name_as_it_was_checked"),
        ("core/test_gate.py", "test_a_read_takes_memory_for_what_the_file_holds_not_for_its_limit"),
        ("core/test_gate.py", "test_a_record_with_a_number_past_pythons_digit_limit_is_one_line"),
        ("config/test_received_config.py", "test_no_id_and_no_experiment_may_be_named_results"),
    ],
    "a valid run-length-encoded .hdr 256 pixels wide or more": [
        ("render/test_envmaps.py", "test_an_rle_hdr_reads_exactly_at_any_width"),
        ("render/test_envmaps.py", "test_the_reference_rle_encoder_follows_the_format"),
    ],
}


def test_every_probe_of_the_corpus_has_its_test():
    """The index above names tests that exist (a renamed or removed probe fails here)."""
    import ast

    tests = Path(__file__).resolve().parents[1]
    defined: dict[str, set[str]] = {}
    for module in {m for held in PROBES.values() for m, _ in held}:
        tree = ast.parse((tests / module).read_text())
        defined[module] = {n.name for n in tree.body if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")}
    missing = [f"{m}::{f}" for held in PROBES.values() for m, f in held if f not in defined[m]]
    assert not missing, missing


_PLAIN_IDS = st.sampled_from(["vase", "p0", "a.b-c_1", "Z9"])
_PLAIN_TEXTS = st.sampled_from(["a {object} made of wood", "=1+1 vase", "a 'vase' <b>", "ваза", "-x {object}"])


@st.composite
def accepted_configs(draw) -> dict:
    """Generated configs of the kind that pass: ids, texts and numbers within bounds, from a
    built-in mesh, with prompts a spreadsheet, a shell or HTML would misread."""
    config = {
        "meshes": {draw(_PLAIN_IDS): {"builtin": draw(st.sampled_from(["vase", "candle", "knot"]))}},
        "prompts": {draw(_PLAIN_IDS): draw(st.one_of(_PLAIN_TEXTS, st.builds(lambda t: {"text": t}, _PLAIN_TEXTS)))},
    }
    if draw(st.booleans()):
        config["raycache"] = {"views": draw(st.sampled_from([4, 8])), "anchor_azimuth": draw(st.floats(-6.0, 6.0))}
    if draw(st.booleans()):
        config["decimate"] = {"enabled": True, "mode": "share", "target_share": draw(st.floats(0.05, 0.95))}
    return config


@pytest.mark.slow(minutes=0.5)
@given(accepted_configs())
@settings(max_examples=6, deadline=None, suppress_health_check=list(HealthCheck))
def test_a_generated_config_that_passes_the_checks_runs_its_dry_run(config):
    """What the checks accept, Snakemake can plan: each generated config's dry run builds its jobs
    (a real ``snakemake -n`` in a scratch folder, about two seconds each)."""
    import tempfile

    import yaml
    from conftest import run_snakemake

    from stages.config.workflow import WorkflowConfig

    WorkflowConfig(config)  # accepted by the checks
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "generated.yaml"
        path.write_text(yaml.safe_dump(config, allow_unicode=True))
        proc = run_snakemake(Path(d), "-n", "--configfile", str(path), timeout=120)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-2000:]
