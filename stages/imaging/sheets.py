"""Contact sheets of rendered views, and PNG files written atomically."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..core.provenance import atomic_path


def contact_sheet(images: list[torch.Tensor], columns: int) -> np.ndarray:
    """Tile ``(3, h, w)`` images row-major into one ``(H, W, 3) uint8`` array."""
    rows = math.ceil(len(images) / columns)
    _, h, w = images[0].shape
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, columns)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = (img.clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round()
    return sheet


def save_png(path: str | Path, array: np.ndarray) -> None:
    """Write an ``(H, W, 3) uint8`` image as PNG, atomically."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(array).save(tmp, format="PNG")


#: the labels' line height and margins, in pixels (PIL's built-in bitmap font)
LINE = 14
PAD = 4
#: the grey scale's length in pixels (one per level)
RAMP = 256


def annotate(
    sheet: np.ndarray,
    title: str,
    columns: list[str] | None = None,
    rows: list[str] | None = None,
    scale: tuple[str, str, str] | None = None,
) -> np.ndarray:
    """``sheet (H, W, 3) uint8`` with what it shows written around it: a ``title`` line on top, a
    label over each of its ``columns`` and before each of its ``rows`` (equal tiles), and with
    ``scale = (low, high, what)`` a grey ramp under it from black (``low``) to white (``high``)
    saying what the grey levels mean. White margins, black text; returns a new ``uint8`` array."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default()
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))

    def width(text: str) -> int:
        return int(probe.textlength(text, font=font))

    h, w = sheet.shape[:2]
    left = PAD + max((width(r) for r in rows), default=-PAD) + PAD if rows else 0
    top = PAD + LINE + (LINE if columns else 0)
    bottom = (2 * LINE + 3 * PAD) if scale else PAD
    needed = [left + w, width(title) + 2 * PAD]
    if scale:
        needed += [left + 5 * PAD + width(scale[0]) + RAMP + width(scale[1]), left + 2 * PAD + width(scale[2])]
    canvas = Image.new("RGB", (max(needed), top + h + bottom), "white")
    canvas.paste(Image.fromarray(sheet), (left, top))
    draw = ImageDraw.Draw(canvas)
    draw.text((PAD, PAD // 2), title, fill="black", font=font)
    if columns:
        tile = w / len(columns)
        for k, text in enumerate(columns):
            draw.text((left + tile * (k + 0.5) - width(text) / 2, top - LINE), text, fill="black", font=font)
    if rows:
        tile = h / len(rows)
        for k, text in enumerate(rows):
            draw.text((PAD, top + tile * (k + 0.5) - LINE / 2), text, fill="black", font=font)
    if scale:
        low, high, what = scale
        y, ramp = top + h + PAD, RAMP
        bar = np.repeat(np.linspace(0, 255, ramp).round().astype(np.uint8)[None, :, None], LINE - 4, 0).repeat(3, 2)
        x = left + PAD + width(low) + PAD
        draw.text((left + PAD, y), low, fill="black", font=font)
        canvas.paste(Image.fromarray(bar), (x, y + 2))
        draw.rectangle((x - 1, y + 1, x + ramp, y + LINE - 2), outline="black")
        draw.text((x + ramp + PAD, y), high, fill="black", font=font)
        draw.text((left + PAD, y + LINE + PAD), what, fill="black", font=font)
    return np.asarray(canvas)
