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

import glob
import os
from pathlib import Path

import numpy as np

#: our camera-to-world times this is Mitsuba's sensor-to-world (x and z axes negated)
OPENGL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])
#: the variant used when none is given: CPU, no LLVM needed
DEFAULT_VARIANT = "scalar_rgb"
#: Dr.Jit's LLVM back end needs LLVM 16 or newer (older ones abort on ``fminimum``); newest first
LLVM_MAJORS = (20, 19, 18, 17, 16)
LIBRARY_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib", "/usr/local/lib")


def find_libllvm() -> str | None:
    """A libLLVM that Dr.Jit's vectorised CPU back end can use: ``DRJIT_LIBLLVM_PATH`` when set and
    present, else the newest ``libLLVM`` 16+ in the usual library folders (Debian: ``apt-get
    install libllvm19``), else None."""
    given = os.environ.get("DRJIT_LIBLLVM_PATH")
    if given:
        return given if Path(given).is_file() else None
    for major in LLVM_MAJORS:
        for folder in LIBRARY_DIRS:
            for pattern in (f"libLLVM.so.{major}*", f"libLLVM-{major}.so*"):
                found = sorted(glob.glob(os.path.join(folder, pattern)))
                if found:
                    return found[0]
    return None


def choose_variant(requested: str = "auto") -> str:
    """``auto``: ``llvm_ad_rgb`` (vectorised, several times faster) when :func:`find_libllvm`
    finds a usable libLLVM, else ``scalar_rgb``. An explicit LLVM variant without one fails with
    what to install."""
    if requested == "auto":
        return "llvm_ad_rgb" if find_libllvm() else "scalar_rgb"
    if requested.startswith("llvm") and not find_libllvm():
        raise ImportError(
            f"Mitsuba variant {requested} needs libLLVM 16 or newer (Debian: apt-get install libllvm19, "
            "or set DRJIT_LIBLLVM_PATH); use variant scalar_rgb or auto instead"
        )
    return requested


def import_mitsuba(variant: str = DEFAULT_VARIANT):
    """``import mitsuba`` with ``variant`` set, or an ImportError that says what to install. For
    an LLVM variant, ``DRJIT_LIBLLVM_PATH`` is pointed at :func:`find_libllvm`'s library first."""
    if variant.startswith("llvm"):
        lib = find_libllvm()
        if lib is None:
            choose_variant(variant)  # raises with the remedy
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", lib)
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise ImportError(
            "the Mitsuba 3 reference renderer is not installed: pip install -e '.[reference]' "
            "(scripts/setup.sh installs it with the test set-up)"
        ) from exc
    if mi.variant() != variant:
        mi.set_variant(variant)
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
