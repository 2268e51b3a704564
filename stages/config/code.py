"""Digests of the code a job runs, for Snakemake's params: a rule's job reruns when the source
of its stage module, or of any module of this package it imports (transitively), changes.

Found without importing anything (building the DAG imports no torch): each module's file is
parsed (``ast``) for its ``import``/``from ... import`` statements naming this package, resolved
to files, and followed. The digest hashes each file's syntax tree (``ast.dump``), so comments and
formatting do not rerun jobs; code and docstrings do. Imports inside functions count too (the
stages import heavy dependencies lazily, and a few of their own modules the same way). The files a
package ships besides its modules (its folders that are not packages: ``render/data/``, the
report's ``results/web/``) count byte for byte with every module of that package. Third-party
code is not followed: its versions are recorded in every output's metadata instead.
"""

from __future__ import annotations

import ast
import hashlib
from functools import cache
from pathlib import Path

from ..core.safefiles import DATA_LIMIT, read_bytes, read_text

PACKAGE = "stages"
ROOT = Path(__file__).resolve().parents[1]  # the stages/ folder


def module_file(name: str, root: Path = ROOT) -> Path | None:
    """``stages.a.b`` -> ``<root>/a/b.py`` or ``<root>/a/b/__init__.py``; None if neither exists."""
    parts = name.split(".")[1:]
    base = root.joinpath(*parts)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _tree(path: Path) -> ast.Module:
    st = path.stat()
    return _parse(path, st.st_mtime_ns, st.st_size)


@cache
def _parse(path: Path, mtime_ns: int, size: int) -> ast.Module:
    """Parsed once per version of a file (the key has its modification time and size)."""
    return ast.parse(read_text(path), str(path))


def _imported(path: Path, name: str, root: Path) -> frozenset[str]:
    """The modules of this package that ``path`` (module ``name``) imports, anywhere in its body."""
    return _imports_of(_tree(path), path, name, root)


@cache
def _imports_of(tree: ast.Module, path: Path, name: str, root: Path) -> frozenset[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.split(".")[0] == PACKAGE)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != PACKAGE:
                continue
            out.add(target)
            # "from .pkg import mod" imports a module when mod is one
            out.update(f"{target}.{a.name}" for a in node.names if module_file(f"{target}.{a.name}", root))
    # importing a.b.c runs a/__init__.py and a/b/__init__.py too
    for mod in list(out):
        parts = mod.split(".")
        out.update(".".join(parts[:i]) for i in range(1, len(parts)))
    return frozenset(m for m in out if module_file(m, root))


def module_closure(name: str, root: Path = ROOT) -> dict[str, Path]:
    """Every module of this package that running ``name`` may import: ``{module: file}``."""
    seen: dict[str, Path] = {}
    todo = [name]
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        path = module_file(mod, root)
        if path is None:
            raise ValueError(f"no module {mod!r} under {root}")
        seen[mod] = path
        todo.extend(_imported(path, mod, root) - seen.keys())
    return seen


def package_data(package_dir: Path) -> list[Path]:
    """The files a package ships besides its modules: everything under its sub-folders that are
    not packages themselves (no ``__init__.py``; caches aside), sorted."""
    out: list[Path] = []
    for sub in sorted(package_dir.iterdir()):
        if sub.is_dir() and sub.name != "__pycache__" and not (sub / "__init__.py").is_file():
            out += sorted(p for p in sub.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    return out


def code_digest(name: str, root: Path = ROOT) -> str:
    """16 hex characters: the SHA-256 of the syntax trees of :func:`module_closure` of ``name``,
    in module order, and of the data files of every package among them (:func:`package_data`)."""
    h = hashlib.sha256()
    for mod, path in sorted(module_closure(name, root).items()):
        h.update(mod.encode())
        h.update(_tree_digest(_tree(path)))
        if path.name == "__init__.py":
            for data in package_data(path.parent):
                st = data.stat()
                h.update(data.relative_to(root).as_posix().encode())
                h.update(_file_digest(data, st.st_mtime_ns, st.st_size))
    return h.hexdigest()[:16]


@cache
def _file_digest(path: Path, mtime_ns: int, size: int) -> bytes:
    """A data file's SHA-256, computed once per version of the file."""
    return hashlib.sha256(read_bytes(path, DATA_LIMIT)).digest()


@cache
def _tree_digest(tree: ast.Module) -> bytes:
    return hashlib.sha256(ast.dump(tree).encode()).digest()
