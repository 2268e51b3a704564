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


#: the senders a refresh shades at once
SENDER_CHUNK = 16384


def field_shading(field, senders: FaceSides, device) -> Callable[[Light, Callable], Shading]:
    """The senders' shading by ``field`` (its networks at their centroids and flat normals, seen
    along the normal, on ``device``), in pieces of :data:`SENDER_CHUNK`: what
    :func:`bounce_table` takes."""
    points = torch.from_numpy(senders.points).float().to(device)
    normals = torch.from_numpy(senders.normals).float().to(device)

    def shade(light: Light, visibility: Callable) -> Shading:
        inputs = visibility(light)
        parts = []
        for lo in range(0, len(points), SENDER_CHUNK):
            part = slice(lo, lo + SENDER_CHUNK)
            vis = None if inputs is None else tuple(None if v is None else v[part].to(device) for v in inputs)
            out = field(points[part], normals[part], normals[part], light, None, visibility=lambda _, vis=vis: vis)
            parts.append(out.shading)
        return Shading(torch.cat([p.diffuse for p in parts]), torch.cat([p.specular for p in parts]))

    return shade


@torch.no_grad()
def field_surface(field, senders: FaceSides, device) -> dict[str, np.ndarray]:
    """``field``'s surface at the senders (its networks at their centroids and flat normals, seen
    along the flat normal, as :func:`field_shading` runs them), rows in ``senders``' order: the
    material's parameters and the unit shading ``normal``, as arrays (what a shading of a known
    surface takes, :func:`~stages.imaging.relit.surface_shading`)."""
    points = torch.from_numpy(senders.points).float().to(device)
    normals = torch.from_numpy(senders.normals).float().to(device)
    parts: dict[str, list] = {}
    for lo in range(0, len(points), SENDER_CHUNK):
        part = slice(lo, lo + SENDER_CHUNK)
        material, normal = field.surface(points[part], normals[part], normals[part])
        for k, x in {**material.parameters(), "normal": normal}.items():
            parts.setdefault(k, []).append(x.float().cpu())
    return {k: torch.cat(x).numpy() for k, x in parts.items()}


def bounce_samples(field) -> int | None:
    """The first hits per point of ``field``'s bounce (its light's ``bounce`` component), None
    where it models none."""
    light = getattr(field, "light", None)
    module = dict(light.named_children()).get(BounceLight.kind) if isinstance(light, torch.nn.Module) else None
    return None if module is None else int(module.samples)


def blocked_median(views) -> float | None:
    """The median over every hit of ``views`` (a :class:`~stages.imaging.views.ViewStore`-like
    sequence of views with shadows) of the share of its hemisphere the mesh blocks, or None
    without shadows."""
    shares = []
    for i in range(len(views)):
        shadows = views[i].shadows
        if shadows is None:
            return None
        shares.append(shadows.blocked_share())
    return float(np.median(np.concatenate(shares))) if shares else 0.0


def resolve_bounces(setting: int | str, views, needed: float) -> tuple[int, dict]:
    """``optimize.bounces`` as a count (0 or 1) and the record of how it was decided: a number as
    it is (1 needs the views' shadows: the ray cache's visibility and ``optimize.shadows``);
    ``auto`` by :func:`blocked_median` of the training ``views`` against ``needed``
    (``bounce_auto_median``), 0 without shadows.

    Raises:
        ValueError: 1 asked for where the views have no shadows (what to do, in the message)."""
    median = blocked_median(views) if setting != 0 else None
    if setting != "auto":
        if int(setting) and median is None:
            raise ValueError(
                "optimize.bounces: 1 needs shadows: set optimize.shadows: true and raycache.visibility: on "
                "(or bounces: auto, which models none without them)"
            )
        return int(setting), {"setting": int(setting), "bounces": int(setting), "blocked_median": median}
    if median is None:
        return 0, {"setting": "auto", "bounces": 0, "why": "no shadows (the ray cache has no visibility, or shadows: false)"}
    count = int(median >= needed)
    why = f"the median blocked share of the hemisphere over the training hits {median:.3f} {'>=' if count else '<'} {needed}"
    return count, {"setting": "auto", "bounces": count, "blocked_median": median, "needed": needed, "why": why}


def with_bounce(light: Light, bounce: BounceLight) -> Light:
    """``light`` with ``bounce`` in place of any bounce it had (added last)."""
    return Light((*(c for c in light.components if c.kind != BounceLight.kind), bounce))


__all__ = [
    "FaceSides",
    "blocked_median",
    "bounce_samples",
    "bounce_table",
    "field_shading",
    "field_surface",
    "resolve_bounces",
    "with_bounce",
]
