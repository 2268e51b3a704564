"""The gate holds: every read, write, delete, copy and rename in ``stages/`` goes through
``stages/core/safefiles.py`` (plain files only, no link inside a results folder, no FIFO or device,
a size limit), found by walking the code; and each of the gate's checks is needed (a test below
fails when it is taken out)."""

from __future__ import annotations

import ast
import os
import socket
from dataclasses import dataclass
from pathlib import Path

import pytest

from stages.core import safefiles
from stages.core.errors import StageInputError

STAGES = Path(__file__).resolve().parents[2] / "stages"
GATE = STAGES / "core" / "safefiles.py"

#: calls by their dotted name that read, delete, copy or move a file by its path
FORBIDDEN_FUNCTIONS = {
    "open",
    "io.open",
    "json.load",
    "pickle.load",
    "pd.read_csv",
    "pandas.read_csv",
    "np.load",
    "numpy.load",
    "np.fromfile",
    "np.loadtxt",
    "Image.open",
    "PIL.Image.open",
    "torch.load",
    "trimesh.load",
    "os.remove",
    "os.unlink",
    "os.rename",
    "os.replace",
    "os.rmdir",
    "shutil.rmtree",
    "shutil.copy",
    "shutil.copy2",
    "shutil.copyfile",
    "shutil.copytree",
    "shutil.move",
    "OpenEXR.File",
}
#: methods of a path that read, delete or move a file
FORBIDDEN_METHODS = {"read_text", "read_bytes", "unlink", "rmdir", "rename"}
#: methods of a path that write it in place: only on the temporary path of ``atomic_path``
WRITE_METHODS = {"write_text", "write_bytes"}
#: the gate's readers: a forbidden reader handed what they opened or read is the gate's read
GATE_READERS = {"open_read", "read_bytes", "read_text", "io.StringIO", "io.BytesIO", "StringIO", "BytesIO"}

#: where a library must open a file itself, or the file is not a results folder's: (module,
#: function, call) -> why. Each entry is needed (a test fails on an entry no call uses).
ALLOWED = {
    ("__init__.py", "_version", "read_text"): "the package's own pyproject.toml (a source checkout's version), read "
    "by the package's top module, which imports none of its sub-packages",
    ("geometry/meshio.py", "load_mesh", "trimesh.load"): "trimesh opens the user's mesh itself, to find a glTF's buffers "
    "and an OBJ's materials beside it; the gate checked it a plain file first (require_plain_file)",
    ("render/hdrio.py", "read_exr", "OpenEXR.File"): "OpenEXR reads only by a file's name; the gate checked it a plain "
    "file first (require_plain_file) and the header is read and bounded before the pixels",
    ("render/hdrio.py", "write_exr", "OpenEXR.File"): "builds the image to write (its header and channels), not a read",
    ("reference/blender_job.py", "main", "read_text"): "runs inside Blender's Python, without this package, on the job "
    "file the judge wrote into its own temporary folder",
    ("reference/blender_job.py", "render", "unlink"): "runs inside Blender's Python, in the judge's own temporary folder",
    ("reference/blender_job.py", "main", "write_text"): "runs inside Blender's Python, in the judge's own temporary folder",
}


@dataclass(frozen=True)
class Finding:
    module: str
    function: str
    call: str
    line: int

    def __str__(self) -> str:
        return f"stages/{self.module}:{self.line} {self.function}: {self.call}(...) outside stages/core/safefiles.py"


