"""First-hit ray queries against a triangle mesh: Embree (embreex) and trimesh's pure-Python
tracer (a reference for tests on tiny inputs)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .meshio import TriMesh


@dataclass(frozen=True)
class Hits:
    """First hits of one batch of rays: ``face (N,) int32`` (-1 = miss), ``bary (N, 2) float32``,
    ``depth (N,) float32`` (ray parameter ``t`` for unit directions; inf on a miss)."""

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray


class EmbreeTracer:
    """First-hit queries against a triangle mesh through embreex (Embree 4)."""

    def __init__(self, mesh: TriMesh) -> None:
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as exc:  # pragma: no cover
            raise ImportError("the raycache stage needs embreex: pip install embreex") from exc
        self._scene = rtcore_scene.EmbreeScene()
        triangles = np.ascontiguousarray(mesh.vertices[mesh.faces], dtype=np.float32)
        self._geometry = TriangleMesh(self._scene, triangles)  # keep a reference alive

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """``origins, directions (N, 3)``; directions need not be unit (depth is then ``t``)."""
        out = self._scene.run(
            np.ascontiguousarray(origins, dtype=np.float32),
            np.ascontiguousarray(directions, dtype=np.float32),
            output=1,
        )
        face = out["primID"].astype(np.int32, copy=False)
        bary = np.stack([out["u"], out["v"]], axis=1)
        depth = np.where(face >= 0, out["tfar"], np.inf).astype(np.float32)
        return Hits(face, bary, depth)


class TrimeshTracer:
    """trimesh's pure-Python tracer (about 400 rays/s): a reference for tests on tiny inputs."""

    def __init__(self, mesh: TriMesh) -> None:
        import trimesh
        from trimesh.ray.ray_triangle import RayMeshIntersector

        self._mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        self._rmi = RayMeshIntersector(self._mesh)

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        origins = np.asarray(origins, np.float64)
        directions = np.asarray(directions, np.float64)
        n = len(origins)
        face = np.full(n, -1, np.int32)
        bary = np.zeros((n, 2), np.float32)
        depth = np.full(n, np.inf, np.float32)
        tri_idx, ray_idx, loc = self._rmi.intersects_id(origins, directions, multiple_hits=True, return_locations=True)
        if len(ray_idx):
            t = np.einsum("ij,ij->i", loc - origins[ray_idx], directions[ray_idx]) / np.einsum(
                "ij,ij->i", directions[ray_idx], directions[ray_idx]
            )
            order = np.lexsort((t, ray_idx))
            first = order[np.r_[True, ray_idx[order][1:] != ray_idx[order][:-1]]]
            r, f = ray_idx[first], tri_idx[first]
            face[r] = f
            depth[r] = t[first]
            tri = self._mesh.vertices[self._mesh.faces[f]]
            e1, e2, p = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], loc[first] - tri[:, 0]
            d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
            p1, p2 = (p * e1).sum(1), (p * e2).sum(1)
            den = d11 * d22 - d12 * d12
            bary[r, 0] = (d22 * p1 - d12 * p2) / den
            bary[r, 1] = (d11 * p2 - d12 * p1) / den
        return Hits(face, bary, depth)


def make_tracer(mesh: TriMesh, backend: str = "embree"):
    return EmbreeTracer(mesh) if backend == "embree" else TrimeshTracer(mesh)
