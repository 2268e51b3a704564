"""One bounce in our renderer against Mitsuba's: a grey Lambertian box on a grey floor under a
3-degree disc 40 degrees up, the light the surfaces send each other being what Mitsuba's path
tracer adds between ``max_depth`` 2 (direct light) and 3 (one bounce more), rendered with the
same seed so that the direct part is the same samples in both; ours, the face sides' direct
radiance (the sun found in the map, its shadow rays) reflected once through 64 cosine-distributed
first hits per pixel (``BounceLight``). Judged over the surfaces that receive most of it: the box's
sides (measured within 0.6%) and the floor around it (0.5%); hemisphere directions drawn uniform
instead of by the cosine fail it (15% low)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_sun_vs_mitsuba import _disc_map, _found_sun, _hits, _mitsuba, _renderer

from stages.geometry.meshio import TriMesh
from stages.geometry.raycache import ViewSet
from stages.geometry.tracing import EmbreeTracer
from stages.geometry.visibility import viewer_side_normals
from stages.model.bounce import FaceSides, bounce_table
from stages.model.shadows import ShadowCache
from stages.render.brdf import TANGO
from stages.render.light import Light

ALBEDO = 0.6


def _grid(corner: np.ndarray, a: np.ndarray, b: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A quad ``corner + s a + t b`` split into ``n x n`` cells of two triangles (normal ``a x b``)."""
    s, t = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    v = corner + s.reshape(-1, 1) * a + t.reshape(-1, 1) * b
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    i = i.reshape(-1)
    f = np.concatenate([np.stack([i, i + n + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + 1], 1)])
    return v, f


def _scene() -> TriMesh:
    """A floor ``[-3, 3]^2`` (60 x 60 cells) and a unit box standing on it (8 x 8 cells a side, its
    faces outwards; no bottom: the floor closes it)."""
    parts = [_grid(np.array([-3.0, 0.0, -3.0]), np.array([0.0, 0.0, 6.0]), np.array([6.0, 0.0, 0.0]), 60)]
    x, y, z = np.eye(3)
    lo = np.array([-0.5, 0.0, -0.5])
    for corner, a, b in ((lo, z, y), (lo + x, y, z), (lo, y, x), (lo + z, x, y), (lo + y, z, x)):  # outwards; no bottom
        parts.append(_grid(corner, a, b, 8))
    vertices, faces, base = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + base)
        base += len(v)
    return TriMesh(np.concatenate(vertices), np.concatenate(faces))


@pytest.mark.slow(minutes=0.5)
def test_one_bounce_matches_mitsubas_second_bounce():
    mi = _mitsuba()
    mesh = _scene()
    el = math.radians(40.0)
    axis = np.array([math.cos(el) * math.cos(0.6), math.sin(el), math.cos(el) * math.sin(0.6)])
    env = _disc_map(axis)
    views = ViewSet(np.array([0.6 + math.pi / 2]), np.array([math.radians(30.0)]), np.array([4.0]), 50.0, 96, 0.0, 0.0)
    hits = _hits(mesh, views)
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [ALBEDO] * 3}}
    direct, alpha = _renderer(mi, mesh, views, env, hits, depth=2, spp=512)(grey)
    bounced, _ = _renderer(mi, mesh, views, env, hits, depth=3, spp=512)(grey)
    theirs = (bounced - direct).mean(1)
    sun = _found_sun(env, 16)
    senders = FaceSides(mesh, 64)
    m_send = SimpleNamespace(albedo=torch.full((len(senders), 3), ALBEDO, dtype=torch.float64), specular=None, roughness=None)
    n_send = torch.from_numpy(senders.normals)

    def shade(light, visibility):
        return light.shade(TANGO, n_send, n_send, m_send, None, visibility(light))

    bounce = bounce_table(senders, shade, Light.of(sun), 64)
    oriented = viewer_side_normals(mesh.face_normals[hits.face], hits.direction)
    cache = ShadowCache(mesh, hits.point.astype(np.float64), oriented, EmbreeTracer(mesh), directions=64, samples=0)
    n = torch.from_numpy(oriented)
    v = -torch.from_numpy(hits.direction.astype(np.float64))
    m = SimpleNamespace(albedo=torch.full((len(n), 3), ALBEDO, dtype=torch.float64), specular=None, roughness=None)
    ours = bounce.shade(TANGO, n, v, m, None, cache.bounce_irradiance(bounce)).rgb.numpy().mean(1)
    covered = alpha > 0.999
    on_box = (mesh.face_normals[hits.face][:, 1] < 0.5) & covered  # the box's sides
    near = (np.abs(hits.point[:, 0]) < 1.5) & (np.abs(hits.point[:, 2]) < 1.5) & (hits.point[:, 1] < 1e-6) & covered
    for region in (on_box, near):
        assert region.sum() > 300
        assert abs(ours[region].sum() / theirs[region].sum() - 1.0) < 0.03, (ours[region].sum(), theirs[region].sum())
    assert abs(ours[covered].sum() / theirs[covered].sum() - 1.0) < 0.03
