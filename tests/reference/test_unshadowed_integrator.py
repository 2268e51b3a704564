"""The unshadowed direct-light integrator of the ceilings (stages/reference/limits.py) in both
Mitsuba variants a machine may run: the vectorised LLVM one and the scalar fallback (no libLLVM
16+), where a ray that missed the scene crashed the process (a miss has no BSDF)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require_tool

from stages.reference import mitsuba as mref

ALBEDO = 0.5
#: radiance of the constant environment
RADIANCE = 1.0


def scene_of_two_spheres(mi):
    """A diffuse sphere with a second one touching it, under a constant environment, seen so that
    half the image is background: unshadowed, every hit reflects albedo x radiance exactly (the
    cosine-weighted hemisphere integrates to one), though the second sphere blocks much of the
    first one's sky near where they touch."""
    bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [ALBEDO] * 3}}
    # a box filter keeps each sample in its pixel; alpha is the pixel's covered share
    film = {"type": "hdrfilm", "width": 24, "height": 24, "pixel_format": "rgba", "rfilter": {"type": "box"}}
    look = mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0.5, 0, 0], up=[0, 1, 0])
    return mi.load_dict(
        {
            "type": "scene",
            "a": {"type": "sphere", "center": [0, 0, 0], "radius": 1.0, "bsdf": bsdf},
            "b": {"type": "sphere", "center": [2, 0, 0], "radius": 1.0, "bsdf": bsdf},
            "light": {"type": "constant", "radiance": {"type": "rgb", "value": [RADIANCE] * 3}},
            "sensor": {"type": "perspective", "fov": 60, "to_world": look, "film": film},
        }
    )


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "scalar_rgb"])
def test_unshadowed_direct_light_is_albedo_times_radiance_at_every_hit(variant):
    from stages.reference.limits import unshadowed_integrator

    try:
        mref.import_mitsuba("scalar_rgb")
    except ImportError:
        require_tool(False, "Mitsuba 3 is not installed (pip install -e '.[reference]')")
    if variant.startswith("llvm"):
        require_tool(mref.find_libllvm() is not None, "no libLLVM 16+ found (Debian: apt-get install libllvm19)")
    mi = mref.import_mitsuba(variant)
    scene = scene_of_two_spheres(mi)
    rgba = np.array(mi.render(scene, integrator=unshadowed_integrator(mi), spp=64, seed=1), dtype=np.float64)
    image, alpha = rgba[..., :3], rgba[..., 3]
    hits, misses = alpha == 1, alpha == 0
    assert hits.mean() > 0.1 and misses.mean() > 0.1  # hits and misses both present
    assert np.isfinite(rgba).all() and (image[misses] == 0).all()
    np.testing.assert_allclose(image[hits].mean(), ALBEDO * RADIANCE, rtol=0.01)
    assert np.abs(image[hits] - ALBEDO * RADIANCE).max() < 0.12  # no pixel darkened by the blocked sky
    direct = mi.load_dict({"type": "direct", "hide_emitters": True})
    shadowed = np.array(mi.render(scene, integrator=direct, spp=64, seed=1), dtype=np.float64)[..., :3]
    assert shadowed[hits].mean() < 0.97 * image[hits].mean()  # the direct integrator does darken them
