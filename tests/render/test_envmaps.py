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


# ---- malformed maps: one line naming the file, sizes checked before any allocation --------------
HEADER = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n"


def _rle_scanline(w: int, value: int) -> bytes:
    """One new-style run-length scanline of width ``w``: per channel one run of ``value``."""
    return bytes([2, 2, w >> 8, w & 255]) + b"".join(bytes([128 + w, value]) for _ in range(4))


def _refused(tmp_path, name: str, data: bytes, needle: str) -> str:
    import time

    import pytest

    from stages.core.errors import StageInputError
    from stages.render.hdrio import read_envmap

    path = tmp_path / name
    path.write_bytes(data)
    t0 = time.perf_counter()
    with pytest.raises(StageInputError) as err:
        read_envmap(path)
    message = str(err.value)
    assert time.perf_counter() - t0 < 2.0
    assert needle in message and str(path) in message and "\n" not in message, message
    return message


def test_a_malformed_hdr_is_one_line(tmp_path):
    from stages.render.hdrio import read_envmap

    h, w = 8, 16
    good = HEADER + f"-Y {h} +X {w}\n".encode() + b"".join(_rle_scanline(w, 130) for _ in range(h))
    path = tmp_path / "rle.hdr"
    path.write_bytes(good)
    img = read_envmap(path)  # the encoder in this test is right: every pixel 130 x 2^(130-136) ... per channel
    assert img.shape == (h, w, 3) and np.allclose(img, 130 * 2.0 ** (130 - 136))
    _refused(tmp_path, "cut_rle.hdr", good[: len(good) - 5], "is truncated or corrupt (the data ends in scanline 8 of 8)")
    flat = HEADER + f"-Y {h} +X {w}\n".encode() + bytes(4 * w * h - 3)
    _refused(tmp_path, "cut_flat.hdr", flat, "the data ends in scanline 8 of 8")
    overflow = HEADER + f"-Y {h} +X {w}\n".encode() + bytes([2, 2, 0, w, 128 + w + 5, 1]) + bytes(200)
    _refused(tmp_path, "overflow.hdr", overflow, "a run of 21 overflows scanline 1")
    zero_run = HEADER + f"-Y {h} +X {w}\n".encode() + bytes([2, 2, 0, w, 0]) + bytes(200)
    _refused(tmp_path, "zero.hdr", zero_run, "a run of 0 overflows scanline 1")
    # a header of 100,000 x 200,000 (74.5 GiB of pixels) is refused from the header alone
    _refused(tmp_path, "huge.hdr", HEADER + b"-Y 100000 +X 200000\n" + bytes(64), "is 200000x100000, more than 16384x8192")
    _refused(tmp_path, "square.hdr", HEADER + b"-Y 16 +X 16\n" + bytes(64), "is 16x16, not a 2:1 equirectangular map")
    _refused(tmp_path, "digits.hdr", HEADER + b"-Y 99999999999 +X 1\n", "unsupported Radiance HDR header")
    _refused(tmp_path, "text.hdr", b"hello", "is not a Radiance HDR file")


def test_a_malformed_exr_is_one_line(tmp_path, monkeypatch):
    from stages.render import hdrio

    _refused(tmp_path, "junk.exr", b"junk" * 100, "is not a readable OpenEXR image")
    good = tmp_path / "good.exr"
    hdrio.write_exr(good, np.ones((8, 16, 3), np.float32))
    _refused(tmp_path, "cut.exr", good.read_bytes()[:-40], "is not a readable OpenEXR image")
    hdrio.write_exr(tmp_path / "square.exr", np.ones((8, 8, 3), np.float32))
    assert "not a 2:1 equirectangular map" in _refused(tmp_path, "square2.exr", (tmp_path / "square.exr").read_bytes(), "8x8")
    monkeypatch.setattr(hdrio, "MAX_ENV_HEIGHT", 4)  # the size comes from the header, before the pixels
    _refused(tmp_path, "big.exr", good.read_bytes(), "is 16x8, more than 8x4")
