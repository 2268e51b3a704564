"""High-dynamic-range images: Radiance RGBE (.hdr, read and write, no dependency) and OpenEXR
(.exr, through the OpenEXR package). Arrays are ``(H, W, 3) float32``, linear radiance, row 0 at
the top."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.provenance import atomic_path
from ..core.safefiles import read_bytes, require_plain_file, user_file


def _to_rgbe(rgb: np.ndarray) -> np.ndarray:
    rgb = np.maximum(np.asarray(rgb, np.float32), 0.0)
    m = rgb.max(axis=-1)
    mant, exp = np.frexp(m)
    scale = np.where(m > 1e-32, mant * 256.0 / np.where(m > 0, m, 1.0), 0.0)
    out = np.zeros(rgb.shape[:-1] + (4,), np.uint8)
    out[..., :3] = np.clip(rgb * scale[..., None], 0, 255).astype(np.uint8)
    out[..., 3] = np.where(m > 1e-32, exp + 128, 0).astype(np.uint8)
    return out


def write_hdr(path: str | Path, rgb: np.ndarray) -> None:
    """Write ``rgb (H, W, 3)`` as a flat (uncompressed) Radiance RGBE file, atomically."""
    h, w, _ = rgb.shape
    header = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n".encode("ascii")
    with atomic_path(path) as tmp:
        tmp.write_bytes(header + _to_rgbe(rgb).tobytes())


#: the largest environment map read: 8192 rows of 16384 pixels (the target's environment_height limit)
MAX_ENV_HEIGHT = 8192


#: the largest .hdr file read: the largest map run-length encoded at its worst (a literal run of
#: 128 values costs 129 bytes, and each scanline starts with 4), and its header
MAX_HDR_BYTES = 4 * 2 * MAX_ENV_HEIGHT * MAX_ENV_HEIGHT * 129 // 128 + 4 * MAX_ENV_HEIGHT + (1 << 16)


def _check_size(path: Path, h: int, w: int) -> None:
    """Refuse, from the header alone, a map that is not 2:1 or is too large to hold."""
    if h < 1 or w != 2 * h:
        raise StageInputError(path, f"is {w}x{h}, not a 2:1 equirectangular map", "Give a map twice as wide as it is tall.")
    if h > MAX_ENV_HEIGHT:
        raise StageInputError(
            path,
            f"is {w}x{h}, more than {2 * MAX_ENV_HEIGHT}x{MAX_ENV_HEIGHT}",
            "Downsample it (the renderer fits lobes to far fewer).",
        )


def read_hdr(path: str | Path) -> np.ndarray:
    """Read a Radiance RGBE file (flat or new-style run-length encoded, ``-Y H +X W``): every
    malformed file (signature, header, size, truncated or corrupt pixel data) is one
    :class:`StageInputError` naming it, and the size is checked before anything is allocated."""
    path = Path(path)
    data = read_bytes(user_file(path), MAX_HDR_BYTES, remedy="Give an equirectangular .hdr file.")
    if not data.startswith(b"#?"):
        raise StageInputError(path, "is not a Radiance HDR file (no #? signature)")
    end = data.find(b"\n\n")
    m = re.match(rb"-Y (\d{1,9}) \+X (\d{1,9})\n", data[end + 2 : end + 40])
    if end < 0 or not m:
        raise StageInputError(path, "has an unsupported Radiance HDR header (need '-Y H +X W')")
    h, w = int(m.group(1)), int(m.group(2))
    _check_size(path, h, w)
    buf = np.frombuffer(data, np.uint8, offset=end + 2 + m.end())
    out = np.zeros((h, w, 4), np.uint8)
    try:
        _decode_rgbe(buf, out)
    except (IndexError, ValueError) as exc:
        raise StageInputError(path, f"is truncated or corrupt ({exc})", "Export the map again.") from None
    return out[..., :3] * _RGBE_SCALE[out[..., 3]][..., None]


#: what a mantissa byte is multiplied by for each exponent byte e: 2^(e - 136), 0 where e is 0
#: (exact in float32: a lookup gives the same floats as computing them, in far less time and memory)
_RGBE_SCALE = np.where(np.arange(256) > 0, np.ldexp(1.0, np.arange(256) - 136), 0.0).astype(np.float32)


def _decode_rgbe(buf: np.ndarray, out: np.ndarray) -> None:
    """Radiance's scanlines from ``buf`` into ``out (H, W, 4) uint8``: flat RGBE quadruples, or per
    channel runs (a count above 128: one value repeated count - 128 times; else count literal
    values). Raises ValueError where the data ends early or a run overflows its scanline."""
    h, w = out.shape[:2]
    i = 0
    for y in range(h):
        if (
            8 <= w < 32768
            and i + 4 <= len(buf)
            and buf[i] == 2
            and buf[i + 1] == 2
            and (int(buf[i + 2]) << 8 | int(buf[i + 3])) == w
        ):
            i += 4
            for c in range(4):
                x = 0
                while x < w:
                    if i >= len(buf):
                        raise ValueError(f"the data ends in scanline {y + 1} of {h}")
                    n = int(buf[i])
                    i += 1
                    run = n - 128 if n > 128 else n
                    if run == 0 or x + run > w:
                        raise ValueError(f"a run of {run} overflows scanline {y + 1} of {h} at pixel {x}")
                    if i + (1 if n > 128 else n) > len(buf):
                        raise ValueError(f"the data ends in scanline {y + 1} of {h}")
                    if n > 128:
                        out[y, x : x + run, c] = buf[i]
                        i += 1
                    else:
                        out[y, x : x + n, c] = buf[i : i + n]
                        i += n
                    x += run
        else:
            if i + 4 * w > len(buf):
                raise ValueError(f"the data ends in scanline {y + 1} of {h}")
            out[y] = buf[i : i + 4 * w].reshape(w, 4)
            i += 4 * w


def write_exr(path: str | Path, rgb: np.ndarray) -> None:
    """Write ``rgb (H, W, 3)`` as a ZIP-compressed float32 OpenEXR file, atomically."""
    try:
        import OpenEXR
    except ImportError as exc:  # pragma: no cover
        raise ImportError("writing EXR needs the OpenEXR package: pip install OpenEXR") from exc
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(rgb, np.float32)}) as f:
            f.write(str(tmp))


#: the most channels an OpenEXR map may have: R, G, B and a few more (alpha, depth, ...). Its
#: pixels are read channel by channel, each at the map's full size: 67 float channels of 4096x2048
#: would be 2.2 GB from a file of a few megabytes
MAX_EXR_CHANNELS = 16


def _check_exr_header(path: Path, f) -> None:
    """Refuse, from the header of ``f`` (an ``OpenEXR.File`` opened ``header_only``), every file
    whose pixels would take more memory than its map: more than one part (every part is read),
    deep data (its sample counts are in the pixel data), a size :func:`_check_size` refuses, more
    than :data:`MAX_EXR_CHANNELS` channels, or tiles larger than the largest map (the library's
    buffers grow with the tile size, not the image's); then one without R, G and B."""
    import OpenEXR

    if len(f.parts) != 1:
        raise StageInputError(path, f"has {len(f.parts)} parts, not one", "Save the map as a single-part image.")
    header = f.header()
    if header.get("type") in (OpenEXR.deepscanline, OpenEXR.deeptile):
        raise StageInputError(path, "holds deep data, not a flat image", "Save the map as a flat (non-deep) image.")
    lo, hi = (np.asarray(v, np.int64) for v in header["dataWindow"])
    _check_size(path, int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))
    names = [c.name for c in header["channels"]]
    if len(names) > MAX_EXR_CHANNELS:
        raise StageInputError(
            path, f"has {len(names)} channels, more than {MAX_EXR_CHANNELS}", "Save only its R, G and B channels."
        )
    tiles = header.get("tiles")
    if tiles is not None and (tiles.xSize > 2 * MAX_ENV_HEIGHT or tiles.ySize > MAX_ENV_HEIGHT):
        raise StageInputError(
            path,
            f"has {tiles.xSize}x{tiles.ySize} tiles, larger than the largest map ({2 * MAX_ENV_HEIGHT}x{MAX_ENV_HEIGHT})",
            "Save it as a scanline image or with smaller tiles.",
        )
    if not {"R", "G", "B"} <= set(names):
        raise StageInputError(path, f"has no R, G and B channels (it has {', '.join(sorted(names)) or 'none'})")