def dotted(node: ast.AST) -> str:
    """``a.b.c`` for a name or attribute chain, else ''."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        inner = dotted(node.value)
        return f"{inner}.{node.attr}" if inner else ""
    return ""


def _gate_call(node: ast.AST) -> bool:
    return isinstance(node, ast.Call) and dotted(node.func).split(".")[-1] in {g.split(".")[-1] for g in GATE_READERS}


def forbidden_call(call: ast.Call) -> str | None:
    """The name of what ``call`` does to a file by path, or None."""
    name = dotted(call.func)
    if name in FORBIDDEN_FUNCTIONS:
        return name
    if isinstance(call.func, ast.Attribute):
        method = call.func.attr
        if method in FORBIDDEN_METHODS:
            return method
        # Path.replace(target) takes one argument; str.replace two, dataclasses.replace keywords
        if method == "replace" and len(call.args) == 1 and not call.keywords and dotted(call.func.value) != "dataclasses":
            if not isinstance(call.func.value, ast.Constant):
                return method
    return None


class Scanner(ast.NodeVisitor):
    """Every forbidden call of one module, with its enclosing function; a forbidden reader whose
    first argument the gate opened (``np.load(open_read(...))``, or a name bound by ``with
    open_read(...) as fh``) is the gate's."""

    def __init__(self, module: str):
        self.module = module
        self.stack: list[str] = []
        self.gated: list[set[str]] = [set()]
        self.findings: list[Finding] = []

    def _function(self, node):
        self.stack.append(node.name)
        self.gated.append(set())
        self.generic_visit(node)
        self.gated.pop()
        self.stack.pop()

    visit_FunctionDef = visit_AsyncFunctionDef = _function

    def visit_With(self, node: ast.With):
        for item in node.items:
            atomic = isinstance(item.context_expr, ast.Call) and dotted(item.context_expr.func).endswith("atomic_path")
            if (_gate_call(item.context_expr) or atomic) and isinstance(item.optional_vars, ast.Name):
                self.gated[-1].add(item.optional_vars.id)
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call):
        func = node.func
        if isinstance(func, ast.Attribute) and func.attr in WRITE_METHODS:
            if not (isinstance(func.value, ast.Name) and func.value.id in self.gated[-1]):
                self.findings.append(Finding(self.module, ".".join(self.stack) or "<module>", func.attr, node.lineno))
        name = forbidden_call(node)
        if name is not None:
            first = node.args[0] if node.args else None
            gated = first is not None and (_gate_call(first) or (isinstance(first, ast.Name) and first.id in self.gated[-1]))
            if not gated:
                self.findings.append(Finding(self.module, ".".join(self.stack) or "<module>", name, node.lineno))
        self.generic_visit(node)


def scan(source: str, module: str = "x.py") -> list[Finding]:
    scanner = Scanner(module)
    scanner.visit(ast.parse(source))
    return scanner.findings


def all_findings() -> list[Finding]:
    out = []
    for path in sorted(STAGES.rglob("*.py")):
        if path != GATE:
            out += scan(path.read_text(), str(path.relative_to(STAGES)))
    return out


def _allowed(f: Finding) -> bool:
    return (f.module, f.function.split(".")[-1], f.call) in ALLOWED


def test_every_file_operation_in_stages_goes_through_the_gate():
    outside = [str(f) for f in all_findings() if not _allowed(f)]
    assert not outside, "\n".join(outside)


def test_every_allowed_entry_is_used():
    used = {(f.module, f.function.split(".")[-1], f.call) for f in all_findings()}
    assert not set(ALLOWED) - used, set(ALLOWED) - used


@pytest.mark.parametrize(
    "source",
    [
        "open(p)",
        "json.load(fh)",
        "p.read_text()",
        "Path(p).read_bytes()",
        "pd.read_csv(p)",
        "np.load(p)",
        "Image.open(p)",
        "torch.load(p, weights_only=True)",
        "p.unlink(missing_ok=True)",
        "shutil.rmtree(d)",
        "shutil.copyfile(a, b)",
        "os.replace(a, b)",
        "tmp.replace(target)",
        "p.rename(q)",
        "with open_read(p, 9) as fh:\n    pass\nnp.load(other)",
        "p.write_text('x')",
        "with atomic_path(p) as tmp:\n    other.write_bytes(b'x')",
    ],
)
def test_the_scanner_finds_each_kind_of_direct_file_operation(source):
    """Mutation check of the walk: each forbidden form, written directly, is found."""
    assert len(scan(source)) == 1, scan(source)


@pytest.mark.parametrize(
    "source",
    [
        "text.replace('a', 'b')",
        "dataclasses.replace(s, x=1)",
        "np.load(open_read(p, 9))",
        "with open_read(p, 9) as fh, np.load(fh) as z:\n    pass",
        "pd.read_csv(io.StringIO(read_text(p)))",
        "Image.open(io.BytesIO(read_bytes(p, 9)))",
        "with atomic_path(p) as tmp:\n    tmp.write_text('x')",
    ],
)
def test_the_scanner_passes_the_gates_own_forms(source):
    assert scan(source) == []


# ----------------------------------------------------------------- each check of the gate needed
@pytest.fixture
def results(tmp_path):
    root = tmp_path / "results"
    (root / "exp" / "report" / "figures").mkdir(parents=True)
    return root


