"""Mitsuba 3 with our cameras: a pinhole sensor that is exactly the ray cache's camera.

Our cameras (:mod:`stages.geometry.cameras`) follow OpenGL: the camera looks along its -z axis,
+x right, +y up, row 0 at the top, rays through pixel centres, ``fov`` the full (square) field of
view. Mitsuba's perspective sensor looks along its local +z with +x to the *left* (its ``look_at``
builds ``[left, up, forward]``), so its ``to_world`` is our camera-to-world with x and z negated.
One non-jittered stratified sample per pixel sits at the pixel centre and a box filter of radius
half a pixel keeps it in its own pixel, so each pixel holds the ray through its centre, as in the
cache. ``tests/reference/test_mitsuba_cameras.py`` compares silhouettes and hit points.

Mitsuba's ``depth`` AOV measures from the near-clip plane (rays start at ``near_clip`` along the
optical axis), so distances are taken from the ``position`` AOV instead.
"""

from __future__ import annotations

import ctypes
import glob
import importlib.metadata
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.threads import cpu_threads

#: our camera-to-world times this is Mitsuba's sensor-to-world (x and z axes negated)
OPENGL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])
#: the variant used when none is given: CPU, no LLVM needed
DEFAULT_VARIANT = "scalar_rgb"
#: Dr.Jit's LLVM back end needs LLVM 16 or newer (older ones abort on ``fminimum``)
LLVM_MIN_MAJOR = 16
LIBRARY_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib", "/usr/local/lib")
#: the Python wheel that ships a libLLVM and its libc++ (the ``reference`` extra installs it)
LLVM_WHEEL = "karellen-llvm-core"
#: the wheel's C++ runtime, in the order its libraries need each other (libLLVM needs libc++.so.1)
WHEEL_RUNTIME = ("libunwind.so.1", "libc++abi.so.1", "libc++.so.1")

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LibLLVM:
    """A libLLVM for Dr.Jit's vectorised CPU back end: its ``path``, LLVM ``version`` (major.minor,
    from the file name; "" when the name does not say) and ``origin``: ``DRJIT_LIBLLVM_PATH`` (the
    user's choice, which always wins), ``the system`` or ``the karellen-llvm-core wheel``."""

    path: str
    version: str
    origin: str

    def describe(self) -> str:
        version = f"libLLVM {self.version}" if self.version else "libLLVM"
        return f"{version} from {self.origin} ({self.path})"


def _llvm_version(name: str) -> tuple[int, str] | None:
    """``libLLVM.so.19.1`` or ``libLLVM-19.so.1`` -> (19, "19.1"); None for other names."""
    m = re.fullmatch(r"libLLVM\.so\.(\d+)(?:\.(\d+))?.*", name) or re.fullmatch(r"libLLVM-(\d+)(?:\.(\d+))?\.so.*", name)
    if m is None:
        return None
    return int(m.group(1)), m.group(1) + (f".{m.group(2)}" if m.group(2) else "")


def library_dirs() -> tuple[str, ...]:
    """The folders searched for a system libLLVM: ``TANGO_LIBLLVM_DIRS`` (folders separated by
    ``os.pathsep``; set but empty: none, so only the wheel's is used) when set, else
    :data:`LIBRARY_DIRS`."""
    given = os.environ.get("TANGO_LIBLLVM_DIRS")
    if given is None:
        return LIBRARY_DIRS
    return tuple(f for f in given.split(os.pathsep) if f)


def system_libllvm(folders=None) -> LibLLVM | None:
    """The newest system ``libLLVM`` of major version 16 or newer in ``folders`` (default
    :func:`library_dirs`; Debian: ``apt-get install libllvm19``), or None."""
    found = []
    for folder in library_dirs() if folders is None else folders:
        for path in glob.glob(os.path.join(folder, "libLLVM*.so*")):
            version = _llvm_version(os.path.basename(path))
            if version is not None and version[0] >= LLVM_MIN_MAJOR:
                found.append((version[0], version[1], path))
    if not found:
        return None
    major, version, path = max(found, key=lambda f: (f[0], f[1], -len(f[2]), f[2]))
    return LibLLVM(path, version, "the system")


def wheel_libllvm() -> LibLLVM | None:
    """The libLLVM of the ``karellen-llvm-core`` wheel when it is installed in this environment,
    or None."""
    try:
        dist = importlib.metadata.distribution(LLVM_WHEEL)
    except importlib.metadata.PackageNotFoundError:
        return None
    for file in dist.files or ():
        version = _llvm_version(Path(file).name)
        if version is not None and Path(file).name.startswith("libLLVM.so"):
            path = Path(dist.locate_file(file)).resolve()
            if path.is_file():
                return LibLLVM(str(path), version[1], f"the {LLVM_WHEEL} wheel")
    return None


def load_wheel_runtime(lib: LibLLVM) -> None:
    """Load the wheel's libc++ (and what it needs) into the process before its libLLVM, so that the
    libLLVM finds it whether or not the wheel's ``libc++.so.1`` links were made at install time
    (the wheel names the files ``libc++.so.1.0``; a loaded library answers to its soname). Raises
    OSError when one does not load on this machine."""
    folder = Path(lib.path).parent
    for name in WHEEL_RUNTIME:
        matches = sorted(folder.glob(f"*/{name}*")) + sorted(folder.glob(f"{name}*"))
        if matches:
            ctypes.CDLL(str(matches[0]), mode=ctypes.RTLD_GLOBAL)
    ctypes.CDLL(lib.path, mode=ctypes.RTLD_GLOBAL)


