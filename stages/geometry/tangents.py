"""Tangent frames for normal maps: MikkTSpace (Mikkelsen 2008, "Simulation of wrinkled surfaces
revisited"), the frame glTF viewers compute when a file has no tangents and Blender computes for its
Normal Map node, written here from the paper and the reference implementation's documented rules.

Inputs per face corner: position, unit shading normal and texture coordinate ``st`` (``t`` up, the
normal map's +Y; glTF's ``v`` is ``1 - t``).

1. Per face: ``dP/ds`` and ``dP/dt`` from its positions and ``st`` (unit), and its orientation
   ``w = sign(ds x dt)`` (+1 where the UV map preserves orientation).
2. Corners with identical position, normal and ``st`` are one vertex (MikkTSpace welds by value, so
   an unindexed, faceted mesh gets the same frame as an indexed one). With flat normals no corner
   is shared between faces: Blender derives a flat face's normal itself, and rounding keeps even
   coplanar faces apart, so each face gets its own frame there.
3. Around each vertex, faces connected through shared edges and of equal orientation form a group;
   each corner's ``dP/ds`` is projected onto the plane of its vertex normal and normalised, weighted
   by the corner's angle measured in that plane, and summed over the group: the group's tangent.
4. A pixel's frame is the *interpolated, unnormalised* tangent ``T`` and normal ``N`` with bitangent
   ``B = w (N x T)`` (MikkTSpace's per-pixel rule); a tangent-space normal ``c`` means the world
   normal ``normalize(c.x T + c.y B + c.z N)``: :func:`frame_at` and :func:`to_tangent_space`.

Where a group's tangent cancels (degenerate UVs), an arbitrary unit vector orthogonal to the normal
is used (MikkTSpace copies a neighbour's; such faces carry no texture detail).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .normals import NormalSpec, corner_groups, perpendicular, unit_face_normals


def face_uv_derivatives(positions: np.ndarray, st: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per face ``dP/ds``, ``dP/dt`` (unit, zero where undefined) and orientation ``w (F,)`` (+1/-1)
    from ``positions (F, 3, 3)`` and ``st (F, 3, 2)``."""
    d1, d2 = positions[:, 1] - positions[:, 0], positions[:, 2] - positions[:, 0]
    t1, t2 = st[:, 1] - st[:, 0], st[:, 2] - st[:, 0]
    det = t1[:, 0] * t2[:, 1] - t1[:, 1] * t2[:, 0]
    w = np.where(det > 0, 1.0, -1.0)
    # det * dP/ds and det * dP/dt (MikkTSpace's eq. 18 and 19); the sign of det restores the direction
    os_ = (t2[:, 1:2] * d1 - t1[:, 1:2] * d2) * w[:, None]
    ot_ = (-t2[:, 0:1] * d1 + t1[:, 0:1] * d2) * w[:, None]
    return _unit(os_), _unit(ot_), w


def mikktspace(positions: np.ndarray, normals: np.ndarray, st: np.ndarray, shared: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """MikkTSpace tangents ``(F, 3, 3)`` (unit, orthogonal to each corner's normal) and the
    handedness ``w (F,)`` from per-corner ``positions, normals (F, 3, 3)`` and ``st (F, 3, 2)``.
    ``shared=False``: no corner is shared between faces (each face its own frame: what MikkTSpace
    computes on a mesh whose faces share no vertex, and what Blender computes for flat-shaded
    faces, whose normals it derives per face so that rounding keeps coplanar faces apart)."""
    p = np.asarray(positions, np.float64)
    n = np.asarray(normals, np.float64)
    st = np.asarray(st, np.float64)
    nf = len(p)
    os_, _, w = face_uv_derivatives(p, st)
    # 2. vertices by value (position, normal, st), as MikkTSpace welds them
    key = np.concatenate([p, n, st], axis=-1).reshape(3 * nf, -1).astype(np.float32)
    if not shared:
        key = np.concatenate([key, np.repeat(np.arange(nf, dtype=np.float32), 3)[:, None]], axis=1)
    _, vid = np.unique(key, axis=0, return_inverse=True)
    vid = vid.reshape(nf, 3)
    # 3. groups: corners at one vertex joined across shared edges of faces of equal orientation
    group = corner_groups(vid, lambda f1, f2: w[f1] == w[f2])
    proj = os_[:, None, :] - n * (n * os_[:, None, :]).sum(-1, keepdims=True)
    proj = _unit(proj)
    e_prev = p[:, [2, 0, 1]] - p
    e_next = p[:, [1, 2, 0]] - p
    e_prev = _unit(e_prev - n * (n * e_prev).sum(-1, keepdims=True))
    e_next = _unit(e_next - n * (n * e_next).sum(-1, keepdims=True))
    angle = np.arccos(np.clip((e_prev * e_next).sum(-1), -1.0, 1.0))
    flat = group.reshape(-1)
    total = np.zeros((int(flat.max(initial=-1)) + 1, 3))
    np.add.at(total, flat, (angle[..., None] * proj).reshape(-1, 3))
    t = total[flat].reshape(nf, 3, 3)
    t = t - n * (n * t).sum(-1, keepdims=True)
    norm = np.linalg.norm(t, axis=-1, keepdims=True)
    bad = norm[..., 0] <= 1e-12
    if bad.any():
        t[bad] = perpendicular(n[bad])
        norm = np.linalg.norm(t, axis=-1, keepdims=True)
    return t / np.maximum(norm, 1e-300), w


def vertex_tangents(positions: np.ndarray, normals: np.ndarray, uv: np.ndarray, triangles: np.ndarray) -> np.ndarray | None:
    """MikkTSpace tangents ``(V, 4)`` (xyz and handedness) per vertex, or None where two corners of
    one vertex get different ones (a vertex shared across a mirrored UV seam)."""
    st = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=-1)[triangles]
    t, w = mikktspace(positions[triangles], normals[triangles], st)
    corner = np.concatenate([t, np.repeat(w[:, None, None], 3, axis=1)], axis=-1).reshape(-1, 4)
    out = np.zeros((len(positions), 4))
    out[triangles.reshape(-1)] = corner
    if np.abs(out[triangles.reshape(-1)] - corner).max(initial=0.0) > 1e-4:
        return None
    return out.astype(np.float32)


