"""Which libLLVM Mitsuba's vectorised variant runs on (:mod:`stages.reference.mitsuba`): the user's
``DRJIT_LIBLLVM_PATH`` always, else the newest system libLLVM 16+, else the ``karellen-llvm-core``
wheel's (the ``reference`` extra installs it), its C++ runtime loaded first; where none loads,
``scalar_rgb``. CI installs libllvm19, so the wheel's path is taken here with the system folders
hidden (``TANGO_LIBLLVM_DIRS`` empty), in fresh processes (a process loads one libLLVM once)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, require_tool

from stages.reference import mitsuba as mref


def wheel() -> mref.LibLLVM:
    lib = mref.wheel_libllvm()
    require_tool(lib is not None, "the karellen-llvm-core wheel is not installed (pip install -e '.[reference]')")
    return lib


def clean_env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("DRJIT_LIBLLVM_PATH", "TANGO_LIBLLVM_DIRS")}
    return {**env, **extra}


def python(code: str, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize(
    "name, expected",
    [
        ("libLLVM.so.19.1", (19, "19.1")),
        ("libLLVM-17.so.1", (17, "17")),
        ("libLLVM.so.23.1", (23, "23.1")),
        ("libLLVM-15.so", (15, "15")),
        ("libLLVM.so", None),
        ("libLLVMSupport.a", None),
    ],
)
def test_versions_from_file_names(name, expected):
    assert mref._llvm_version(name) == expected


def test_the_newest_system_library_of_16_or_later_is_chosen(tmp_path, monkeypatch):
    """Names only (the files are empty): 14 and 15 are too old for Dr.Jit, 19.1 beats 17 and 16."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    for folder, name in [
        (a, "libLLVM-14.so.1"),
        (a, "libLLVM-15.so.1"),
        (a, "libLLVM-17.so.1"),
        (b, "libLLVM.so.19.1"),
        (b, "libLLVM.so.16"),
    ]:
        (folder / name).touch()
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setenv("TANGO_LIBLLVM_DIRS", os.pathsep.join([str(a), str(b)]))
    lib = mref.locate_libllvm()
    assert lib == mref.LibLLVM(str(b / "libLLVM.so.19.1"), "19.1", "the system")
    assert lib.describe() == f"libLLVM 19.1 from the system ({b / 'libLLVM.so.19.1'})"
    monkeypatch.setenv("TANGO_LIBLLVM_DIRS", str(a / "libLLVM-15.so.1").rsplit("/", 1)[0])
    (a / "libLLVM-17.so.1").unlink()
    assert mref.system_libllvm() is None  # only 14 and 15 left


def test_the_users_path_always_wins(tmp_path, monkeypatch):
    """``DRJIT_LIBLLVM_PATH`` naming a file is used whatever else there is; naming none, no libLLVM
    (the user's setting is never replaced by another library): ``auto`` takes scalar_rgb and an
    explicit LLVM variant is refused with what to install."""
    given = tmp_path / "libLLVM.so.21.1"
    given.touch()
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(given))
    assert mref.locate_libllvm() == mref.LibLLVM(str(given), "21.1", "DRJIT_LIBLLVM_PATH")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "absent.so"))
    assert mref.locate_libllvm() is None and mref.choose_variant("auto") == "scalar_rgb"
    with pytest.raises(ImportError, match="pip install karellen-llvm-core"):
        mref.choose_variant("llvm_ad_rgb")


def test_without_system_library_or_wheel_mitsuba_runs_scalar(monkeypatch):
    """The fallback: no system folder holds one and the wheel is absent."""
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setenv("TANGO_LIBLLVM_DIRS", "")
    monkeypatch.setattr(mref, "wheel_libllvm", lambda: None)
    assert mref.locate_libllvm() is None and mref.choose_variant("auto") == "scalar_rgb"


