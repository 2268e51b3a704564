"""The shipped environment file and the procedural maps it comes from."""

import math

import numpy as np
import pytest
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


# ---- run-length encoded maps of every width, against an encoder written here from the format ----
def _rle_scanlines(rgbe: np.ndarray) -> list[bytes]:
    """Radiance's new-style run-length encoding of the scanlines ``rgbe (N, W, 4) uint8``, one
    bytes object per scanline: the 4 bytes 2, 2, W >> 8, W & 255, then each channel's W bytes in
    turn as packets: a count n above 128 followed by one byte repeated n - 128 times, or a count n
    from 1 to 128 followed by n literal bytes. Runs of 4 or more equal bytes are repeated packets
    (at most 127 each), the bytes between them literal packets (at most 128 each)."""
    rows, w, _ = rgbe.shape
    v = np.ascontiguousarray(rgbe.transpose(0, 2, 1)).reshape(-1)  # (N, 4, W): one line per channel
    new_run = np.r_[True, v[1:] != v[:-1]]
    new_run[::w] = True  # no run goes on from one channel's line to the next
    run_start = np.flatnonzero(new_run)
    run_len = np.diff(np.r_[run_start, v.size])
    # stretches: each long run alone, the short runs between them together
    rep = run_len >= 4
    first = np.flatnonzero(rep | np.r_[True, rep[:-1]] | (run_start % w == 0))
    st_start, st_len, st_rep = run_start[first], np.add.reduceat(run_len, first), rep[first]
    # packets: each stretch cut into pieces of at most 127 (repeated) or 128 (literal) bytes
    cap = np.where(st_rep, 127, 128)
    pieces = -(-st_len // cap)
    st = np.repeat(np.arange(first.size), pieces)
    nth = np.arange(st.size) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    pk_start = st_start[st] + nth * cap[st]
    pk_len = np.minimum(cap[st], st_len[st] - nth * cap[st])
    pk_rep = st_rep[st]
    size = np.where(pk_rep, 2, 1 + pk_len)
    at = np.cumsum(size) - size
    out = np.empty(int(size.sum()), np.uint8)
    out[at] = np.where(pk_rep, 128 + pk_len, pk_len)
    out[at[pk_rep] + 1] = v[pk_start[pk_rep]]
    lit_start, lit_len, lit_at = pk_start[~pk_rep], pk_len[~pk_rep], at[~pk_rep] + 1
    k = np.arange(int(lit_len.sum())) - np.repeat(np.cumsum(lit_len) - lit_len, lit_len)
    out[np.repeat(lit_at, lit_len) + k] = v[np.repeat(lit_start, lit_len) + k]
    # each scanline's bytes run from its first packet to the next scanline's
    ends = np.r_[at, out.size][np.searchsorted(pk_start, np.arange(rows + 1) * 4 * w)]
    mark = bytes([2, 2, w >> 8, w & 255])
    return [mark + out[a:b].tobytes() for a, b in zip(ends[:-1], ends[1:], strict=True)]


def _hdr_file(rgbe: np.ndarray, flat: np.ndarray) -> bytes:
    """A Radiance file of ``rgbe (H, W, 4) uint8``: the scanlines where ``flat (H,)`` is set as
    plain RGBE quadruples, the others run-length encoded (256 scanlines at a time)."""
    h, w, _ = rgbe.shape
    parts = [HEADER, f"-Y {h} +X {w}\n".encode()]
    for y0 in range(0, h, 256):
        rle = _rle_scanlines(rgbe[y0 : y0 + 256])
        parts += [rgbe[y].tobytes() if flat[y] else rle[y - y0] for y in range(y0, min(h, y0 + 256))]
    return b"".join(parts)


def _rgbe_map(h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A map to encode, ``(h, w, 4) uint8``, and which of its scanlines to write flat (every fourth,
    its first byte 1 so that it cannot pass for a run-length encoded one). Along each channel's
    scanline: stretches of one value (1 to min(w, 2000) pixels, so runs longer than the 127 of a
    packet), and between them, noisy stretches (1 to 300 pixels of random bytes, one pixel in 8)."""
    rng = np.random.default_rng(seed)
    n = h * 4 * w
    lengths = rng.integers(1, min(w, 2000) + 1, 2 * n // min(w, 2000) + 64)
    v = np.repeat(rng.integers(0, 256, lengths.size, dtype=np.uint8), lengths)
    gaps = np.zeros(2 * (n // 1000) + 64, np.int64)
    gaps[0::2], gaps[1::2] = rng.integers(1, 2001, gaps.size // 2), rng.integers(1, 301, gaps.size // 2)
    noisy = np.repeat(np.arange(gaps.size) % 2 == 1, gaps)
    assert v.size >= n and noisy.size >= n
    v, noisy = v[:n], noisy[:n]
    v[noisy] = rng.integers(0, 256, int(noisy.sum()), dtype=np.uint8)
    rgbe = np.ascontiguousarray(v.reshape(h, 4, w).transpose(0, 2, 1))
    flat = np.arange(h) % 4 == 3
    rgbe[flat, 0, 0] = 1
    return rgbe, flat


def test_the_reference_rle_encoder_follows_the_format():
    """The encoder above, on one scanline of 8 pixels and one of 300, against bytes written out by
    hand: repeated packets (count - 128, value), literal ones (count, values), 127 and 128 at most."""
    line = np.array([[5, 5, 5, 5, 5, 7, 8, 9], [0] * 8, [1, 2, 3, 4, 5, 6, 7, 8], [9, 9, 9, 1, 9, 9, 9, 9]], np.uint8).T[None]
    assert _rle_scanlines(line) == [
        bytes([2, 2, 0, 8])
        + bytes([128 + 5, 5, 3, 7, 8, 9])
        + bytes([128 + 8, 0])
        + bytes([8, 1, 2, 3, 4, 5, 6, 7, 8])
        + bytes([4, 9, 9, 9, 1, 128 + 4, 9])
    ]
    noise = np.arange(130, dtype=np.uint8) * 2 + 1  # no two neighbours equal
    long = np.zeros((1, 300, 4), np.uint8)
    long[0, :130, 1] = noise
    long[0, :, 2] = 7
    assert _rle_scanlines(long) == [
        bytes([2, 2, 1, 44])
        + bytes([255, 0, 255, 0, 128 + 46, 0])
        + bytes([128])
        + noise[:128].tobytes()
        + bytes([2])
        + noise[128:].tobytes()
        + bytes([255, 0, 128 + 43, 0])
        + bytes([255, 7, 255, 7, 128 + 46, 7])
        + bytes([255, 0, 255, 0, 128 + 46, 0])
    ]


@pytest.mark.parametrize("w", [256, 1024, pytest.param(8192, marks=pytest.mark.slow(minutes=0.1))])
def test_an_rle_hdr_reads_exactly_at_any_width(tmp_path, w):
    """A ``(w/2, w)`` map, three in four of its scanlines run-length encoded (widths of 256 and more
    take the high byte of the scanline's width mark), reads as exactly the floats the RGBE bytes
    stand for: mantissa x 2^(exponent - 136), 0 where the exponent byte is 0."""
    from stages.render.hdrio import read_envmap

    h = w // 2
    rgbe, flat = _rgbe_map(h, w)
    path = tmp_path / f"rle{w}.hdr"
    path.write_bytes(_hdr_file(rgbe, flat))
    img = read_envmap(path)
    assert img.shape == (h, w, 3) and img.dtype == np.float32
    for y0 in range(0, h, 256):
        e = rgbe[y0 : y0 + 256, :, 3:].astype(np.int64)
        want = (rgbe[y0 : y0 + 256, :, :3] * np.where(e > 0, 2.0 ** (e - 136), 0.0)).astype(np.float32)
        assert np.array_equal(img[y0 : y0 + 256], want), f"scanlines {y0} to {y0 + 255} differ"


# ---- EXR headers that would size a far larger allocation than the map ---------------------------
def _write_exr(path, channels: dict, **header) -> None:
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **header}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def _pixels_unread(monkeypatch) -> None:
    """From here on, opening an EXR file for its pixels (not ``header_only``) fails the test."""
    import OpenEXR

    open_file = OpenEXR.File

    def header_only(*args, **kwargs):
        assert kwargs.get("header_only"), "the pixels were read"
        return open_file(*args, **kwargs)

    monkeypatch.setattr(OpenEXR, "File", header_only)


def test_an_exr_with_too_many_channels_is_refused_from_its_header(tmp_path, monkeypatch):
    """A 16x8 map of R, G, B and 64 more channels (67: at 4096x2048 that is 2.2 GB of float pixels
    from a file of 2.2 MB) is refused from its header, before any pixel is read, in one line that
    names the file, its 67 channels and the limit; one of MAX_EXR_CHANNELS channels still reads."""
    from stages.render import hdrio

    rgb = np.arange(8 * 16 * 3, dtype=np.float32).reshape(8, 16, 3)
    extra = {f"extra{i:02d}": np.ones((8, 16), np.float32) for i in range(64)}
    limit = hdrio.MAX_EXR_CHANNELS
    _write_exr(tmp_path / "at_limit.exr", {"RGB": rgb, **dict(list(extra.items())[: limit - 3])})
    assert np.array_equal(hdrio.read_envmap(tmp_path / "at_limit.exr"), rgb)
    _write_exr(tmp_path / "many.exr", {"RGB": rgb, **extra})
    _pixels_unread(monkeypatch)
    _refused(tmp_path, "channels.exr", (tmp_path / "many.exr").read_bytes(), f"has 67 channels, more than {limit}")


def test_an_exr_of_parts_deep_data_or_huge_tiles_is_refused_from_its_header(tmp_path, monkeypatch):
    """Refused from the header, before any pixel is read, in one line naming the file: two parts
    (every part's pixels would be read), deep data (sample counts unknown until the pixels are
    read), tiles larger than the largest map (a 16x8 map with 8M x 8M tiles took 1.5 GB). A map in
    tiles no larger than that still reads."""
    import OpenEXR

    from stages.render import hdrio

    rgb = np.arange(8 * 16 * 3, dtype=np.float32).reshape(8, 16, 3)
    two = [OpenEXR.Part({"type": OpenEXR.scanlineimage}, {"RGB": rgb}, name) for name in ("a", "b")]
    with OpenEXR.File(two) as f:
        f.write(str(tmp_path / "two.exr"))
    deep = np.empty((8, 16), dtype=object)
    for y, x in np.ndindex(deep.shape):
        deep[y, x] = np.ones(2, np.float32)  # two samples per pixel
    _write_exr(tmp_path / "deep.exr", {c: deep for c in "RGB"}, type=OpenEXR.deepscanline, compression=OpenEXR.ZIPS_COMPRESSION)

    def tiled(name, x, y):
        tiles = OpenEXR.TileDescription()
        tiles.xSize, tiles.ySize = x, y
        _write_exr(tmp_path / name, {"RGB": rgb}, type=OpenEXR.tiledimage, tiles=tiles)
        return (tmp_path / name).read_bytes()

    monkeypatch.setattr(hdrio, "MAX_ENV_HEIGHT", 8)  # the largest map: 16x8
    tiled("small_tiles.exr", 16, 8)
    assert np.array_equal(hdrio.read_envmap(tmp_path / "small_tiles.exr"), rgb)
    big_tiles = tiled("big_tiles.exr", 32, 8)
    _pixels_unread(monkeypatch)
    _refused(tmp_path, "parts.exr", (tmp_path / "two.exr").read_bytes(), "has 2 parts, not one")
    _refused(tmp_path, "deep2.exr", (tmp_path / "deep.exr").read_bytes(), "holds deep data, not a flat image")
    _refused(tmp_path, "tiles.exr", big_tiles, "has 32x8 tiles, larger than the largest map (16x8)")


def test_a_map_linked_from_a_content_addressed_store_reads_as_its_name_says(tmp_path):
    """A map whose name is a link to a blob without a suffix (a model hub's cache, DVC,
    git-annex) reads by the name given; the format comes from that name."""
    from stages.render.hdrio import read_envmap, write_hdr

    blobs = tmp_path / "blobs"
    blobs.mkdir()
    rgb = np.full((8, 16, 3), 0.5, np.float32)
    write_hdr(blobs / "map.hdr", rgb)
    (blobs / "map.hdr").rename(blobs / "9f86d081884c7d65")
    (tmp_path / "sky.hdr").symlink_to(blobs / "9f86d081884c7d65")
    assert np.allclose(read_envmap(tmp_path / "sky.hdr"), 0.5, rtol=1 / 128)
