"""Which package index scripts/setup.sh installs torch from; prints pip's index arguments (or nothing).

Without an NVIDIA driver (no ``nvidia-smi``, no ``/proc/driver/nvidia``) torch comes from PyTorch's
CPU wheel index, so that pip does not fetch the multi-GB CUDA build the default index holds for
Linux; with a driver, from the default index (its CUDA build). ``TANGO_TORCH_INDEX`` names another
index (a mirror, or a CUDA index such as https://download.pytorch.org/whl/cu128); ``default``
means the default index. An index that cannot be reached is said in one line on stderr and the
default index used instead. Standard library only (it runs before the environment exists).

    python3 scripts/torch_index.py   # e.g. "--index-url https://download.pytorch.org/whl/cpu"
"""

from __future__ import annotations

import os
import shutil
import sys
import urllib.error
import urllib.request
from pathlib import Path

#: PyTorch's CPU-only wheel index
CPU_INDEX = "https://download.pytorch.org/whl/cpu"
#: seconds to wait for an index to answer
TIMEOUT = 10.0


def has_nvidia_driver() -> bool:
    """An NVIDIA driver on this machine (its tool on PATH, or the kernel module's proc entry)."""
    return shutil.which("nvidia-smi") is not None or Path("/proc/driver/nvidia/version").exists()


def reachable(index: str) -> str | None:
    """None when ``index`` answers for torch's project page, else why not (one phrase)."""
    url = index.rstrip("/") + "/torch/"
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT) as response:
            response.read(1)
    except urllib.error.HTTPError as exc:
        return f"HTTP {exc.code} for {url}"
    except (urllib.error.URLError, OSError, ValueError) as exc:
        return f"{getattr(exc, 'reason', exc)}"
    return None


def index_arguments(environ: dict[str, str] | None = None) -> tuple[list[str], str]:
    """(pip's index arguments, what was decided in words)."""
    environ = os.environ if environ is None else environ
    chosen = environ.get("TANGO_TORCH_INDEX", "").strip()
    if chosen == "default":
        return [], "torch from the default index (TANGO_TORCH_INDEX=default)"
    if not chosen:
        if has_nvidia_driver():
            return [], "torch from the default index (an NVIDIA driver is here: its CUDA build)"
        chosen = CPU_INDEX
    why = reachable(chosen)
    if why is not None:
        return [], (
            f"warning: the torch index {chosen} cannot be reached ({why}); installing torch from the default index, "
            "which may be the multi-GB CUDA build (set TANGO_TORCH_INDEX to a reachable index, or default)"
        )
    return ["--index-url", chosen], f"torch from {chosen}"


def main() -> int:
    args, said = index_arguments()
    sys.stderr.write(f"setup: {said}\n")
    sys.stdout.write(" ".join(args) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
