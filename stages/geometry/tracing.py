"""First-hit and any-hit ray queries against a triangle mesh: Embree (embreex) and trimesh's
pure-Python tracer (a reference for tests on tiny inputs).

Embree's calls release the GIL, so :class:`EmbreeTracer` splits a large batch over
:func:`~stages.core.threads.cpu_threads` threads (each ray is traced on its own: the results do
not depend on the split); the stages set the count from their ``--threads``."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..core.threads import cpu_threads
from .meshio import TriMesh

#: the fewest rays a thread is given: below it a batch is traced in the calling thread
RAYS_PER_THREAD = 1 << 15


def _split(count: int, threads: int | None = None) -> list[slice]:
    """``count`` rays in at most ``threads`` (default :func:`~stages.core.threads.cpu_threads`)
    contiguous slices of at least :data:`RAYS_PER_THREAD` rays (one slice for a small batch)."""
    parts = max(1, min(threads or cpu_threads(), count // RAYS_PER_THREAD))
    bounds = np.linspace(0, count, parts + 1).astype(np.int64)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


@dataclass(frozen=True)
class Hits:
    """First hits of one batch of rays: ``face (N,) int32`` (-1 = miss), ``bary (N, 2) float32``,
    ``depth (N,) float32`` (ray parameter ``t`` for unit directions; inf on a miss)."""

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray


class EmbreeTracer:
    """First-hit and any-hit queries against a triangle mesh through embreex (Embree 4)."""

    #: queries may come from several threads at once (Embree's scenes are read-only once built)
    concurrent = True

    def __init__(self, mesh: TriMesh) -> None:
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as exc:  # pragma: no cover
            raise ImportError("the raycache stage needs embreex: pip install embreex") from exc
        self._scene = rtcore_scene.EmbreeScene()
        triangles = np.ascontiguousarray(mesh.vertices[mesh.faces], dtype=np.float32)
        self._geometry = TriangleMesh(self._scene, triangles)  # keep a reference alive
        # embreex builds the BVH at the first query: made here, once, so that concurrent first
        # queries do not both build it
        self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="OCCLUDED")

    def _run(self, origins: np.ndarray, directions: np.ndarray, threads: int | None = None, **query) -> list:
        """embreex's ``run`` over the batch's slices (:func:`_split` into ``threads``), in threads
        when more than one."""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        parts = _split(len(o), threads)
        if len(parts) == 1:
            return [self._scene.run(o, d, **query)]
        with ThreadPoolExecutor(len(parts)) as pool:
            return list(pool.map(lambda s: self._scene.run(o[s], d[s], **query), parts))

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """The first hits of rays ``origins, directions (N, 3)``; directions need not be unit
        (depth is then ``t``)."""
        parts = self._run(origins, directions, output=1)
        face = np.concatenate([p["primID"] for p in parts]).astype(np.int32, copy=False)
        bary = np.concatenate([np.stack([p["u"], p["v"]], axis=1) for p in parts]).reshape(-1, 2)
        tfar = np.concatenate([p["tfar"] for p in parts])
        depth = np.where(face >= 0, tfar, np.inf).astype(np.float32)
        return Hits(face, bary, depth)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, threads: int | None = None) -> np.ndarray:
        """Whether each ray ``origins, directions (N, 3)`` meets the mesh at all -> ``(N,) bool``:
        Embree's any-hit query (it stops at the first triangle found, not the nearest), the same
        answer as ``trace(...).face >= 0``; on up to ``threads`` threads (default
        :func:`~stages.core.threads.cpu_threads`)."""
        parts = self._run(origins, directions, threads, query="OCCLUDED")
        return np.concatenate([np.asarray(p) for p in parts]) != -1


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

    def occluded(self, origins: np.ndarray, directions: np.ndarray, threads: int | None = None) -> np.ndarray:
        """Whether each ray meets the mesh -> ``(N,) bool`` (from :meth:`trace`; one thread, whatever
        ``threads`` says)."""
        return self.trace(origins, directions).face >= 0


def make_tracer(mesh: TriMesh, backend: str = "embree"):
    return EmbreeTracer(mesh) if backend == "embree" else TrimeshTracer(mesh)