def locate_libllvm() -> LibLLVM | None:
    """The libLLVM Mitsuba's LLVM variants will use: ``DRJIT_LIBLLVM_PATH`` when set (None when it
    names no file: the user's setting is never overridden), else the newest system libLLVM 16+,
    else the ``karellen-llvm-core`` wheel's when it loads here (its C++ runtime loaded first:
    :func:`load_wheel_runtime`; one that does not load is logged and skipped), else None."""
    given = os.environ.get("DRJIT_LIBLLVM_PATH")
    if given and given == _POINTED_AT.get("path"):
        return _POINTED_AT["lib"]  # set by import_mitsuba from this search, not by the user
    if given:
        version = _llvm_version(Path(given).name)
        return LibLLVM(given, version[1] if version else "", "DRJIT_LIBLLVM_PATH") if Path(given).is_file() else None
    lib = system_libllvm()
    if lib is not None:
        return lib
    lib = wheel_libllvm()
    if lib is None:
        return None
    try:
        load_wheel_runtime(lib)
    except OSError as exc:
        log.warning("the %s wheel's libLLVM does not load on this machine (%s); Mitsuba runs scalar_rgb", LLVM_WHEEL, exc)
        return None
    return lib


#: the library import_mitsuba pointed DRJIT_LIBLLVM_PATH at (``path``, ``lib``), so that a later
#: search in this process still says where it came from
_POINTED_AT: dict = {}


def find_libllvm() -> str | None:
    """The path of :func:`locate_libllvm`'s library, or None."""
    lib = locate_libllvm()
    return lib.path if lib is not None else None


def choose_variant(requested: str = "auto") -> str:
    """``auto``: ``llvm_ad_rgb`` (vectorised, several times faster) when :func:`find_libllvm`
    finds a usable libLLVM, else ``scalar_rgb``. An explicit LLVM variant without one fails with
    what to install."""
    if requested == "auto":
        return "llvm_ad_rgb" if find_libllvm() else "scalar_rgb"
    if requested.startswith("llvm") and not find_libllvm():
        raise ImportError(
            f"Mitsuba variant {requested} needs libLLVM 16 or newer (pip install {LLVM_WHEEL}, which the "
            "reference extra installs; or Debian: apt-get install libllvm19; or set DRJIT_LIBLLVM_PATH); "
            "use variant scalar_rgb or auto instead"
        )
    return requested


def import_mitsuba(variant: str = DEFAULT_VARIANT):
    """``import mitsuba`` with ``variant`` set, or an ImportError that says what to install. For
    an LLVM variant, ``DRJIT_LIBLLVM_PATH`` is pointed at :func:`find_libllvm`'s library first."""
    if variant.startswith("llvm"):
        lib = locate_libllvm()
        if lib is None:
            choose_variant(variant)  # raises with the remedy
        if "DRJIT_LIBLLVM_PATH" not in os.environ:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib.path
            _POINTED_AT.update(path=lib.path, lib=lib)
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise ImportError(
            "the Mitsuba 3 reference renderer is not installed: pip install -e '.[reference]' "
            "(scripts/setup.sh installs it with the test set-up)"
        ) from exc
    if mi.variant() != variant:
        mi.set_variant(variant)
    import drjit

    drjit.set_thread_count(cpu_threads())  # the job's --threads (a rule's threads), else every CPU
    return mi


def sensor(
    c2w: np.ndarray, fov_deg: float, width: int, spp: int = 1, *, centred: bool = True, alpha: bool = False, mi=None
) -> dict:
    """A Mitsuba perspective sensor for our camera ``c2w (4, 4)``: ``width x width`` pixels, full
    field of view ``fov_deg``. ``centred``: one sample per pixel at its centre (``spp`` must be
    1); otherwise ``spp`` uniformly random samples per pixel, each kept in its own pixel by the
    box filter, so a pixel holds the mean radiance over its footprint (for rendering).
    ``alpha``: an RGBA film (alpha = the footprint's covered fraction). ``mi``: the imported
    module (default: :func:`import_mitsuba` with the default variant)."""
    mi = mi or import_mitsuba()
    if centred and spp != 1:
        raise ValueError("a centred sensor takes one sample per pixel")
    sampler = (
        {"type": "stratified", "sample_count": 1, "jitter": False} if centred else {"type": "independent", "sample_count": spp}
    )
    return {
        "type": "perspective",
        "fov": float(fov_deg),
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f((np.asarray(c2w, np.float64) @ OPENGL_TO_MITSUBA).tolist()),
        "film": {
            "type": "hdrfilm",
            "width": int(width),
            "height": int(width),
            "rfilter": {"type": "box"},
            "pixel_format": "rgba" if alpha else "rgb",
        },
        "sampler": sampler,
    }


def hit_positions(mesh_ply: str | Path, c2w: np.ndarray, fov_deg: float, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's first hits of the rays through every pixel centre of our camera: ``mask (W, W)
    bool`` (the silhouette) and ``position (W, W, 3)`` float32 (world space; zero where missed)."""
    mi = import_mitsuba()
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "aov", "aovs": "p:position,n:geo_normal"},
            "sensor": sensor(c2w, fov_deg, width),
            "mesh": {"type": "ply", "filename": str(mesh_ply), "face_normals": True},
        }
    )
    img = np.array(mi.render(scene), dtype=np.float32)
    # the geometric normal is a unit vector on a hit and zero on a miss
    mask = np.linalg.norm(img[..., 3:6], axis=-1) > 0.5
    return mask, np.where(mask[..., None], img[..., :3], 0.0)
