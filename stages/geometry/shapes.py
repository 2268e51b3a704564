"""Built-in sample meshes generated in code (no downloads), y-up like TANGO's camera convention.

* ``vase``   -- a thick-walled vase, a closed surface of revolution (genus 0);
* ``candle`` -- a candle body with a wick and a teardrop flame tip, one closed surface of
  revolution (genus 0);
* ``knot``   -- a tube around a (2, 3) torus knot (genus 1).

All three are watertight, consistently oriented outwards, and are built at the size of a
real object (centimetres, off-centre) so the normalise stage has work to do.
"""

from __future__ import annotations

import numpy as np

BUILTIN_NAMES = ("vase", "candle", "knot")


def revolve(profile: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Revolve a profile curve around the y axis.

    Args:
        profile: ``(P, 2)`` float, points ``(r, y)`` with ``r >= 0``; the first and last points
            must lie on the axis (``r == 0``) so the surface closes at two poles; the interior
            points must have ``r > 0``.
        segments: number of angular segments, ``>= 3``.

    Returns:
        ``vertices (2 + (P - 2) * segments, 3)`` float64 and ``faces (F, 3)`` int64, with
        ``F = 2 * segments * (P - 2)``, a closed genus-0 triangle mesh oriented outwards when the
        profile runs from the bottom pole to the top pole on the outside.
    """
    profile = np.asarray(profile, dtype=np.float64)
    if profile[0, 0] != 0 or profile[-1, 0] != 0 or np.any(profile[1:-1, 0] <= 0):
        raise ValueError("profile must start and end on the axis and stay off it in between")
    rings = profile[1:-1]
    theta = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring_v = np.stack(
        [
            rings[:, None, 0] * np.cos(theta)[None, :],
            np.broadcast_to(rings[:, None, 1], (len(rings), segments)),
            -rings[:, None, 0] * np.sin(theta)[None, :],
        ],
        axis=-1,
    ).reshape(-1, 3)
    bottom = np.array([[0.0, profile[0, 1], 0.0]])
    top = np.array([[0.0, profile[-1, 1], 0.0]])
    vertices = np.concatenate([bottom, ring_v, top])
    n_rings = len(rings)
    idx = 1 + np.arange(n_rings * segments).reshape(n_rings, segments)
    nxt = np.roll(idx, -1, axis=1)
    faces = []
    # bottom fan: pole -> ring 0
    faces.append(np.stack([np.zeros(segments, int), nxt[0], idx[0]], axis=1))
    # quads between rings, two triangles each
    a, b, c, d = idx[:-1], nxt[:-1], nxt[1:], idx[1:]
    faces.append(np.stack([a, b, c], axis=-1).reshape(-1, 3))
    faces.append(np.stack([a, c, d], axis=-1).reshape(-1, 3))
    # top fan: ring -1 -> pole
    top_i = len(vertices) - 1
    faces.append(np.stack([idx[-1], nxt[-1], np.full(segments, top_i)], axis=1))
    return vertices, np.concatenate(faces).astype(np.int64)


def _orient_outwards(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip all faces if the closed mesh's signed volume is negative."""
    tri = vertices[faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    return faces if volume > 0 else faces[:, ::-1].copy()


def vase(segments: int = 96, samples: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A thick-walled vase (outer wall, rounded lip, inner wall, inner floor), in cm."""
    t = np.linspace(0.0, 1.0, samples)
    height = 24.0
    outer_r = 5.0 + 3.2 * np.sin(np.pi * (0.15 + 0.75 * t)) - 2.2 * t**2 + 0.35 * np.sin(9 * t)
    outer = np.stack([outer_r, height * t], axis=1)
    wall = 0.6
    lip_angles = np.linspace(0.0, np.pi, 9)[1:-1]
    lip_c = np.array([outer_r[-1] - wall / 2, height])
    lip = lip_c + (wall / 2) * np.stack([np.cos(lip_angles), np.sin(lip_angles)], axis=1)
    inner_t = t[::-1][:-4]
    inner_r = outer_r[::-1][:-4] - wall
    inner = np.stack([inner_r, height * inner_t], axis=1)
    floor_y = 1.5
    inner = inner[inner[:, 1] > floor_y + 0.5]
    floor_r = np.linspace(inner[-1, 0], 0.0, 6)[1:-1]
    floor = np.stack([floor_r, np.full_like(floor_r, floor_y)], axis=1)
    base_r = np.linspace(0.0, outer_r[0], 6)[:-1]
    base = np.stack([base_r, np.zeros_like(base_r)], axis=1)
    profile = np.concatenate([base, outer[1:], lip, inner, floor, [[0.0, floor_y]]])
    v, f = revolve(profile, segments)
    v += np.array([3.0, 100.0, -2.0])  # off-centre, like real scans
    return v, _orient_outwards(v, f)


def candle(segments: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A pillar candle with a melted top rim, a wick and a teardrop flame, in cm."""
    body_r, body_h = 3.5, 10.0
    base = np.stack([np.linspace(0, body_r - 0.2, 6)[:-1], np.zeros(5)], axis=1)
    bevel_a = np.linspace(-np.pi / 2, 0, 5)
    bevel = np.stack([body_r - 0.2 + 0.2 * np.cos(bevel_a), 0.2 + 0.2 * np.sin(bevel_a)], axis=1)
    wall_y = np.linspace(0.4, body_h, 24)
    wall = np.stack([body_r + 0.05 * np.sin(wall_y * 1.7), wall_y], axis=1)
    rim_a = np.linspace(0, np.pi / 2, 6)[1:]
    rim = np.stack([body_r - 0.3 + 0.3 * np.cos(rim_a), body_h + 0.3 * np.sin(rim_a)], axis=1)
    # a shallow melted dish down to the wick
    dish_r = np.linspace(body_r - 0.35, 0.12, 12)
    dish = np.stack([dish_r, body_h + 0.3 - 0.6 * (1 - dish_r / body_r) ** 0.5], axis=1)
    wick_base = dish[-1, 1]
    wick = np.array([[0.06, wick_base], [0.06, wick_base + 0.9]])
    fl = np.linspace(0.0, 1.0, 20)[1:]
    flame_h = 2.6
    flame_r = 0.55 * np.sin(np.pi * fl) ** 1.2 * (1 - fl) ** 0.35 + 0.06 * (1 - fl)
    flame = np.stack([flame_r, wick_base + 0.9 + flame_h * fl], axis=1)
    flame = flame[flame[:, 0] > 1e-3]
    tip = [[0.0, wick_base + 0.9 + flame_h]]
    profile = np.concatenate([base, bevel, wall, rim, dish, wick, flame, tip])
    v, f = revolve(profile, segments)
    v += np.array([-1.0, 20.0, 4.0])
    return v, _orient_outwards(v, f)


def knot(p: int = 2, q: int = 3, samples: int = 320, sides: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """A tube of radius 0.45 around a (p, q) torus knot on a torus of radii 2 and 1 (genus 1).

    The tube frame uses ``d(t)``, the unit vector from the torus' core circle to the curve: it is
    exactly perpendicular to the curve's tangent (the core's tangent is perpendicular to ``d`` and
    ``d'`` is perpendicular to ``d``), so the frame is smooth and closes up without twist.
    """
    t = np.linspace(0.0, 2.0 * np.pi, samples, endpoint=False)
    c_pt, s_pt = np.cos(p * t), np.sin(p * t)
    c_qt, s_qt = np.cos(q * t), np.sin(q * t)
    curve = np.stack([(2 + c_qt) * c_pt, (2 + c_qt) * s_pt, s_qt], axis=1)
    tangent = np.stack(
        [
            -q * s_qt * c_pt - p * (2 + c_qt) * s_pt,
            -q * s_qt * s_pt + p * (2 + c_qt) * c_pt,
            q * c_qt,
        ],
        axis=1,
    )
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([c_qt * c_pt, c_qt * s_pt, s_qt], axis=1)
    binormal = np.cross(tangent, normal)
    phi = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    radius = 0.45
    ring = radius * (np.cos(phi)[None, :, None] * normal[:, None, :] + np.sin(phi)[None, :, None] * binormal[:, None, :])
    v = (curve[:, None, :] + ring).reshape(-1, 3)
    idx = np.arange(samples * sides).reshape(samples, sides)
    a = idx
    b = np.roll(idx, -1, axis=0)
    c = np.roll(b, -1, axis=1)
    d = np.roll(idx, -1, axis=1)
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    # stand the knot up (its symmetry axis along +z becomes +y) and place it off-centre, in cm
    v = v[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0]) * 4.0 + np.array([10.0, 5.0, 0.0])
    return v, _orient_outwards(v, f.astype(np.int64))


def builtin_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of the built-in mesh ``name``."""
    makers = {"vase": vase, "candle": candle, "knot": knot}
    if name not in makers:
        raise KeyError(f"unknown built-in mesh {name!r}; choose one of {', '.join(BUILTIN_NAMES)}")
    return makers[name]()
