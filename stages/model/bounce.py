"""Where the mesh's own light comes from: each face side as a sender of one bounce
(:mod:`stages.render.light.bounce`).

A face side sends the diffuse radiance its centroid reflects of the direct light (the light's
other components, shadowed as the side sees them): :class:`FaceSides` holds the centroids of
every face's two sides (row ``2 f`` the front, ``2 f + 1`` the back, as the bounce's table), their
flat normals and their own :class:`~stages.model.shadows.ShadowCache` (the visibility of the same
direction set as the views', traced once), and :func:`bounce_table` turns the senders' shading
into the table (a degenerate face sends nothing).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

from ..geometry.meshio import TriMesh
from ..geometry.tracing import EmbreeTracer
from ..render.light import Light
from ..render.light.bounce import BounceLight
from ..render.shading import Shading
from .shadows import ShadowCache


class FaceSides:
    """The senders of ``mesh``: the centroid, flat normal (turned to the side) and face of each
    face side that has an area (``rows``: their rows in the table, ``2 f`` front and ``2 f + 1``
    back), with their shadows over ``directions`` stored directions (through ``tracer``, or one
    made for the mesh)."""

    def __init__(self, mesh: TriMesh, directions: int, tracer=None) -> None:
        t0 = time.perf_counter()
        n = mesh.face_normals
        ok = np.flatnonzero(np.linalg.norm(n, axis=1) > 0.5)
        self.sides = 2 * len(mesh.faces)
        self.rows = np.stack([2 * ok, 2 * ok + 1], axis=1).reshape(-1)
        self.face = self.rows // 2
        self.back = (self.rows % 2).astype(bool)
        self.points = mesh.vertices[mesh.faces[self.face]].mean(axis=1)
        self.normals = np.where(self.back[:, None], -n[self.face], n[self.face])
        self.shadows = ShadowCache(mesh, self.points, self.normals, tracer or EmbreeTracer(mesh), directions, samples=0)
        #: seconds the senders' visibility took
        self.seconds = time.perf_counter() - t0

    def __len__(self) -> int:
        return len(self.rows)


def bounce_table(senders: FaceSides, shade: Callable[[Light, Callable], Shading], light: Light, samples: int) -> BounceLight:
    """The bounce of ``light`` (its components other than a bounce: one bounce, not more) off the
    ``senders``: ``shade(direct, visibility)`` is the senders' shading (rows in ``senders``' order)
    under the light ``direct`` with ``visibility`` (a light -> its visibility inputs at the
    senders: :meth:`~stages.render.light.Light.shadowed_by` of their shadows); its diffuse
    radiance goes into the table's rows of the senders, zero elsewhere; ``samples`` directions per
    receiving point. No gradient (a table is refreshed, not learned through)."""
    direct = Light(tuple(c for c in light.components if c.kind != BounceLight.kind))
    with torch.no_grad():
        out = shade(direct, lambda lt: lt.shadowed_by(senders.shadows, None)).diffuse
    table = torch.zeros(senders.sides, out.shape[-1], dtype=out.dtype, device=out.device)
    table[torch.from_numpy(senders.rows).to(out.device)] = out
    return BounceLight(table, samples)


def with_bounce(light: Light, bounce: BounceLight) -> Light:
    """``light`` with ``bounce`` in place of any bounce it had (added last)."""
    return Light((*(c for c in light.components if c.kind != BounceLight.kind), bounce))


__all__ = ["FaceSides", "bounce_table", "with_bounce"]
