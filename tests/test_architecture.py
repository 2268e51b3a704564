"""The library's structure (ARCHITECTURE.md): layers whose imports only go down, stage modules that
never import each other, one stage module per rule, no import hidden in a function to dodge a
cycle, and a workflow whose DAG builds without torch."""

import ast
import importlib
import os
import re
import shutil
import subprocess
import sys

import pytest
from conftest import REPO, require_tool

STAGES = REPO / "stages"
#: the modules at the top of stages/ that are commands, not rules (ARCHITECTURE.md)
COMMANDS = ("doctor", "plan", "quick")
#: the library's layers, top to bottom (as in pyproject.toml's import contract)
LAYERS = (
    "testing",
    "training",
    "assets",
    "results",
    "reference",
    "guidance",
    "imaging",
    "model",
    "render",
    "geometry",
    "config",
    "core",
)


def rules() -> dict[str, str]:
    """Rule name -> the stage module its shell line runs (``python -m stages.<module>``)."""
    out = {}
    for smk in sorted((REPO / "workflow" / "rules").glob("*.smk")):
        text = smk.read_text()
        for m in re.finditer(r"^rule (\w+):\n(.*?)(?=^rule |\Z)", text, re.S | re.M):
            called = re.findall(r"python -m stages\.(\w+)", m.group(2))
            assert len(called) == 1, f"rule {m.group(1)} ({smk.name}) must call exactly one stage"
            out[m.group(1)] = called[0]
    return out