def test_open_read_refuses_a_link_a_link_on_the_way_a_fifo_a_device_and_a_large_file(results, tmp_path):
    outside = tmp_path / "outside.csv"
    outside.write_text("secret,1\n")
    report = results / "exp" / "report"
    (report / "summary.csv").symlink_to(outside)
    (report / "other").symlink_to(tmp_path, target_is_directory=True)
    os.mkfifo(report / "pipe.json")
    (report / "big.json").write_text("[" + "0," * 100 + "0]")
    for name, words in [
        ("summary.csv", "it is a symbolic link inside"),
        ("other/outside.csv", "reached through .*other, which is a symbolic link"),
        ("pipe.json", "is a FIFO, not a plain file"),
        ("big.json", "more than the 100 such a file may hold"),
    ]:
        with pytest.raises(StageInputError, match=words) as err:
            safefiles.read_text(report / name, limit=100)
        assert "\n" not in str(err.value) and "secret" not in str(err.value)
    with pytest.raises(StageInputError, match="is a device, not a plain file"):
        safefiles.read_bytes("/dev/zero", 100)
    (report / "ok.json").write_text('{"a": 1}')
    assert safefiles.read_json(report / "ok.json") == {"a": 1}


def test_open_read_checks_the_handle_it_opened(results, monkeypatch):
    """A file swapped for a FIFO between the check and the open is refused on the handle (the
    name check is made to pass here, as a race would)."""
    pipe = results / "exp" / "pipe.json"
    os.mkfifo(pipe)
    monkeypatch.setattr(safefiles, "require_plain_file", lambda path, root=None, remedy="": Path(path))
    with pytest.raises(StageInputError, match="changed into something other than a plain file"):
        safefiles.open_read(pipe, 100)


def test_open_read_does_not_follow_a_link_swapped_in(results, tmp_path, monkeypatch):
    secret = tmp_path / "secret"
    secret.write_text("x")
    link = results / "exp" / "meta.json"
    link.symlink_to(secret)
    monkeypatch.setattr(safefiles, "require_plain_file", lambda path, root=None, remedy="": Path(path))
    with pytest.raises(StageInputError, match="could not be opened"):
        safefiles.open_read(link, 100)


def test_a_record_nested_past_the_parser_is_one_line(results):
    deep = results / "exp" / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(StageInputError, match="nested too deeply"):
        safefiles.read_json(deep)


def test_deletes_refuse_a_linked_folder_and_delete_only_entries(results, tmp_path):
    pictures = tmp_path / "pictures"
    pictures.mkdir()
    (pictures / "holiday.png").write_bytes(b"png")
    report = results / "exp" / "report"
    (report / "figures").rmdir()
    (report / "figures").symlink_to(pictures, target_is_directory=True)
    with pytest.raises(StageInputError, match="would be cleared through .*figures, a symbolic link"):
        safefiles.clear(report / "figures", "*.png")
    with pytest.raises(StageInputError, match="would be deleted through .*figures, a symbolic link"):
        safefiles.remove(report / "figures" / "holiday.png")
    with pytest.raises(StageInputError, match="would be deleted through .*figures, a symbolic link"):
        safefiles.remove_tree(report / "figures")
    assert (pictures / "holiday.png").read_bytes() == b"png"
    # a link inside a plain folder: the link goes, never what it points to
    (report / "cells").mkdir()
    (report / "cells" / "link.png").symlink_to(pictures / "holiday.png")
    assert safefiles.clear(report / "cells", "*.png") == [report / "cells" / "link.png"]
    (report / "cells" / "inner").symlink_to(pictures, target_is_directory=True)
    safefiles.remove_tree(report / "cells")
    assert not (report / "cells").exists() and (pictures / "holiday.png").is_file()


def test_a_rename_and_a_copy_refuse_a_linked_folder(results, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    exp = results / "exp"
    (exp / "export").symlink_to(elsewhere, target_is_directory=True)
    (exp / "a.txt").write_text("a")
    with pytest.raises(StageInputError, match="would be written through"):
        safefiles.replace(exp / "a.txt", exp / "export" / "a.txt")
    with pytest.raises(StageInputError, match="would be written through"):
        safefiles.copy_file(exp / "a.txt", exp / "export" / "b.txt")
    assert not list(elsewhere.iterdir())


def test_a_socket_is_not_a_plain_file(results):
    path = results / "exp" / "s.json"
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(path))
        with pytest.raises(StageInputError, match="is a socket, not a plain file"):
            safefiles.read_json(path)


def test_a_name_with_a_nul_or_control_character_is_one_line(results):
    for name in ("a\x00.png", "a\n.png", "a\x85.png"):
        with pytest.raises(StageInputError, match="holds a control character"):
            safefiles.inside(results, name)