def frame_at(tangents: np.ndarray, normals: np.ndarray, w: np.ndarray, face: np.ndarray, bary: np.ndarray):
    """The per-pixel frame ``T, B, N (N, 3)`` at faces ``face (N,)`` and barycentrics ``bary (N, 2)``
    (``(1-u-v) c0 + u c1 + v c2``): interpolated tangents and normals (not normalised) and
    ``B = w (N x T)``."""
    u, v = bary[:, :1], bary[:, 1:2]
    c = np.concatenate([1.0 - u - v, u, v], axis=1)[..., None]
    t = (c * tangents[face]).sum(1)
    n = (c * normals[face]).sum(1)
    return t, w[face][:, None] * np.cross(n, t), n


def to_tangent_space(world: np.ndarray, t: np.ndarray, b: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Unit ``c (N, 3)`` with ``normalize(c.x T + c.y B + c.z N) = world``: the inverse of
    :func:`from_tangent_space` (exact for any non-singular frame)."""
    # the inverse's rows are (B x N, N x T, T x B) / det; a near-singular frame falls back to projections
    det = (t * np.cross(b, n)).sum(-1, keepdims=True)
    adj = np.stack([(np.cross(b, n) * world).sum(-1), (np.cross(n, t) * world).sum(-1), (np.cross(t, b) * world).sum(-1)], -1)
    ok = np.abs(det) > 1e-9
    proj = np.stack([(t * world).sum(-1), (b * world).sum(-1), (n * world).sum(-1)], -1)
    return _unit(np.where(ok, adj / np.where(ok, det, 1.0), proj))


def from_tangent_space(c: np.ndarray, t: np.ndarray, b: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The unit world normal ``normalize(c.x T + c.y B + c.z N)`` of tangent-space ``c (N, 3)``."""
    return _unit(c[:, :1] * t + c[:, 1:2] * b + c[:, 2:3] * n)


def _unit(x: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(norm > 1e-300, x / np.maximum(norm, 1e-300), 0.0)


@dataclass(frozen=True)
class CornerFrames:
    """The normal-map frame of a textured mesh: per corner unit shading ``normals`` and MikkTSpace
    ``tangents`` ``(F, 3, 3)``, the handedness ``w (F,)`` and the flat ``face_normals (F, 3)`` (the
    side a viewer sees). The bake writes the normal map in this frame, the exporters hand its
    normals and tangents to viewers, and the fidelity renders read the map back through it."""

    normals: np.ndarray
    tangents: np.ndarray
    handedness: np.ndarray
    face_normals: np.ndarray

    @classmethod
    def build(cls, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, spec: NormalSpec) -> CornerFrames:
        """For a mesh with atlas ``uv (F, 3, 2)`` (glTF's ``v`` down) and shading normals ``spec``."""
        p = np.asarray(vertices, np.float64)[faces]
        n = spec.corner_normals(vertices, faces)
        st = np.stack([uv[..., 0], 1.0 - uv[..., 1]], axis=-1).astype(np.float64)
        # flat normals: each face its own frame (Blender's for flat-shaded faces; module docstring)
        t, w = mikktspace(p, n, st, shared=spec.mode != "flat")
        return cls(n, t, w, unit_face_normals(vertices, faces))

    def at(self, face: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``T, B, N (N, 3)`` at hits (:func:`frame_at`)."""
        return frame_at(self.tangents, self.normals, self.handedness, face, bary)

    def arrays(self) -> dict[str, np.ndarray]:
        """What ``atlas.npz`` stores of the frame (float32)."""
        return {
            "normal": self.normals.astype(np.float32),
            "tangent": self.tangents.astype(np.float32),
            "handedness": self.handedness.astype(np.float32),
            "face_normal": self.face_normals.astype(np.float32),
        }

    @classmethod
    def from_arrays(cls, a: dict) -> CornerFrames:
        return cls(*(np.asarray(a[k], np.float64) for k in ("normal", "tangent", "handedness", "face_normal")))
