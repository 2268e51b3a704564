"""The multiresolution hash encoding (``material_encoding``/``normal_encoding: hashgrid``) against
a plain loop written here from Mueller et al. 2022 (Instant NGP, Sec. 3: per-level resolution
``floor(N_min b^l)``, one-to-one indexing where the level's vertices fit the table, else the
spatial hash with primes 1, 2654435761, 805459861 in uint32 arithmetic, trilinear weights), in
value and gradient; continuity across cell faces; finiteness at the extremes; the table's step
scale; a field built and saved with it."""

from __future__ import annotations

import math

import pytest
import torch

from stages.config.sections import OptimizeSettings
from stages.core.errors import ConfigError
from stages.model.field import StyleField
from stages.model.networks import HashGridEncoding, _GridInterpolation

SMALL = dict(levels=6, features=2, log2_size=12, min_resolution=4, max_resolution=96)


def paper_encoding(x: torch.Tensor, table: torch.Tensor, *, levels, features, log2_size, min_resolution, max_resolution):
    """The paper's encoding, one point, level and corner at a time (float64; ``table`` is the
    effective ``(levels * T, F)`` table). Returns ``(N, levels * F)``."""
    size = 2**log2_size
    out = []
    for p in x.tolist():
        u = [min(max((c + 1.0) / 2.0, 0.0), 1.0) for c in p]
        feats = []
        for level in range(levels):
            # N_min b^l with b^(levels-1) = N_max / N_min (1e-9: float rounding of an integer)
            n = math.floor(min_resolution * (max_resolution / min_resolution) ** (level / (levels - 1)) + 1e-9)
            lo = [min(math.floor(c * n), n - 1) for c in u]
            f = [c * n - v for c, v in zip(u, lo, strict=True)]
            acc = torch.zeros(features, dtype=torch.float64)
            for i in (0, 1):
                for j in (0, 1):
                    for k in (0, 1):
                        v = (lo[0] + i, lo[1] + j, lo[2] + k)
                        if (n + 1) ** 3 <= size:
                            idx = v[0] + v[1] * (n + 1) + v[2] * (n + 1) ** 2
                        else:
                            h = 0
                            for c, prime in zip(v, (1, 2654435761, 805459861), strict=True):
                                h ^= (c * prime) & 0xFFFFFFFF
                            idx = h % size
                        w = (f[0] if i else 1 - f[0]) * (f[1] if j else 1 - f[1]) * (f[2] if k else 1 - f[2])
                        acc = acc + w * table[level * size + idx]
            feats.append(acc)
        out.append(torch.cat(feats))
    return torch.stack(out)


def _points(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    corners = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0])] * 3)
    return torch.cat([corners, torch.zeros(1, 3), torch.tensor([[0.3, -1.7, 5.0]]), torch.rand(n, 3, generator=g) * 2 - 1])