def read_exr(path: str | Path) -> np.ndarray:
    """An OpenEXR file's RGB as ``(H, W, 3) float32``. The header is checked before any pixel is
    read (:func:`_check_exr_header`: one flat part, the size, at most :data:`MAX_EXR_CHANNELS`
    channels, the tile size, R, G and B); a header that fails, a file OpenEXR cannot read, or one
    whose R, G and B cannot be read as one image is one :class:`StageInputError`."""
    import OpenEXR

    path = Path(path)
    opened = str(require_plain_file(user_file(path), remedy="Give an equirectangular .exr file."))
    try:
        with OpenEXR.File(opened, header_only=True) as f:
            _check_exr_header(path, f)
        with OpenEXR.File(opened) as f:
            ch = f.channels()
            if "RGB" in ch:
                return np.asarray(ch["RGB"].pixels, np.float32)
            if not all(c in ch for c in "RGB"):
                raise StageInputError(path, f"has no R, G and B channels (it has {', '.join(sorted(ch)) or 'none'})")
            return np.stack([np.asarray(ch[c].pixels, np.float32) for c in "RGB"], axis=-1)
    except (RuntimeError, KeyError, ValueError, TypeError) as exc:
        raise StageInputError(
            path, f"is not a readable OpenEXR image ({str(exc).splitlines()[0][:120]})", "Export it again."
        ) from None


def read_envmap(path: str | Path) -> np.ndarray:
    """An equirectangular environment map from ``.hdr`` or ``.exr``: ``(H, W, 3) float32``; the
    format is the name's as given (a link to a file of another name, as content-addressed caches
    keep them, reads as the name says)."""
    path = Path(path)
    if not path.exists():
        raise StageInputError(path, "file not found", "Give an equirectangular .hdr or .exr file.")
    if path.suffix.lower() == ".hdr":
        img = read_hdr(path)
    elif path.suffix.lower() == ".exr":
        img = read_exr(path)
    else:
        raise StageInputError(path, f"unsupported environment map format {path.suffix!r}", "Use .hdr or .exr.")
    if img.ndim != 3 or img.shape[1] != 2 * img.shape[0]:
        raise StageInputError(path, f"is {img.shape[1]}x{img.shape[0]}, not a 2:1 equirectangular map")
    if not np.isfinite(img).all():
        raise StageInputError(path, "contains NaN or infinite pixels")
    return img