def test_import_contracts_hold():
    """import-linter's layers, independence and forbidden contracts (pyproject.toml)."""
    exe = shutil.which("lint-imports", path=os.path.dirname(sys.executable)) or shutil.which("lint-imports")
    require_tool(exe is not None, "import-linter is not installed (pip install -e '.[test]')")
    proc = subprocess.run([exe, "--no-cache"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


def test_every_rule_runs_its_own_thin_stage_module():
    found = rules()
    assert {"normalize", "decimate", "raycache", "optimize", "bake", "export", "relight", "metrics"} <= set(found)
    # (stages/__main__.py: the tango command in front of the commands, run by no rule)
    stage_files = {p.stem for p in STAGES.glob("*.py") if p.stem not in ("__init__", "__main__")} - set(COMMANDS)
    assert set(found.values()) == stage_files, "every stage module is run by a rule, and only stage modules sit in stages/"
    for command in COMMANDS:  # the commands beside them (not rules): python -m stages.<command>
        assert callable(importlib.import_module(f"stages.{command}").main), command
    for rule, module in found.items():
        assert rule == module, f"rule {rule} runs stages.{module}: name them alike"
        mod = importlib.import_module(f"stages.{module}")
        assert callable(mod.run) and callable(mod.main), module


def test_per_cell_rules_write_the_folder_named_after_them():
    """Rule ``export`` writes ``export/``: each per-cell rule's outputs sit in its own folder."""
    common = (REPO / "workflow" / "rules" / "common.smk").read_text()
    for stage in ("optimize", "bake", "export", "relight", "metrics"):
        smk = (REPO / "workflow" / "rules" / f"{stage}.smk").read_text()
        folders = set(re.findall(r"\{CELL\}/(\w+)/", smk + common)) - {"logs", "benchmarks"}
        assert stage in folders, stage
    assert "{CELL}/asset/" not in common


def test_no_project_import_inside_a_function():
    """Function-local imports hide cycles; third-party ones (heavy or optional packages) are fine."""
    offenders = []
    for path in sorted(STAGES.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                for sub in ast.walk(node):
                    if isinstance(sub, ast.ImportFrom) and (sub.level or (sub.module or "").startswith("stages")):
                        offenders.append(f"{path.relative_to(REPO)}:{sub.lineno}")
                    if isinstance(sub, ast.Import) and any(a.name.startswith("stages") for a in sub.names):
                        offenders.append(f"{path.relative_to(REPO)}:{sub.lineno}")
    assert not offenders, offenders


def test_layers_are_packages_with_a_description():
    for layer in LAYERS:
        init = STAGES / layer / "__init__.py"
        assert init.is_file(), layer
        assert ast.get_docstring(ast.parse(init.read_text())), f"stages/{layer}/__init__.py says what the layer holds"
    assert (REPO / "ARCHITECTURE.md").is_file()
    text = (REPO / "ARCHITECTURE.md").read_text()
    for layer in LAYERS:
        assert f"stages/{layer}" in text, layer


def test_dry_run_builds_the_dag_without_torch(tmp_path):
    """``snakemake -n`` on the default config imports neither torch nor numpy's heavy users."""
    code = (
        "import sys\n"
        "from snakemake.cli import main\n"
        "try:\n"
        "    main(['-n', '--quiet', '--directory', sys.argv[1], '--snakefile', sys.argv[2]])\n"
        "except SystemExit as exc:\n"
        "    assert not exc.code, exc.code\n"
        "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH')\n"
    )
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    (tmp_path / "config").mkdir()
    shutil.copy(REPO / "config" / "config.yaml", tmp_path / "config" / "config.yaml")
    proc = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path), str(REPO / "Snakefile")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "NO-TORCH"


def test_importing_the_settings_loads_no_torch():
    code = "import sys, stages.config.workflow, stages.config.sections, stages.config.layout; print('torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() == "False", proc.stderr


@pytest.mark.parametrize("stage", ["html_report", "report", "pack", "export"])
def test_stages_that_need_no_torch_start_without_it(stage):
    """The stages whose work needs no torch start without importing it (about 1.2 s a job): the
    report's viewer path is in ``core.tools``, the BRDFs' asset facts in the torch-free
    ``config.brdfs`` rows. (``plan`` calibrates with torch and imported it already at dbef3c0.)"""
    code = f"import sys, stages.{stage}; print('torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() == "False", proc.stderr


@pytest.mark.parametrize(
    "helper",
    ["psnr", "ssim", "linear_to_srgb", "srgb_encode", "stage_main", "resolve_device", "contact_sheet", "save_png", "clip_spec"],
)
def test_each_shared_helper_is_defined_once(helper):
    defined = [str(p.relative_to(REPO)) for p in STAGES.rglob("*.py") if re.search(rf"^\s*def {helper}\(", p.read_text(), re.M)]
    assert len(defined) == 1, defined


#: the longest function (lines) and the most parameters (self aside) a function of stages/ may have
MAX_FUNCTION_LINES, MAX_PARAMETERS = 100, 10


def _function_sizes():
    for path in sorted(STAGES.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names = [*a.posonlyargs, *a.args, *a.kwonlyargs, *filter(None, (a.vararg, a.kwarg))]
                params = len([n for n in names if n.arg not in ("self", "cls")])
                yield f"{path.relative_to(REPO)}:{node.name}", node.end_lineno - node.lineno + 1, params


def test_no_function_is_longer_or_takes_more_parameters_than_one_reads_at_once():
    sizes = list(_function_sizes())
    assert len(sizes) > 900  # every function of stages/ was read (979 when this was written)
    over = {name: (lines, params) for name, lines, params in sizes if lines > MAX_FUNCTION_LINES or params > MAX_PARAMETERS}
    assert not over, f"past {MAX_FUNCTION_LINES} lines or {MAX_PARAMETERS} parameters (lines, parameters): {over}"


def _edits_sys_path(node: ast.AST) -> bool:
    """Whether ``node`` (a statement) reads or changes ``sys.path``."""
    return any(
        isinstance(n, ast.Attribute) and n.attr == "path" and isinstance(n.value, ast.Name) and n.value.id == "sys"
        for n in ast.walk(node)
    )


def test_benchmarks_are_modules_of_one_package_that_no_test_imports():
    """The benchmarks run as ``python -m benchmarks.<topic>.<name>``: none edits ``sys.path`` (the
    import contracts in pyproject.toml keep each to ``stages`` and ``benchmarks.common``); no test
    imports a benchmark or puts benchmarks/ on its path (what a test needs of one lives in
    ``stages``, as the recovery protocol and the precision judge in ``stages.testing`` do)."""
    offenders = []
    for path in sorted((REPO / "benchmarks").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.stmt) and not isinstance(node, ast.FunctionDef | ast.ClassDef) and _edits_sys_path(node):
                offenders.append(f"{path.relative_to(REPO)}:{node.lineno} uses sys.path")
    for path in sorted((REPO / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            names += [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n == "benchmarks" or n.startswith("benchmarks.") for n in names):
                offenders.append(f"{path.relative_to(REPO)}:{node.lineno} imports a benchmark")
            if isinstance(node, ast.Expr | ast.Assign) and _edits_sys_path(node) and "benchmarks" in ast.unparse(node):
                offenders.append(f"{path.relative_to(REPO)}:{node.lineno} puts benchmarks/ on the path")
    assert not offenders, offenders
