"""The shadow cache of a fixed point set: a ball over a floor casts a sun's shadow exactly (rays
drawn from the lobe), a broad lobe's shadow by quadrature with gradients, the sharp lobes' rays
traced once and again only when the lobe has moved."""

import math

import numpy as np
import torch
import trimesh

from stages.geometry.meshio import TriMesh
from stages.geometry.tracing import EmbreeTracer
from stages.model.shadows import ShadowCache
from stages.render.shading import SGLight


def _scene():
    floor = trimesh.creation.box(extents=(40.0, 40.0, 0.1))
    floor.apply_translation((0.0, 0.0, -0.05))
    ball = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    ball.apply_translation((0.0, 0.0, 2.0))
    m = trimesh.util.concatenate([floor, ball])
    mesh = TriMesh(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64))
    # floor points from under the ball outwards along x
    points = np.stack([np.linspace(0.0, 3.0, 13), np.zeros(13), np.zeros(13)], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (13, 1))
    return mesh, points, normals


def _light(axis, sharpness):
    axis = torch.nn.functional.normalize(torch.tensor(axis, dtype=torch.float32), dim=-1)
    return SGLight(axis, torch.tensor(sharpness, dtype=torch.float32)[:, None], torch.ones(len(axis), 3))


def test_a_sun_casts_the_balls_shadow_exactly():
    """A sun straight above (sharpness 1e4: 0.6 degrees wide): the floor is dark out to the ball's
    radius and lit beyond it, the edge where the ball's silhouette is (x = 1, within a sample's
    spread); a sun from 45 degrees moves the shadow to x = 2 (the ball's centre projected)."""
    mesh, points, normals = _scene()
    shadows = ShadowCache(mesh, points, normals, EmbreeTracer(mesh), directions=512, samples=32)
    x = points[:, 0]
    up = shadows.shares(_light([[0.0, 0.0, 1.0]], [1e4]))[:, 0].numpy()
    assert (up[x < 0.95] < 0.05).all() and (up[x > 1.05] > 0.95).all(), up
    slanted = shadows.shares(_light([[-1.0, 0.0, 1.0]], [1e4]))[:, 0].numpy()  # a sun towards -x
    # the shadow of a unit ball at height 2 under a 45-degree sun: x in 2 -+ sqrt(2)
    inside = np.abs(x - 2.0) < math.sqrt(2.0) - 0.1
    outside = np.abs(x - 2.0) > math.sqrt(2.0) + 0.1
    assert (slanted[inside] < 0.05).all() and (slanted[outside] > 0.95).all(), slanted


def test_a_broad_lobe_is_shadowed_by_quadrature_with_gradients():
    """A lobe of sharpness 4 straight up: its share under the ball against the integral over the
    polar angle written here (the ball's cone of half-angle 30 degrees blocked), and a gradient in
    its axis and sharpness."""
    mesh, points, normals = _scene()
    shadows = ShadowCache(mesh, points[:1], normals[:1], EmbreeTracer(mesh), directions=1024)
    raw = torch.tensor([[0.0, 0.0, 1.0]], requires_grad=True)
    log_lam = torch.tensor([[math.log(4.0)]], requires_grad=True)
    light = SGLight(torch.nn.functional.normalize(raw, dim=-1), torch.exp(log_lam), torch.ones(1, 3))
    share = shadows.shares(light)
    t = np.linspace(0.0, math.pi / 2, 100_001)
    f = np.exp(4.0 * (np.cos(t) - 1.0)) * np.cos(t) * np.sin(t)
    expected = np.trapezoid(np.where(t > math.asin(0.5), f, 0.0), t) / np.trapezoid(f, t)
    assert abs(float(share.detach()) - expected) < 0.03, (float(share.detach()), expected)
    share.sum().backward()
    assert float(log_lam.grad) < 0  # sharper: more of the lobe in the blocked cone, less lit
    assert torch.isfinite(raw.grad).all()


def test_sharp_lobes_are_traced_once_and_again_only_when_moved():
    mesh, points, normals = _scene()
    shadows = ShadowCache(mesh, points, normals, EmbreeTracer(mesh), directions=256, samples=16, tolerance=0.25)
    light = _light([[0.0, 0.0, 1.0], [0.0, 1.0, 0.2]], [1e3, 2.0])
    index = torch.tensor([0, 3, 5])
    first = shadows.shares(light, index)
    lobe = shadows._lobes[0]
    assert lobe.traces == 3 and 1 not in shadows._lobes  # the broad lobe is never traced
    torch.testing.assert_close(shadows.shares(light, index), first)
    assert lobe.traces == 3
    # moved by less than a quarter of its width (1 / sqrt(1000) = 1.8 degrees): no new rays
    nudged = _light([[0.0, 0.005, 1.0], [0.0, 1.0, 0.2]], [1e3, 2.0])
    shadows.shares(nudged, index)
    assert lobe.traces == 3
    # moved by more: every point asked for is traced again
    moved = _light([[0.0, 0.05, 1.0], [0.0, 1.0, 0.2]], [1e3, 2.0])
    shadows.shares(moved, torch.tensor([0, 1]))
    assert lobe.traces == 5
    assert shadows.blocked_share().shape == (13,) and shadows.seconds > 0


def test_without_samples_every_lobe_takes_the_quadrature():
    """samples=0 (the training's path): a sun sees the nearest stored directions, so the ball's
    shadow is still cast, at the directions' resolution, and nothing is traced."""
    mesh, points, normals = _scene()
    shadows = ShadowCache(mesh, points, normals, EmbreeTracer(mesh), directions=1024, samples=0)
    up = shadows.shares(_light([[0.0, 0.0, 1.0]], [1e4]))[:, 0].numpy()
    x = points[:, 0]
    assert (up[x < 0.8] < 0.05).all() and (up[x > 1.3] > 0.95).all(), up
    assert not shadows._lobes
