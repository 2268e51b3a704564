"""The shipped environment file and the procedural maps it comes from."""

import math

import numpy as np
from conftest import REPO

from stages.render.envmap import load_env, procedural_envmap, radiant_energy, solid_angles


def test_shipped_studio_hdr_is_what_its_command_writes():
    """config/envmaps/studio.hdr is the procedural studio at 128 rows, to RGBE's rounding (8 bits
    of mantissa: within 1/128 of each pixel's largest channel)."""
    shipped = load_env(str(REPO / "config" / "envmaps" / "studio.hdr"))
    made = procedural_envmap("studio", 128)
    assert shipped.shape == made.shape == (128, 256, 3)
    assert (np.abs(shipped - made) <= made.max(-1, keepdims=True) / 128 + 1e-6).all()


def test_studio_lights_where_it_says():
    """The key softbox (radiance ~4) covers 44 x 28 degrees high on its side, the strip (~6) is
    narrow and behind; the room is dim: most of the energy comes from the two lights. Their solid
    angles, counted over the map's pixels, match the rectangles' (within the edges' softening)."""
    env = procedural_envmap("studio", 256)
    omega = np.broadcast_to(solid_angles(*env.shape[:2]), env.shape[:2])
    lum = env.mean(-1)
    key = (lum > 3.0) & (lum < 5.0)
    strip = lum > 5.0
    rect = lambda w, h: 4.0 * math.asin(math.sin(math.radians(w)) * math.sin(math.radians(h)))  # noqa: E731
    assert abs(float(omega[key].sum()) / rect(22.0, 14.0) - 1.0) < 0.15
    assert abs(float(omega[strip].sum()) / rect(4.0, 25.0) - 1.0) < 0.25
    lights = float((env.mean(-1) * omega)[lum > 1.0].sum())
    assert lights > 0.6 * float(radiant_energy(env).mean())
