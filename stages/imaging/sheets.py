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
