"""Normalisation into the unit sphere (TANGO Sec. 3.1) and its inverse transform.

The vertex centroid moves to the origin and the mesh is scaled so that its farthest vertex lies
at distance 1: ``x_n = s * R (x - c)`` with ``c`` the vertex centroid, ``R`` an optional rotation
that makes the input's up axis the workflow's +y, and ``s = 1 / max_i |R (x_i - c)|``. The
inverse, ``x = R^T x_n / s + c``, is written as JSON so exports can return to the input's units.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config.sections import NormalizeSettings
from .meshio import TriMesh, load_mesh

#: rotation taking the named input up axis to +y (right-handed, proper rotations); keyed by
#: :data:`stages.config.sections.UP_AXES` (tested)
UP_AXIS_ROTATIONS = {
    "+y": np.eye(3),
    "-y": np.diag([1.0, -1.0, -1.0]),
    "+z": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
    "-z": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
    "+x": np.array([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]]),
    "-x": np.array([[0, 1.0, 0], [-1.0, 0, 0], [0, 0, 1.0]]),
}


@dataclass(frozen=True)
class Similarity:
    """``x_n = scale * rotation @ (x - centroid)``; all float64."""

    centroid: np.ndarray  # (3,)
    scale: float
    rotation: np.ndarray  # (3, 3)

    def forward(self, x: np.ndarray) -> np.ndarray:
        """Original units -> normalised frame; ``x (..., 3)``."""
        return self.scale * (np.asarray(x, np.float64) - self.centroid) @ self.rotation.T

    def inverse(self, x: np.ndarray) -> np.ndarray:
        """Normalised frame -> original units; ``x (..., 3)``."""
        return (np.asarray(x, np.float64) @ self.rotation) / self.scale + self.centroid

    def inverse_matrix(self) -> np.ndarray:
        """``(4, 4)`` homogeneous matrix of :meth:`inverse` (column vectors)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.T / self.scale
        m[:3, 3] = self.centroid
        return m

    def forward_matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = -self.scale * self.rotation @ self.centroid
        return m

    def to_json(self) -> dict:
        return {
            "convention": "x_normalized = scale * rotation @ (x_original - centroid); "
            "x_original = inverse_matrix @ [x_normalized, 1] (column vectors)",
            "centroid": self.centroid.tolist(),
            "scale": self.scale,
            "rotation": self.rotation.tolist(),
            "forward_matrix": self.forward_matrix().tolist(),
            "inverse_matrix": self.inverse_matrix().tolist(),
        }

    @classmethod
    def from_json(cls, data: dict) -> Similarity:
        return cls(np.array(data["centroid"], np.float64), float(data["scale"]), np.array(data["rotation"]))


def normalization_transform(vertices: np.ndarray, up_axis: str = "+y") -> Similarity:
    """The similarity that puts ``vertices (V, 3)`` at centroid 0 with farthest vertex at 1."""
    v = np.asarray(vertices, np.float64)
    centroid = v.mean(axis=0)
    rotation = UP_AXIS_ROTATIONS[up_axis]
    radius = float(np.linalg.norm(v - centroid, axis=1).max())
    return Similarity(centroid, 1.0 / radius, rotation)


@dataclass(frozen=True)
class NormalizeResult:
    mesh: TriMesh
    transform: Similarity
    stats: dict


def normalize_mesh(source: str | Path, settings: NormalizeSettings) -> NormalizeResult:
    """Load ``source`` (a path or ``builtin:<name>``) and normalise it into the unit sphere."""
    mesh = load_mesh(source)
    tf = normalization_transform(mesh.vertices, settings.up_axis)
    v = tf.forward(mesh.vertices)
    out = TriMesh(v, mesh.faces)
    areas = out.face_areas
    stats = {
        "vertices": int(len(v)),
        "faces": int(len(mesh.faces)),
        "degenerate_faces": int((areas <= 1e-14).sum()),
        "original_bounds": [mesh.vertices.min(0).tolist(), mesh.vertices.max(0).tolist()],
        "original_radius": float(1.0 / tf.scale),
        "centroid_after": v.mean(0).tolist(),
        "radius_after": float(np.linalg.norm(v, axis=1).max()),
    }
    stats.update(_topology_stats(mesh.faces))
    return NormalizeResult(out, tf, stats)


def _topology_stats(faces: np.ndarray) -> dict:
    """Edge counts: boundary (1 face), manifold (2), non-manifold (>2); duplicate faces."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    dup = len(faces) - len(np.unique(np.sort(faces, axis=1), axis=0))
    n = max(len(counts), 1)
    return {
        "edges": int(len(counts)),
        "boundary_edges_fraction": float((counts == 1).sum() / n),
        "non_manifold_edges_fraction": float((counts > 2).sum() / n),
        "duplicate_faces": int(dup),
    }
