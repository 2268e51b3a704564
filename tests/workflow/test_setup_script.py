"""scripts/setup.sh installs torch's CPU build without an NVIDIA driver: from PyTorch's CPU index
(``TANGO_TORCH_INDEX`` overrides it), else, when that index cannot be reached, from the default
index after a one-line warning. Run against stub ``pip``/``python``/``npm`` that record their
arguments (nothing is installed), with a local index served here and a port nothing listens on."""

from __future__ import annotations

import functools
import http.server
import os
import shutil
import socket
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from conftest import REPO

STUB = """#!/bin/sh
echo "$(basename "$0") $*" >> "{log}"
case "$*" in
  "-c import torch") exit 1 ;;
  *"torch.__version__"*) echo 2.13.0 ;;
esac
exit 0
"""


def project(tmp_path: Path, driver: bool = False) -> tuple[Path, Path, dict]:
    """A copy of the set-up's inputs with a stub .venv (and a stub nvidia-smi where ``driver``)."""
    root = tmp_path / "p"
    (root / "scripts").mkdir(parents=True)
    for name in ("scripts/setup.sh", "scripts/torch_index.py", "pyproject.toml", "package-lock.json"):
        shutil.copy(REPO / name, root / name)
    log = tmp_path / "calls.log"
    bin_dirs = [root / ".venv" / "bin", tmp_path / "tools"]
    for d in bin_dirs:
        d.mkdir(parents=True)
    tools = ["python", "pip"]
    for name in tools:
        (bin_dirs[0] / name).write_text(STUB.format(log=log))
    (bin_dirs[0] / "activate").write_text("# activate\n")
    (bin_dirs[1] / "npm").write_text(STUB.format(log=log))
    if driver:
        (bin_dirs[1] / "nvidia-smi").write_text(STUB.format(log=log))
    for d in bin_dirs:
        for f in d.iterdir():
            f.chmod(f.stat().st_mode | stat.S_IXUSR)
    env = {k: v for k, v in os.environ.items() if k != "TANGO_TORCH_INDEX"}
    env["PATH"] = f"{bin_dirs[1]}{os.pathsep}/usr/bin{os.pathsep}/bin"
    env["PYTHON"] = sys.executable
    return root, log, env


def setup(root: Path, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "scripts/setup.sh", "test"], cwd=root, env=env, capture_output=True, text=True, timeout=120)


def torch_install(log: Path) -> str:
    (line,) = [c for c in log.read_text().splitlines() if c.startswith("pip install") and "torch==" in c]
    return line


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def local_index(tmp_path):
    """A package index served here with a page for torch."""
    root = tmp_path / "index"
    (root / "torch").mkdir(parents=True)
    (root / "torch" / "index.html").write_text("<html><body></body></html>")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()


def test_a_reachable_index_is_used_for_torch(tmp_path, local_index):
    root, log, env = project(tmp_path)
    proc = setup(root, {**env, "TANGO_TORCH_INDEX": local_index})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert torch_install(log).endswith(f"torch==2.13.0 --index-url {local_index}")
    assert f"setup: torch from {local_index}" in proc.stderr
    # the project's own install keeps the default index, with torch pinned
    assert any(c.startswith("pip install --quiet -e .[test]") for c in log.read_text().splitlines())
    assert (root / ".venv" / "constraints.txt").read_text() == "torch==2.13.0\n"


def test_an_unreachable_index_falls_back_to_the_default_with_one_warning(tmp_path):
    root, log, env = project(tmp_path)
    index = f"http://127.0.0.1:{closed_port()}/simple"
    proc = setup(root, {**env, "TANGO_TORCH_INDEX": index})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert torch_install(log).endswith("torch==2.13.0")  # the default index: no --index-url
    (warning,) = [line for line in proc.stderr.splitlines() if "warning" in line]
    assert warning.startswith(f"setup: warning: the torch index {index} cannot be reached (")
    assert "TANGO_TORCH_INDEX" in warning


def test_a_machine_with_an_nvidia_driver_takes_the_default_index(tmp_path):
    root, log, env = project(tmp_path, driver=True)
    proc = setup(root, env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert torch_install(log).endswith("torch==2.13.0") and "an NVIDIA driver is here" in proc.stderr


def test_without_a_driver_the_cpu_index_is_asked_first(tmp_path, monkeypatch):
    """No driver and no override: PyTorch's CPU index is the one tried (here unreachable by name)."""
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import torch_index
    finally:
        sys.path.remove(str(REPO / "scripts"))
    asked = []
    monkeypatch.setattr(torch_index, "has_nvidia_driver", lambda: False)
    monkeypatch.setattr(torch_index, "reachable", lambda index: asked.append(index))
    assert torch_index.index_arguments({}) == (["--index-url", torch_index.CPU_INDEX], f"torch from {torch_index.CPU_INDEX}")
    assert asked == ["https://download.pytorch.org/whl/cpu"]
    assert torch_index.index_arguments({"TANGO_TORCH_INDEX": "default"})[0] == []
