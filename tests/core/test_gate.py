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

#: calls by their full dotted name (import aliases resolved) that open, read, delete, copy, link or
#: move a file by its path
FORBIDDEN_FUNCTIONS = {
    "open",
    "builtins.open",
    "io.open",
    "io.FileIO",
    "os.open",
    "json.load",
    "pickle.load",
    "pandas.read_csv",
    "numpy.load",
    "numpy.fromfile",
    "numpy.loadtxt",
    "PIL.Image.open",
    "torch.load",
    "trimesh.load",
    "zipfile.ZipFile",
    "zipfile.is_zipfile",
    "OpenEXR.File",
    "os.remove",
    "os.unlink",
    "os.rename",
    "os.replace",
    "os.rmdir",
    "os.truncate",
    "os.link",
    "os.symlink",
    "shutil.rmtree",
    "shutil.copy",
    "shutil.copy2",
    "shutil.copyfile",
    "shutil.copytree",
    "shutil.move",
}
#: methods of a path that read, delete, link or move a file
FORBIDDEN_METHODS = {"read_text", "read_bytes", "unlink", "rmdir", "rename", "touch", "symlink_to", "hardlink_to"}
#: what writes a file in place, and which argument is the file: only onto a name the gate gave
#: (``with atomic_path(...) as tmp``, ``with atomic_stream(...) as fh``)
WRITERS = {"numpy.save": 0, "numpy.savez": 0, "numpy.savez_compressed": 0, "torch.save": 1}
WRITE_METHODS = {"write_text": None, "write_bytes": None, "save": 0, "to_csv": 0}
#: the gate's readers and writers: what they opened is the gate's
GATE_CALLS = {"open_read", "read_bytes", "read_text", "atomic_path", "atomic_stream", "StringIO", "BytesIO"}

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
    ("reference/blender_job.py", "inspect", "numpy.savez"): "runs inside Blender's Python, in the judge's own temporary folder",
    ("reference/blender_job.py", "render", "numpy.save"): "runs inside Blender's Python, in the judge's own temporary folder",
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


def aliases(tree: ast.AST) -> dict[str, str]:
    """Every name an import binds in a module, to what it stands for (``np`` -> ``numpy``,
    ``rmtree`` -> ``shutil.rmtree``, ``Image`` -> ``PIL.Image``); relative imports left out."""
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                out[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                out[a.asname or a.name] = f"{node.module}.{a.name}"
    return out


class Scanner(ast.NodeVisitor):
    """Every forbidden call of one module, with its enclosing function; a reader handed what the
    gate opened (``np.load(open_read(...))``, or a name bound by ``with open_read(...) as fh``)
    and a writer onto a name the gate gave are the gate's."""

    def __init__(self, module: str, names: dict[str, str]):
        self.module = module
        self.names = names
        self.stack: list[str] = []
        self.gated: list[set[str]] = [set()]
        self.findings: list[Finding] = []

    def full(self, node: ast.AST) -> str:
        """The dotted name of ``node`` with its first part's import resolved."""
        name = dotted(node)
        head, _, rest = name.partition(".")
        return ".".join(x for x in (self.names.get(head, head), rest) if x)

    def gate_call(self, node: ast.AST) -> bool:
        return isinstance(node, ast.Call) and dotted(node.func).split(".")[-1] in GATE_CALLS

    def given(self, node: ast.AST | None) -> bool:
        """``node`` is what the gate opened or gave."""
        return node is not None and (self.gate_call(node) or (isinstance(node, ast.Name) and node.id in self.gated[-1]))

    def _function(self, node):
        self.stack.append(node.name)
        self.gated.append(set())
        self.generic_visit(node)
        self.gated.pop()
        self.stack.pop()

    visit_FunctionDef = visit_AsyncFunctionDef = _function

    def visit_With(self, node: ast.With):
        for item in node.items:
            if self.gate_call(item.context_expr) and isinstance(item.optional_vars, ast.Name):
                self.gated[-1].add(item.optional_vars.id)
        self.generic_visit(node)

    def _find(self, node: ast.Call, what: str) -> None:
        self.findings.append(Finding(self.module, ".".join(self.stack) or "<module>", what, node.lineno))

    def visit_Call(self, node: ast.Call):
        name, func = self.full(node.func), node.func
        first = node.args[0] if node.args else None
        if name in FORBIDDEN_FUNCTIONS and not self.given(first):
            self._find(node, name)
        elif name in WRITERS:
            at = WRITERS[name]
            if not self.given(node.args[at] if len(node.args) > at else None):
                self._find(node, name)
        elif isinstance(func, ast.Attribute) and name not in WRITERS:
            method = func.attr
            if method in FORBIDDEN_METHODS:
                self._find(node, method)
            elif method in WRITE_METHODS:
                at = WRITE_METHODS[method]
                target = func.value if at is None else (node.args[at] if len(node.args) > at else None)
                if not self.given(target):
                    self._find(node, method)
            # Path.replace(target) takes one argument; str.replace two, dataclasses.replace keywords
            elif method == "replace" and len(node.args) == 1 and not node.keywords:
                if name != "dataclasses.replace" and not isinstance(func.value, ast.Constant):
                    self._find(node, method)
        self.generic_visit(node)


def scan(source: str, module: str = "x.py") -> list[Finding]:
    tree = ast.parse(source)
    scanner = Scanner(module, aliases(tree))
    scanner.visit(tree)
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


#: the imports the scanner's examples use
PRELUDE = "import io, json, os, shutil, zipfile\nimport numpy as np\nimport pandas as pd\nimport torch\nfrom PIL import Image\n"


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
        "from shutil import rmtree\nrmtree(d)",
        "import os as o\no.remove(p)",
        "os.open(p, os.O_RDONLY)",
        "io.FileIO(p)",
        "zipfile.ZipFile(p)",
        "zipfile.is_zipfile(p)",
        "os.link(a, b)",
        "p.touch()",
        "p.symlink_to(q)",
        "np.save(p, a)",
        "np.savez(p, a=a)",
        "torch.save(obj, p)",
        "img.save(folder / 'thumb.png')",
        "frame.to_csv(p)",
    ],
)
def test_the_scanner_finds_each_kind_of_direct_file_operation(source):
    """Mutation check of the walk: each forbidden form, written directly, is found."""
    assert len(scan(PRELUDE + source)) == 1, scan(PRELUDE + source)


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
        "with atomic_stream(p) as fh:\n    np.savez(fh, a=a)",
        "with atomic_path(p) as tmp:\n    img.save(tmp, format='PNG')",
        "with atomic_path(p) as tmp:\n    torch.save(obj, tmp)",
        "with atomic_path(p) as tmp:\n    frame.to_csv(tmp, index=False)",
        "with open_read(p, 9) as fh, zipfile.ZipFile(fh) as z:\n    pass",
    ],
)
def test_the_scanner_passes_the_gates_own_forms(source):
    assert scan(PRELUDE + source) == []


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


