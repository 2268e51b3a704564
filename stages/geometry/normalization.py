"""Normalisation into the unit sphere (TANGO Sec. 3.1) and its inverse transform.

The vertex centroid moves to the origin and the mesh is scaled so that its farthest vertex lies
at distance 1: ``x_n = s * R (x - c)`` with ``c`` the vertex centroid, ``R`` an optional rotation
that makes the input's up axis the workflow's +y, and ``s = 1 / max_i |R (x_i - c)|``. The
inverse, ``x = R^T x_n / s + c``, is written as JSON so exports can return to the input's units.

The up axis is the setting's, or with ``up_axis: auto`` (:func:`resolve_up_axis`): the file
format's convention where it has one (glTF 2.0 specifies +Y up; the built-in shapes are modelled
+Y up), else a guess (:func:`guess_up_axis`) from how the object would rest: for each signed
coordinate axis, the flat base its convex hull offers at the bottom (hull facets within
``BASE_TOLERANCE_DEG`` of facing straight down, as a fraction of the hull's area seen from above)
and whether the surface's centre of mass lies over that base. The largest stable base wins; +y,
the de facto convention of OBJ and PLY files, is kept unless another base is clearly larger
(``PREFER_Y``). The surface's principal axes are reported beside it. It is a guess: an object
with no flat base, or one that rests as well on its top (a lamp whose shades reach a common
plane), can fool it, so the metadata records the candidates and the margin, and a setting
(``normalize.up_axis``, per mesh) overrides it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config.sections import NormalizeSettings
from ..core.errors import StageInputError
from .meshio import TriMesh, load_mesh

log = logging.getLogger(__name__)

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


#: hull facets within this angle of facing straight down form an axis's base
BASE_TOLERANCE_DEG = 3.0
#: a base smaller than this fraction of the hull's area seen along the axis is no base
MIN_BASE_FRACTION = 0.05
#: +y is kept when its base is at least this fraction of the best one
PREFER_Y = 0.75
#: the file formats whose specification fixes the up axis
FORMAT_UP_AXES = {".glb": ("+y", "glTF 2.0 specifies +Y up"), ".gltf": ("+y", "glTF 2.0 specifies +Y up")}


@dataclass(frozen=True)
class UpAxisChoice:
    """The up axis used, how it was chosen (``setting``, ``format convention``, ``built-in`` or
    ``guess``) and, for a guess, its evidence."""

    axis: str
    method: str
    reason: str
    evidence: dict

    def to_dict(self) -> dict:
        return {"axis": self.axis, "method": self.method, "reason": self.reason, **self.evidence}


def guess_up_axis(mesh: TriMesh) -> tuple[str, dict]:
    """Guess the up axis of ``mesh`` among the six signed coordinate axes (module docstring).
    Returns the axis and the evidence: per axis the base fraction and stability, the margin of
    the winner over the runner-up, and the surface's principal axes."""
    from scipy.spatial import ConvexHull, Delaunay, QhullError

    v = np.asarray(mesh.vertices, np.float64)
    tri = v[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = max(float(area.sum()), 1e-300)
    centre = (tri.mean(1) * area[:, None]).sum(0) / total  # the surface's centre of mass
    d = tri.mean(1) - centre
    cov = (d * area[:, None]).T @ d / total
    eigval, eigvec = np.linalg.eigh(cov)
    principal = [
        {
            "extent_std": float(np.sqrt(max(lam, 0.0))),
            "nearest_axis": "xyz"[int(np.argmax(np.abs(e)))],
            "alignment": float(np.abs(e).max()),
        }
        for lam, e in zip(eigval[::-1], eigvec.T[::-1], strict=True)
    ]
    hull = ConvexHull(v)
    hn = hull.equations[:, :3]
    ht = v[hull.simplices]
    ha = 0.5 * np.linalg.norm(np.cross(ht[:, 1] - ht[:, 0], ht[:, 2] - ht[:, 0]), axis=1)
    cos_tol = np.cos(np.radians(BASE_TOLERANCE_DEG))
    candidates = {}
    for name, rot in UP_AXIS_ROTATIONS.items():
        up = rot.T @ np.array([0.0, 1.0, 0.0])  # the input direction this choice turns into +y
        base = hn @ -up >= cos_tol
        seen = float((ha * np.abs(hn @ up)).sum() / 2.0)
        fraction = float(ha[base].sum() / max(seen, 1e-300))
        stable = False
        if fraction >= MIN_BASE_FRACTION:
            # the centre of mass over the base: inside the base's outline, projected along up
            e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(up, e1)
            pts = ht[base].reshape(-1, 3)
            flat = np.stack([pts @ e1, pts @ e2], 1)
            try:
                stable = bool(Delaunay(flat).find_simplex(np.array([[centre @ e1, centre @ e2]]))[0] >= 0)
            except QhullError:
                stable = False
        candidates[name] = {"base_fraction": round(fraction, 4), "stable": stable}
    ranked = sorted((c["base_fraction"], n) for n, c in candidates.items() if c["stable"])[::-1]
    if not ranked:
        axis, margin = "+y", None
    else:
        best, axis = ranked[0]
        y = candidates["+y"]
        if axis != "+y" and y["stable"] and y["base_fraction"] >= PREFER_Y * best:
            axis = "+y"
        others = [f for f, n in ranked if n != axis]
        margin = round(candidates[axis]["base_fraction"] / others[0], 3) if others and others[0] > 0 else None
    return axis, {"candidates": candidates, "margin": margin, "principal_axes": principal}


def resolve_up_axis(setting: str, source: str | Path, mesh: TriMesh) -> UpAxisChoice:
    """The up axis of ``mesh`` read from ``source``: the setting, or for ``auto`` the format's
    convention or a guess (module docstring)."""
    if setting != "auto":
        return UpAxisChoice(setting, "setting", "normalize.up_axis", {})
    if str(source).startswith("builtin:"):
        return UpAxisChoice("+y", "built-in", "the built-in shapes are modelled +Y up", {})
    suffix = Path(str(source)).suffix.lower()
    if suffix in FORMAT_UP_AXES:
        axis, why = FORMAT_UP_AXES[suffix]
        return UpAxisChoice(axis, "format convention", why, {})
    axis, evidence = guess_up_axis(mesh)
    why = f"{suffix or 'this'} files fix no up axis: guessed from the convex hull's flat base and the centre of mass"
    return UpAxisChoice(axis, "guess", why, evidence)


@dataclass(frozen=True)
class NormalizeResult:
    mesh: TriMesh
    transform: Similarity
    stats: dict


def check_face_count(source: str | Path, mesh: TriMesh, settings: NormalizeSettings) -> None:
    """Refuse a mesh above ``normalize.max_faces`` (what the normalize stage and the quick command
    both check), naming it and what to do."""
    if len(mesh.faces) > settings.max_faces:
        raise StageInputError(
            source,
            f"has {len(mesh.faces):,} faces, more than normalize.max_faces ({settings.max_faces:,})",
            "Decimate it first (MeshLab, Blender), or, on a machine with the memory, raise normalize.max_faces "
            "for this mesh and turn on decimate: {enabled: true, mode: budget}, which brings it to the face "
            "budget of its ray cache.",
        )


def normalize_mesh(source: str | Path, settings: NormalizeSettings) -> NormalizeResult:
    """Load ``source`` (a path or ``builtin:<name>``) and normalise it into the unit sphere."""
    mesh = load_mesh(source)
    check_face_count(source, mesh, settings)
    up = resolve_up_axis(settings.up_axis, source, mesh)
    if up.method == "guess":
        log.info("%s: up axis %s (%s; margin %s)", source, up.axis, up.reason, up.evidence["margin"])
    tf = normalization_transform(mesh.vertices, up.axis)
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
        "up_axis": up.to_dict(),
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