def _encoding(**kw):
    enc = HashGridEncoding(**{**SMALL, **kw}, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():  # a trained-looking table: entries of order one
        enc.raw.copy_(torch.randn(enc.raw.shape, generator=torch.Generator().manual_seed(2)) / enc.step_scale)
    return enc


def test_levels_resolutions_and_dense_levels():
    enc = _encoding()
    # 4 (96/4)^(l/5): 4, 7.5, 14.2, 26.9, 50.7, 96
    assert enc.resolution.tolist() == [4, 7, 14, 26, 50, 96]
    # one-to-one where (N+1)^3 <= 4096: resolutions 4, 7, 14 (125, 512, 3375 vertices), hashed above
    assert enc.dense_levels == 3
    assert enc.out_dim == 3 + 6 * 2
    # the finest level is the maximum resolution, not one less (16 b^15 rounds to 1023.99999...)
    assert HashGridEncoding().resolution.tolist()[::5] == [16, 64, 256, 1024]  # 16 x 4^(l/5), exactly
    assert HashGridEncoding(min_resolution=16, max_resolution=4096).resolution[-1] == 4096


def test_values_and_table_gradient_equal_the_paper_loop():
    enc = _encoding()
    x = _points()
    table = (enc.raw.detach().double() * enc.step_scale).requires_grad_(True)
    ref = paper_encoding(x.double(), table, **SMALL)
    ours = enc(x)
    torch.testing.assert_close(ours[:, :3], x)
    torch.testing.assert_close(ours[:, 3:].double(), ref, rtol=1e-5, atol=1e-5)
    weights = torch.randn(ref.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    (ref * weights).sum().backward()
    (ours[:, 3:] * weights.float()).sum().backward()
    # the raw table's gradient is the effective table's times the step scale
    torch.testing.assert_close(enc.raw.grad.double(), table.grad * enc.step_scale, rtol=1e-4, atol=1e-4)
    assert (enc.raw.grad != 0).sum() > 100


def test_point_gradient_matches_the_loop_inside_cells():
    enc = _encoding()
    x = (torch.rand(12, 3, generator=torch.Generator().manual_seed(4)) * 1.8 - 0.9).double()
    table = enc.raw.detach().double() * enc.step_scale
    # the loop is not differentiable in x (Python floats): central differences of it instead
    xo = x.float().requires_grad_(True)
    weights = torch.randn(12, 12, generator=torch.Generator().manual_seed(5))
    (enc(xo)[:, 3:] * weights).sum().backward()
    eps = 1e-5
    fd = torch.zeros_like(x)
    for d in range(3):
        step = torch.zeros_like(x)
        step[:, d] = eps
        hi = (paper_encoding(x + step, table, **SMALL) * weights.double()).sum(-1)
        lo = (paper_encoding(x - step, table, **SMALL) * weights.double()).sum(-1)
        fd[:, d] = (hi - lo) / (2 * eps)
    torch.testing.assert_close(xo.grad.double(), fd, rtol=2e-3, atol=2e-3)


def test_continuous_across_cell_faces():
    enc = _encoding()
    finest = float(enc.resolution[-1])
    face = 2.0 * 37.0 / finest - 1.0  # a vertex plane of the finest level, in [-1, 1]
    x = torch.tensor([[face, 0.1, -0.2]])
    d = torch.tensor([[1e-6, 0.0, 0.0]])
    torch.testing.assert_close(enc(x - d), enc(x + d), rtol=0, atol=1e-3)


@pytest.mark.parametrize("autocast", [False, True])
def test_finite_at_the_extremes(autocast):
    enc = _encoding()
    x = torch.cat(
        [_points(), torch.tensor([[1e4, -1e4, 1e-30], [-1.0, -1.0, -1.0], [1.0 - 1e-7, 1.0, -1.0 + 1e-7], [3e38, -3e38, 0.0]])]
    )
    x.requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        y = enc(x)
    assert y.dtype == torch.float32 and torch.isfinite(y).all()
    y[:, 3:].sum().backward()
    assert torch.isfinite(enc.raw.grad).all() and torch.isfinite(x.grad).all()
    # clamped to the box: far outside equals the face it projects onto
    torch.testing.assert_close(enc(torch.tensor([[5.0, 0.2, -9.0]]))[:, 3:], enc(torch.tensor([[1.0, 0.2, -1.0]]))[:, 3:])


def test_step_scale_multiplies_the_optimiser_step():
    """Adam's step does not depend on the gradient's scale, so the table's effective step is
    ``lr * step_scale``: what the scale is for (no learning rate of its own)."""
    steps = []
    for scale in (1.0, 20.0):
        enc = HashGridEncoding(**SMALL, step_scale=scale, generator=torch.Generator().manual_seed(1))
        opt = torch.optim.Adam(enc.parameters(), lr=1e-3)
        before = enc.raw.detach() * scale
        enc(_points())[:, 3:].sum().backward()
        opt.step()
        moved = (enc.raw.detach() * scale - before).abs()
        steps.append(moved[moved > 0].median())
    torch.testing.assert_close(steps[1] / steps[0], torch.tensor(20.0), rtol=1e-3, atol=0)


def test_field_with_hash_grids_trains_saves_and_loads(tmp_path):
    s = OptimizeSettings(material_encoding="hashgrid", normal_encoding="hashgrid", width=32, hashgrid_log2_size=12)
    f = StyleField(s.field_settings())
    assert f.svbrdf.encoding.out_dim == 3 + 16 * 2
    x = _points()
    n = torch.nn.functional.normalize(torch.randn(x.shape, generator=torch.Generator().manual_seed(6)), dim=-1)
    out = f(x, n, n)
    out.shading.rgb.sum().backward()
    assert torch.isfinite(f.svbrdf.encoding.raw.grad).all() and f.svbrdf.encoding.raw.grad.abs().sum() > 0
    assert f.normal_net.encoding.raw.grad is not None
    torch.save(f.state_dict(), tmp_path / "field.pt")
    g = StyleField(s.field_settings())
    g.load_state_dict(torch.load(tmp_path / "field.pt"))
    torch.testing.assert_close(g(x, n, n).shading.rgb, out.shading.rgb)


@pytest.mark.parametrize(
    "bad",
    [
        {"hashgrid_levels": 0},
        {"hashgrid_log2_size": 30},
        {"hashgrid_min_resolution": 64, "hashgrid_max_resolution": 32},
        {"hashgrid_step_scale": 0.0},
        {"material_encoding": "hash"},
    ],
)
def test_bad_hash_grid_settings_fail(bad):
    with pytest.raises(ConfigError):
        OptimizeSettings(**bad)


def test_far_corner_stays_inside_a_level_that_fills_its_table():
    """At ``x = +1`` the cell is the last one (not one past it): on levels whose ``(N + 1)^3``
    vertices fill the table exactly, a vertex past the grid would index the next level's table
    or past the end."""
    kw = dict(levels=2, features=2, log2_size=12, min_resolution=15, max_resolution=15)
    enc = _encoding(**kw)
    assert enc.dense_levels == 2 and (enc.resolution + 1).pow(3).eq(2**12).all()
    x = torch.tensor([[1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])
    table = enc.raw.detach().double() * enc.step_scale
    torch.testing.assert_close(enc(x)[:, 3:].double(), paper_encoding(x.double(), table, **kw), rtol=1e-5, atol=1e-5)


def test_interpolation_gradients_by_gradcheck():
    """The written-out gather/scatter against numerical derivatives in float64, with rows shared
    by several corners and points (the scatter-add must sum them)."""
    g = torch.Generator().manual_seed(7)
    table = torch.randn(10, 3, dtype=torch.float64, generator=g, requires_grad=True)
    index = torch.randint(0, 10, (2, 5, 8), generator=g)
    assert len(index.unique()) < index.numel()
    w = torch.rand(2, 5, 8, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(_GridInterpolation.apply, (table, index, w))


def test_float64_table_runs_in_float64():
    enc = _encoding().double()
    x = _points().double()
    y = enc(x)
    assert y.dtype == torch.float64
    table = enc.raw.detach() * enc.step_scale
    torch.testing.assert_close(y[:, 3:], paper_encoding(x, table, **SMALL), rtol=1e-10, atol=1e-10)