def test_a_read_takes_memory_for_what_the_file_holds_not_for_its_limit(tmp_path):
    """Under an address-space limit of 2 GiB (a login node's ``ulimit -v``), a small file reads
    with the 16 GiB limit of arrays: the limit bounds the read, it is not reserved."""
    import subprocess
    import sys

    small = tmp_path / "mesh.obj"
    small.write_text("v 0 0 0\n")
    code = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30)); "
        "from stages.core.safefiles import DATA_LIMIT, read_bytes; "
        "sys.stdout.write(read_bytes(sys.argv[1], DATA_LIMIT).decode())"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(small)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout == "v 0 0 0\n", proc.stderr[-2000:]


def test_a_folder_named_results_inside_the_results_folder_is_no_second_root(results, tmp_path):
    """The outermost folder named ``results`` is the root: a link named ``results`` further down
    (where no id may be ``results``) is one more link on the way, not a root that may be one."""
    secret = tmp_path / "secret"
    secret.mkdir()
    (secret / "summary.csv").write_text("TOP SECRET")
    (results / "exp" / "bunny").mkdir()
    (results / "exp" / "bunny" / "results").symlink_to(secret, target_is_directory=True)
    assert safefiles.results_root(results / "exp" / "bunny" / "results" / "summary.csv") == results
    with pytest.raises(StageInputError, match="reached through .*bunny/results, which is a symbolic link"):
        safefiles.read_text(results / "exp" / "bunny" / "results" / "summary.csv")


def test_a_dotdot_is_resolved_by_name_as_it_was_checked(results, tmp_path):
    """``exp/link/../summary.csv`` is checked as ``exp/summary.csv`` and opened as that, never
    through the link."""
    outside = tmp_path / "outside"
    (outside / "deeper").mkdir(parents=True)
    (outside / "summary.csv").write_text("outside")
    (results / "exp" / "summary.csv").write_text("inside")
    (results / "exp" / "link").symlink_to(outside / "deeper", target_is_directory=True)
    assert safefiles.read_text(f"{results}/exp/link/../summary.csv") == "inside"


def test_a_record_with_a_number_past_pythons_digit_limit_is_one_line(results):
    record = results / "exp" / "meta.json"
    record.write_text('{"seconds_per_iteration": ' + "9" * 5000 + "}")
    with pytest.raises(StageInputError, match="is not a record of plain values"):
        safefiles.read_json(record)


def test_a_users_own_linked_file_outside_results_is_followed(tmp_path):
    """A mesh or a light map the user links from a store of their own (outside any results
    folder) is theirs: read and hashed through the link, as the stages' metadata hash inputs."""
    from stages.core.provenance import sha256_of

    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "real.obj").write_text("v 0 0 0\n")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "bunny.obj").symlink_to(tmp_path / "store" / "real.obj")
    import hashlib

    assert sha256_of(tmp_path / "data" / "bunny.obj") == hashlib.sha256(b"v 0 0 0\n").hexdigest()
    assert safefiles.read_text(safefiles.user_file(tmp_path / "data" / "bunny.obj")) == "v 0 0 0\n"


def test_place_links_the_entry_checked_or_copies(results, tmp_path):
    src = results / "exp" / "model.glb"
    src.write_bytes(b"glb")
    safefiles.place(src, results / "exp" / "report" / "model.glb")
    assert (results / "exp" / "report" / "model.glb").read_bytes() == b"glb"
    (results / "exp" / "linked.glb").symlink_to(tmp_path)
    with pytest.raises(StageInputError, match="it is a symbolic link inside"):
        safefiles.place(results / "exp" / "linked.glb", results / "exp" / "report" / "linked.glb")
    assert not (results / "exp" / "report" / "linked.glb").exists()


def test_place_undoes_a_link_swapped_in_after_the_check(results, tmp_path, monkeypatch):
    """A file swapped for a link between the check and the hard link (the name check is made to
    pass here, as a race would): the link made is undone and refused, nothing of the target is
    placed."""
    secret = tmp_path / "id_rsa"
    secret.write_text("KEY")
    swapped = results / "exp" / "model.glb"
    swapped.symlink_to(secret)
    monkeypatch.setattr(safefiles, "require_plain_file", lambda path, root=None, remedy="": Path(path))
    target = results / "exp" / "report" / "model.glb"
    with pytest.raises(StageInputError, match="changed into something other than a plain file while it was linked"):
        safefiles.place(swapped, target)
    assert not target.exists() and not target.is_symlink()
