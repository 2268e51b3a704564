"""One bounce (stages/render/light/bounce.py, ShadowCache.bounce_irradiance): the cosine-weighted
directions, the furnace (a point inside a closed sphere whose every side sends ``c`` receives
``pi c``), the configuration factor of a wall seen from a floor (Howell's catalogue: a plane
element and an infinitely long perpendicular strip), the diffuse reflection of it, gradients."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from stages.geometry.meshio import TriMesh
from stages.geometry.tracing import EmbreeTracer
from stages.model.shadows import ShadowCache
from stages.render.brdf import GLTF, TANGO
from stages.render.light.bounce import BounceLight, cosine_directions, indirect_irradiance


def test_cosine_directions_are_distributed_as_the_cosine():
    """Over many points: unit, above the horizon, E[cos] = 2/3 and E[cos^2] = 1/2 (the cosine
    density's moments), no azimuth preferred; at the poles too."""
    gen = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(4000, 3, generator=gen, dtype=torch.float64), dim=-1)
    n[:2] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    d = cosine_directions(n, 16, torch.rand(4000, 2, generator=gen, dtype=torch.float64))
    assert torch.allclose(torch.linalg.vector_norm(d, dim=-1), torch.ones(4000, 16, dtype=torch.float64))
    c = (d * n[:, None]).sum(-1)
    assert bool((c >= 0).all())
    assert float(c.mean()) == pytest.approx(2 / 3, abs=3e-3)
    assert float((c**2).mean()) == pytest.approx(1 / 2, abs=3e-3)
    across = d - c[..., None] * n[:, None]
    assert float(torch.linalg.vector_norm(across.mean((0, 1)))) < 0.01


def _sphere(inward: bool) -> TriMesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    faces = np.asarray(s.faces, np.int64)
    return TriMesh(np.asarray(s.vertices, np.float64), faces[:, ::-1] if inward else faces)


@pytest.mark.parametrize("samples", [1, 8, 64])
def test_a_closed_sphere_is_a_furnace(samples):
    """Points on the inside of a closed sphere, every face side sending ``c``: every ray meets
    the sphere, so ``E = pi c`` exactly; the side met is the front of an inward-facing mesh (row
    ``2 f``) and the back of an outward one (``2 f + 1``)."""
    for inward in (True, False):
        mesh = _sphere(inward)
        gen = np.random.default_rng(1)
        f = gen.integers(0, len(mesh.faces), 300)
        points = mesh.vertices[mesh.faces[f]].mean(1) * 0.999
        normals = -points / np.linalg.norm(points, axis=1, keepdims=True)  # into the sphere
        cache = ShadowCache(mesh, points, normals, EmbreeTracer(mesh), directions=8, samples=0)
        c = torch.tensor([0.3, 1.0, 2.5], dtype=torch.float64)
        table = torch.zeros(2 * len(mesh.faces), 3, dtype=torch.float64)
        table[slice(0 if inward else 1, None, 2)] = c
        e = cache.bounce_irradiance(BounceLight(table, samples))
        assert torch.allclose(e, math.pi * c.expand(300, 3), rtol=1e-12)


def _floor_and_wall(height: float) -> tuple[TriMesh, int]:
    """A floor ``[-50, 50]^2`` at ``y = 0`` (normal up) and a wall at ``x = 0`` of ``height``
    along ``z`` in ``[-200, 200]`` facing ``-x``; returns the mesh and the wall's first face."""
    v = np.array(
        [[-50, 0, -50], [50, 0, -50], [50, 0, 50], [-50, 0, 50], [0, 0, -200], [0, 0, 200], [0, height, 200], [0, height, -200]],
        np.float64,
    )
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]], np.int64)
    return TriMesh(v, f), 2


@pytest.mark.parametrize(("x", "height"), [(0.5, 1.0), (1.0, 1.0), (2.0, 0.5), (0.3, 4.0)])
def test_a_wall_seen_from_the_floor_sends_its_configuration_factor(x, height):
    """A floor point at distance ``x`` from a wall of ``height`` (long along the edge), the wall's
    side facing it sending ``c``: ``E = pi c F`` with Howell's factor for a plane element and an
    infinitely long perpendicular strip, ``F = (1 - x / sqrt(x^2 + h^2)) / 2``, written here.
    Mean over 2,000 points (each its own shifted lattice of 256 directions) within 1%; the rays
    start ``offset`` above the floor, which sees the wall that much lower."""
    mesh, wall = _floor_and_wall(height)
    n = 2000
    z = np.linspace(-5.0, 5.0, n)
    points = np.column_stack([np.full(n, -x), np.zeros(n), z])
    cache = ShadowCache(mesh, points, np.tile([0.0, 1.0, 0.0], (n, 1)), EmbreeTracer(mesh), directions=8, samples=0)
    assert np.allclose(mesh.face_normals[wall : wall + 2], [[-1.0, 0.0, 0.0]] * 2)  # the wall faces the floor point
    table = torch.zeros(2 * len(mesh.faces), 1, dtype=torch.float64)
    table[[2 * wall, 2 * (wall + 1)]] = 2.0  # their fronts: the rays meet them against their normals
    e = cache.bounce_irradiance(BounceLight(table, 256)).mean().item()
    h = height - cache.offset  # the rays start this far above the floor (ShadowCache.offset)
    factor = 0.5 * (1.0 - x / math.sqrt(x * x + h * h))
    assert e == pytest.approx(math.pi * 2.0 * factor, rel=0.01)


