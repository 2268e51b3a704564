"""Images for the guidance model, built from cached ray hits: one global image per view and
local crops with enough object coverage; backgrounds; compositing.

Only the pixels the guidance model will look at are rendered: an image of ``S x S`` pixels drawn
from a ``W x W`` cached view samples the cache at its own resolution (nearest cached pixel per
output pixel, or ``s x s`` sub-pixels averaged when supersampling), and a crop smaller than
``S`` is rendered at its native cached resolution and resized up. The union of the cached hits
that any image needs is shaded once per step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as F


def index_map(pixel: np.ndarray, width: int) -> np.ndarray:
    """``(W, W) int64``: the hit index of each cached pixel, -1 where the ray missed."""
    m = np.full(width * width, -1, np.int64)
    m[pixel] = np.arange(len(pixel))
    return m.reshape(width, width)


@dataclass(frozen=True)
class ImageSpec:
    """One image to render: ``rows, cols (h, w) int64`` cached pixel coordinates per rendered
    pixel, resized to ``out_size`` after rendering when ``h < out_size`` (crops smaller than the
    output), averaged over ``supersample x supersample`` blocks when supersampling."""

    rows: np.ndarray
    cols: np.ndarray
    out_size: int
    supersample: int = 1
    coverage: float = 1.0


def region_spec(top: float, left: float, side: float, out_size: int, supersample: int = 1) -> ImageSpec:
    """Sample a square region (cached-pixel units, float) to an ``out_size`` image.

    If the region is at least ``out_size`` cached pixels wide, each output (sub-)pixel takes its
    nearest cached pixel; otherwise the region's own cached pixels are rendered and resized up.
    """
    if side >= out_size:
        n = out_size * supersample
        centres = (np.arange(n) + 0.5) / n * side
        rows = np.floor(top + centres).astype(np.int64)
        cols = np.floor(left + centres).astype(np.int64)
        ss = supersample
    else:
        n = max(int(round(side)), 1)
        rows = int(round(top)) + np.arange(n)
        cols = int(round(left)) + np.arange(n)
        ss = 1
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    return ImageSpec(rr, cc, out_size, ss)


def global_spec(width: int, out_size: int, supersample: int = 1) -> ImageSpec:
    return region_spec(0.0, 0.0, float(width), out_size, supersample)


def summed_area(mask: np.ndarray) -> np.ndarray:
    """``(H + 1, W + 1)`` summed-area table of ``mask (H, W) bool``: entry ``[r, c]`` counts the
    true pixels above row ``r`` and left of column ``c`` (Crow, SIGGRAPH 1984), so that any
    rectangle's count is four lookups; int32 where the mask has fewer than 2^31 pixels (every
    cache: at most 8,192 x 8,192), else int64. A view's is built once
    (:attr:`~stages.imaging.views.CachedView.mask_sums`), not at every step's crops."""
    dtype = np.int32 if mask.size < 2**31 else np.int64
    table = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), dtype)
    table[1:, 1:] = mask.astype(dtype).cumsum(0, dtype=dtype).cumsum(1, dtype=dtype)
    return table


def sample_crops(
    mask_sums: np.ndarray,
    count: int,
    *,
    scale: tuple[float, float],
    min_coverage: float,
    max_tries: int,
    out_size: int,
    rng: np.random.Generator,
    supersample: int = 1,
) -> list[ImageSpec]:
    """``count`` square crops of a view whose area fraction lies in ``scale`` and whose object
    coverage (fraction of hit pixels, from the view's mask's :func:`summed_area` table
    ``mask_sums (W + 1, W + 1)``) is at least ``min_coverage``.

    Each crop tries at most ``max_tries`` random placements and keeps the first that qualifies,
    or else the best one seen (so thin objects never loop forever). The coverage reached is
    recorded in the spec.
    """
    width = mask_sums.shape[0] - 1
    integral = mask_sums
    specs = []
    for _ in range(count):
        best = None
        for _ in range(max_tries):
            side = np.sqrt(rng.uniform(*scale)) * width
            top, left = rng.uniform(0, width - side, size=2)
            t0, l0 = int(round(top)), int(round(left))
            s = max(int(round(side)), 1)
            t1, l1 = min(t0 + s, width), min(l0 + s, width)
            covered = integral[t1, l1] - integral[t0, l1] - integral[t1, l0] + integral[t0, l0]
            cov = covered / max((t1 - t0) * (l1 - l0), 1)
            if best is None or cov > best[0]:
                best = (cov, top, left, side)
            if cov >= min_coverage:
                break
        cov, top, left, side = best
        spec = region_spec(top, left, side, out_size, supersample)
        specs.append(ImageSpec(spec.rows, spec.cols, spec.out_size, spec.supersample, float(cov)))
    return specs


