"""Images for CLIP: sampling from the cache, crops with coverage, composition, colour encoding."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from stages.guidance.clip import clip_normalize
from stages.imaging.images import (
    background,
    compose,
    gather_points,
    global_spec,
    index_map,
    region_spec,
    sample_crops,
    summed_area,
)
from stages.render.color import linear_to_srgb


def disc_mask(width: int, radius: float) -> np.ndarray:
    yy, xx = np.mgrid[:width, :width]
    c = (width - 1) / 2
    return (yy - c) ** 2 + (xx - c) ** 2 <= radius**2


def test_global_image_evaluates_only_what_clip_sees():
    width, size = 512, 224
    mask = disc_mask(width, 200)
    idx = index_map(np.flatnonzero(mask.ravel()), width)
    spec = global_spec(width, size)
    needed, (lookup,) = gather_points([spec], idx)
    assert lookup.shape == (size, size)
    # at most one point per output pixel, and exactly the output pixels that land on the object
    assert len(needed) == (lookup >= 0).sum() <= size * size
    assert len(needed) < mask.sum() / 4  # far fewer than the 512x512 frame's hits


def test_crops_meet_coverage_and_small_crops_render_natively():
    width, size = 512, 224
    mask = disc_mask(width, 150)
    rng = np.random.default_rng(0)
    crops = sample_crops(summed_area(mask), 20, scale=(0.01, 0.1), min_coverage=0.6, max_tries=50, out_size=size, rng=rng)
    assert all(c.coverage >= 0.6 for c in crops)
    for c in crops:
        h = c.rows.shape[0]
        assert h <= size  # a crop smaller than the output is rendered at its native resolution
        assert c.rows.min() >= 0 and c.rows.max() < width and c.cols.max() < width
    idx = index_map(np.flatnonzero(mask.ravel()), width)
    needed, lookups = gather_points(crops, idx)
    assert len(needed) <= sum(lk.size for lk in lookups)


def test_gather_points_matches_a_sort():
    """The unique hits and each pixel's index into them, as ``np.unique`` and ``np.searchsorted``
    give them (the reference, written here), over random crops that overlap, cross the object's
    edge and miss it, and a view with no hits."""
    rng = np.random.default_rng(3)
    width = 96
    mask = rng.random((width, width)) < 0.3
    idx = index_map(np.flatnonzero(mask.ravel()), width)
    specs = [global_spec(width, 40)] + [region_spec(*rng.uniform(0, 60, 2), rng.uniform(4, 36), 32) for _ in range(6)]
    needed, lookups = gather_points(specs, idx)
    per = [idx[s.rows, s.cols] for s in specs]
    flat = np.concatenate([p.ravel() for p in per])
    want = np.unique(flat[flat >= 0])
    np.testing.assert_array_equal(needed, want)
    for p, lk in zip(per, lookups, strict=True):
        np.testing.assert_array_equal(lk, np.where(p >= 0, np.searchsorted(want, p), -1))
        assert lk.dtype == np.int64 and lk.shape == p.shape
    empty = np.full((width, width), -1, np.int64)
    needed, (lk,) = gather_points([global_spec(width, 40)], empty)
    assert needed.size == 0 and (lk == -1).all()


def test_summed_area_counts_every_rectangle():
    rng = np.random.default_rng(4)
    mask = rng.random((37, 37)) < 0.4
    table = summed_area(mask)
    assert table.shape == (38, 38)
    for _ in range(200):
        t0, t1 = sorted(rng.integers(0, 38, 2))
        l0, l1 = sorted(rng.integers(0, 38, 2))
        count = table[t1, l1] - table[t0, l1] - table[t1, l0] + table[t0, l0]
        assert count == mask[t0:t1, l0:l1].sum()


def test_thin_object_crops_terminate_with_best_effort():
    width = 256
    mask = np.zeros((width, width), bool)
    mask[128, 100:140] = True  # a one-pixel-thin object: no crop can reach 90% coverage
    rng = np.random.default_rng(1)
    t0 = time.perf_counter()
    crops = sample_crops(summed_area(mask), 4, scale=(0.01, 0.02), min_coverage=0.9, max_tries=30, out_size=64, rng=rng)
    assert time.perf_counter() - t0 < 1.0
    assert len(crops) == 4 and all(c.coverage < 0.9 for c in crops)


def test_compose_places_colours_and_background():
    width = 8
    pixel = np.array([0, 9, 63])  # (0,0), (1,1), (7,7)
    idx = index_map(pixel, width)
    spec = region_spec(0, 0, 8, 8)
    needed, (lookup,) = gather_points([spec], idx)
    colors = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])[needed]
    bg = torch.full((3, 8, 8), 0.5)
    img = compose(colors, lookup, spec, bg)
    assert img.shape == (3, 8, 8)
    torch.testing.assert_close(img[:, 0, 0], torch.tensor([1.0, 0, 0]))
    torch.testing.assert_close(img[:, 1, 1], torch.tensor([0, 1.0, 0]))
    torch.testing.assert_close(img[:, 7, 7], torch.tensor([0, 0, 1.0]))
    torch.testing.assert_close(img[:, 3, 4], torch.full((3,), 0.5))
    # a 4-pixel region resized up to 8 and a supersampled one keep the shape
    up = region_spec(0, 0, 4, 8)
    _, (lk,) = gather_points([up], idx)
    assert compose(colors, lk, up, bg).shape == (3, 8, 8)
    ss = region_spec(0, 0, 8, 4, supersample=2)
    _, (lk,) = gather_points([ss], idx)
    assert lk.shape == (8, 8) and compose(colors, lk, ss, torch.zeros(3, 4, 4)).shape == (3, 4, 4)


def test_backgrounds():
    g = torch.Generator().manual_seed(0)
    assert background("black", 4, g, "cpu").sum() == 0
    assert background("white", 4, g, "cpu").min() == 1
    a, b = background("noise", 16, g, "cpu"), background("noise", 16, g, "cpu")
    assert not torch.equal(a, b) and a.min() >= 0 and a.max() <= 1
    with pytest.raises(ValueError):
        background("pink", 4, g, "cpu")


def test_srgb_has_finite_gradient_at_zero_and_clip_normalisation():
    x = torch.tensor([0.0, 0.001, 0.5, 1.0, 2.0], requires_grad=True)
    y = linear_to_srgb(x)
    y.sum().backward()
    assert torch.isfinite(x.grad).all()
    assert y[0] == 0 and y[3].item() == pytest.approx(1.0)
    imgs = torch.full((2, 3, 4, 4), 0.48145466)
    assert clip_normalize(imgs)[:, 0].abs().max() < 1e-6


def test_compose_gathers_like_advanced_indexing_in_value_and_gradient():
    """compose's ``index_select`` gather (whose backward is an ``index_add``) against the plain
    ``colors[idx]`` it replaced: the same image, the same gradient to every point's colour (points
    seen by several pixels accumulate), float64."""
    gen = torch.Generator().manual_seed(0)
    lookup = torch.randint(-1, 5, (6, 6), generator=gen).numpy()  # 5 points, many pixels each; -1: background
    spec = region_spec(0, 0, 6, 6)
    colors = torch.rand(5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    bg = torch.rand(3, 6, 6, generator=gen, dtype=torch.float64)
    weights = torch.rand(3, 6, 6, generator=gen, dtype=torch.float64)
    img = compose(colors, lookup, spec, bg)
    (grad,) = torch.autograd.grad((img * weights).sum(), colors)
    idx = torch.as_tensor(lookup)
    plain = torch.where((idx >= 0)[None], colors[idx.clamp(min=0)].permute(2, 0, 1), bg)
    (plain_grad,) = torch.autograd.grad((plain * weights).sum(), colors)
    torch.testing.assert_close(img, plain, rtol=0, atol=0)
    torch.testing.assert_close(grad, plain_grad, rtol=1e-15, atol=1e-15)


def test_a_views_global_image_gathers_its_hits_counted_from_the_cache(cache):
    """``ViewStore.global_points`` (which sizes a compiled renderer's first pass): at the cache's
    own resolution, one sample a pixel, a view's global image gathers every hit of the view (the
    cache's offsets); at half of it, between a fifth and all of them; at half of it with 2 x 2
    rays a pixel, all of them again."""
    from stages.geometry.normals import NormalSpec
    from stages.geometry.raycache import RayCache
    from stages.imaging.views import ViewStore

    rc = RayCache(cache / "train.npz")
    views = ViewStore(rc, "cpu", NormalSpec())
    hits = np.diff(rc.arrays["offsets"])
    for i in (0, len(hits) - 1):
        assert views.global_points(rc.width, view=i) == hits[i] > 0
        half = views.global_points(rc.width // 2, view=i)
        assert 0.2 * hits[i] <= half <= hits[i]
    assert views.global_points(rc.width // 2, supersample=2) == hits[0]