def test_the_bounce_is_reflected_by_the_diffuse_term():
    """TANGO's sum: ``albedo E / pi``; glTF's layer: times ``1 - F`` of the dielectric
    (``F = 0.04 + 0.96 (1 - v.h)^5`` at ``h`` halfway between the view and the normal), written
    here; no specular term; none without an irradiance."""
    gen = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=-1)
    v = torch.nn.functional.normalize(n + 0.8 * torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=-1)
    v = torch.where(((n * v).sum(-1, keepdim=True) > 0), v, -v)
    albedo = torch.rand(50, 3, generator=gen, dtype=torch.float64)
    e = 3.0 * torch.rand(50, 3, generator=gen, dtype=torch.float64)
    m = SimpleNamespace(albedo=albedo, specular=torch.full_like(albedo, 0.04), roughness=torch.full((50, 1), 0.5))
    light = BounceLight(torch.zeros(4, 3, dtype=torch.float64))
    tango = light.shade(TANGO, n, v, m, None, e)
    assert torch.allclose(tango.diffuse, albedo * e / math.pi) and not bool(tango.specular.any())
    h = torch.nn.functional.normalize(v + n, dim=-1)
    vh = (v * h).sum(-1, keepdim=True)
    layer = 1.0 - (0.04 + 0.96 * (1.0 - vh) ** 5)
    gltf = light.shade(GLTF, n, v, m, None, e)
    assert torch.allclose(gltf.diffuse, albedo * e / math.pi * layer)
    assert not bool(light.shade(TANGO, n, v, m, None, None).rgb.any())


def test_the_irradiance_is_linear_in_the_table_with_its_gradient():
    """``indirect_irradiance`` is ``pi / K`` times the sum of the rows met (a miss adds nothing),
    written out per point; its gradient reaches exactly the rows met, ``pi / K`` per meeting;
    finite in float32 and bfloat16 for tables from 1e-30 to 1e30."""
    sides = torch.tensor([[0, 1, -1, 1], [-1, -1, -1, -1], [3, 3, 3, 3]])
    table = torch.tensor([[1.0], [2.0], [5.0], [7.0]], dtype=torch.float64, requires_grad=True)
    e = indirect_irradiance(table, sides)
    want = torch.tensor([[math.pi / 4 * (1 + 2 + 2)], [0.0], [math.pi * 7.0]], dtype=torch.float64)
    assert torch.allclose(e, want)
    e.sum().backward()
    assert torch.allclose(table.grad[:, 0], torch.tensor([1.0, 2.0, 0.0, 4.0], dtype=torch.float64) * math.pi / 4)
    for dtype in (torch.float32, torch.bfloat16):
        for scale in (1e-30, 1.0, 1e30):
            t = torch.full((4, 3), scale, dtype=dtype, requires_grad=True)
            out = indirect_irradiance(t, sides)
            out.sum().backward()
            assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(t.grad).all())


def _corner_factor(a: np.ndarray, b: np.ndarray, c: float) -> np.ndarray:
    """Howell's catalogue, a plane element to a parallel ``a x b`` rectangle at distance ``c`` whose
    corner lies on the element's normal: ``1/(2 pi) [A/sqrt(1+A^2) atan(B/sqrt(1+A^2)) +
    B/sqrt(1+B^2) atan(A/sqrt(1+B^2))]``, ``A = a/c``, ``B = b/c``."""
    big_a, big_b = a / c, b / c
    ra, rb = np.sqrt(1 + big_a**2), np.sqrt(1 + big_b**2)
    return (big_a / ra * np.arctan(big_b / ra) + big_b / rb * np.arctan(big_a / rb)) / (2 * np.pi)


def test_an_open_box_sends_all_but_what_leaves_by_its_opening():
    """Points on the floor of an open box (side 2, height 1.5), every inner wall sending ``c``:
    ``E = pi c (1 - F)``, ``F`` the factor of the opening above (a parallel square: four rectangles
    cornered at the point's foot, :func:`_corner_factor`); the floor sends nothing to itself.
    Within 1% at each of 40 points (2,000 hits each)."""
    import trimesh

    side, height = 2.0, 1.5
    box = trimesh.creation.box(extents=(side, height, side))
    box.apply_translation([0.0, height / 2, 0.0])
    keep = ~(np.isclose(box.triangles_center[:, 1], height))  # no top: open
    mesh = TriMesh(np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)[keep])
    gen = np.random.default_rng(5)
    foot = gen.uniform(-0.8, 0.8, (40, 2))
    points = np.repeat(np.column_stack([foot[:, 0], np.zeros(40), foot[:, 1]]), 2000, axis=0)
    cache = ShadowCache(mesh, points, np.tile([0.0, 1.0, 0.0], (len(points), 1)), EmbreeTracer(mesh), directions=8, samples=0)
    walls = np.abs(mesh.face_normals[:, 1]) < 0.5
    table = torch.zeros(2 * len(mesh.faces), 1, dtype=torch.float64)
    table[torch.from_numpy(2 * np.flatnonzero(walls) + 1)] = 1.5  # their inner sides: the backs of outward faces
    e = cache.bounce_irradiance(BounceLight(table, 16)).numpy().reshape(40, 2000).mean(1)
    h = height - cache.offset
    x, z = foot[:, 0], foot[:, 1]
    half = side / 2
    opening = sum(_corner_factor(half + sx * x, half + sz * z, h) for sx in (-1, 1) for sz in (-1, 1))
    np.testing.assert_allclose(e, np.pi * 1.5 * (1.0 - opening), rtol=0.01)