def gather_points(specs: list[ImageSpec], hit_index: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The unique cached hits all ``specs`` need, ascending, and each spec's ``(h, w)`` index into
    them (-1 = background). In time linear in the pixels and the view's hits (a mark per hit, then
    each hit's rank), not a sort: it runs on the host at every step, before any of the step's work
    can start (on a GPU, whose step is short, a sort's 8 ms here was a tenth of it)."""
    per = [hit_index[s.rows, s.cols] for s in specs]
    used = np.zeros(int(hit_index.max(initial=-1)) + 2, bool)  # one per hit, and a last for -1 (background)
    for p in per:
        used[p] = True
    used[-1] = False
    needed = np.flatnonzero(used)
    rank = np.full(len(used), -1, np.int64)  # rank[-1] stays -1: background pixels index the last entry
    rank[needed] = np.arange(len(needed))
    return needed, [rank[p] for p in per]


def background(kind: str, size: int, generator: torch.Generator, device) -> Tensor:
    """``(3, size, size)`` background: ``black``, ``white``, or ``noise`` (fresh Gaussian noise,
    mean 0.5, std 0.2, clipped to [0, 1], drawn from ``generator``)."""
    if kind == "black":
        return torch.zeros(3, size, size, device=device)
    if kind == "white":
        return torch.ones(3, size, size, device=device)
    if kind == "noise":
        noise = torch.randn(3, size, size, generator=generator) * 0.2 + 0.5
        return noise.clamp(0.0, 1.0).to(device)
    raise ValueError(f"unknown background {kind!r}; use black, white or noise")


def compose(colors: Tensor, lookup: np.ndarray, spec: ImageSpec, bg: Tensor) -> Tensor:
    """Scatter per-point ``colors (M, 3)`` into one image ``(3, out, out)`` over ``bg`` (moved to
    the colours' device). The pixels gather their points with ``index_select``, whose backward is
    an ``index_add``: advanced indexing's backward (a sorting ``index_put``) took 48% of a CUDA
    training step's GPU time (benchmarks/training/gpu.py's profile, H100)."""
    idx = torch.as_tensor(lookup, device=colors.device)
    h, w = idx.shape
    hit = idx >= 0
    bg = bg.to(colors.device)
    img = colors.index_select(0, idx.clamp(min=0).reshape(-1)).view(h, w, colors.shape[-1]).permute(2, 0, 1)  # (3, h, w)
    if spec.supersample > 1 or h != spec.out_size:
        bg_native = F.interpolate(bg[None], size=(h, w), mode="nearest")[0]
    else:
        bg_native = bg
    img = torch.where(hit[None], img, bg_native)
    if spec.supersample > 1:
        img = F.avg_pool2d(img[None], spec.supersample)[0]
    elif h != spec.out_size:
        img = F.interpolate(img[None], size=(spec.out_size, spec.out_size), mode="bilinear", align_corners=False)[0]
    return img


def render_cached_view(view, width: int, out_size: int, colors, background: float = 0.0) -> Tensor:
    """One cached view as an image: ``colors(view, sel) -> (M, 3)`` (display space) is evaluated
    at the hits ``sel`` (indices into the view's hits) that an ``out_size`` image of the
    ``width``-pixel cache shows, and composed over a constant ``background``. ``view`` has
    ``points``, ``normals``, ``view`` (tensors) and ``index`` (the hit-index map). Returns
    ``(3, out_size, out_size)``."""
    spec = global_spec(width, out_size)
    needed, (lookup,) = gather_points([spec], view.index)
    sel = torch.from_numpy(needed).to(view.points.device)
    col = colors(view, sel)
    bg = torch.full((3, out_size, out_size), float(background), device=view.points.device)
    return compose(col, lookup, spec, bg)