def test_a_wheel_library_that_does_not_load_falls_back_to_scalar(tmp_path, monkeypatch, caplog):
    """A machine the wheel's library does not load on (here a file that is no library): logged with
    the loader's reason, and ``auto`` takes scalar_rgb."""
    broken = tmp_path / "lib" / "libLLVM.so.23.1"
    broken.parent.mkdir()
    broken.write_bytes(b"not an ELF file")
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setenv("TANGO_LIBLLVM_DIRS", "")
    monkeypatch.setattr(mref, "wheel_libllvm", lambda: mref.LibLLVM(str(broken), "23.1", "the karellen-llvm-core wheel"))
    with caplog.at_level("WARNING"):
        assert mref.locate_libllvm() is None and mref.choose_variant("auto") == "scalar_rgb"
    assert "does not load on this machine" in caplog.text and "scalar_rgb" in caplog.text


def test_the_wheel_is_found_from_its_installed_files():
    lib = wheel()
    assert Path(lib.path).is_file() and Path(lib.path).name.startswith("libLLVM.so.") and lib.version.split(".")[0] >= "16"
    assert lib.origin == "the karellen-llvm-core wheel"


def test_without_system_library_mitsuba_renders_llvm_on_the_wheel():
    """System folders hidden, no ``DRJIT_LIBLLVM_PATH``: ``auto`` picks llvm_ad_rgb, a target probe
    renders (the doctor's probe: the target stage's scene), and the process has the wheel's libLLVM
    mapped and no other. (That the LLVM and scalar variants render the same targets is
    tests/reference/test_mitsuba_targets.py's.)"""
    lib = wheel()
    code = (
        "import json\n"
        "from stages.reference import mitsuba as m\n"
        "from stages.reference.targets import probe as probe_targets\n"
        "from stages.config.sections import TargetSettings\n"
        "variant = m.choose_variant('auto')\n"
        "r = probe_targets(TargetSettings())\n"
        "maps = sorted({l.split()[-1] for l in open('/proc/self/maps') if 'libLLVM' in l})\n"
        "env = __import__('os').environ.get('DRJIT_LIBLLVM_PATH')\n"
        "print(json.dumps({'variant': variant, 'probe': r.variant, 'maps': maps, 'env': env}))\n"
    )
    proc = python(code, clean_env(TANGO_LIBLLVM_DIRS=""))
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["variant"] == got["probe"] == "llvm_ad_rgb", got
    assert got["maps"] == [str(Path(lib.path).resolve())] and got["env"] == lib.path, got


def test_the_wheels_runtime_is_loaded_even_without_its_links(tmp_path):
    """The wheel ships ``libc++.so.1.0`` and makes the ``libc++.so.1`` link libLLVM needs when Python
    first starts; without that link (a copy of the wheel's files without links) libLLVM alone does
    not load, and :func:`load_wheel_runtime` loads it (mutation: the runtime not preloaded)."""
    lib = wheel()
    src = Path(lib.path).parent
    (tmp_path / "lib" / "x86_64-unknown-linux-gnu").mkdir(parents=True)
    shutil.copy2(lib.path, tmp_path / "lib" / Path(lib.path).name)
    for f in (src / "x86_64-unknown-linux-gnu").glob("*.so.1.0"):
        shutil.copy2(f, tmp_path / "lib" / "x86_64-unknown-linux-gnu" / f.name)
    copy = tmp_path / "lib" / Path(lib.path).name
    bare = python(f"import ctypes; ctypes.CDLL({str(copy)!r})", clean_env())
    assert bare.returncode != 0 and "libc++.so.1" in bare.stderr, bare.stderr[-1000:]
    code = (
        "from stages.reference import mitsuba as m\n"
        f"m.load_wheel_runtime(m.LibLLVM({str(copy)!r}, {lib.version!r}, 'copy'))\n"
        "print('loaded')\n"
    )
    proc = python(code, clean_env())
    assert proc.returncode == 0 and "loaded" in proc.stdout, proc.stderr[-2000:]
