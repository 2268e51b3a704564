"""Cached views on the device, and images rendered from them through the field."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from ..config.layout import RENDER_KINDS
from ..geometry.normals import NormalSpec
from ..geometry.raycache import RayCache
from ..geometry.tracing import EmbreeTracer
from ..geometry.visibility import viewer_side_normals
from ..model.bounce import FaceSides, bounce_samples, bounce_table, field_shading, with_bounce
from ..model.compiled import CompiledField
from ..model.field import FieldOutput, StyleField
from ..model.shadows import ShadowCache
from ..render.color import linear_to_srgb
from ..render.light import Light
from ..render.shading import face_viewer
from .images import compose, gather_points, global_spec, index_map, render_cached_view, summed_area
from .targets import TargetSet


@dataclass
class CachedView:
    """Tensors of one cached view on the device: hit ``points``, shading ``normals`` (flat or
    smooth, turned to the side of the face the viewer sees) and unit ``view`` directions
    (surface -> eye) ``(N, 3)``, plus the ``(W, W)`` hit-index map."""

    points: torch.Tensor
    normals: torch.Tensor
    view: torch.Tensor
    index: np.ndarray
    #: image targets at the hits (linear radiance ``(N, 3)``, coverage ``(N,)``), when given
    target: torch.Tensor | None = None
    coverage: torch.Tensor | None = None
    #: the hits' shadows (each light lobe's visible share), when the field casts them and the
    #: cache holds their visibility
    shadows: ShadowCache | None = None

    @functools.cached_property
    def mask_sums(self) -> np.ndarray:
        """The summed-area table ``(W + 1, W + 1)`` of the view's mask (its hit pixels), which the
        crops' coverage reads (:func:`~stages.imaging.images.summed_area`): built at the first
        crops, once (training's views), not by stages that draw none."""
        return summed_area(self.index >= 0)

    def shade(self, field: StyleField | CompiledField, sel: torch.Tensor | None = None, light=None, edit=None) -> FieldOutput:
        """The field's forward pass at the hits ``sel`` (all when None), with this view's shadows
        (training's through its :class:`~stages.model.compiled.CompiledField`)."""
        if sel is None:
            pts, nrm, view = self.points, self.normals, self.view
        else:
            pts, nrm, view = self.points[sel], self.normals[sel], self.view[sel]
        shadows = self.shadows
        visibility = None if shadows is None else (lambda lt: lt.shadowed_by(shadows, sel))
        return field(pts, nrm, view, light, edit, visibility=visibility)


class ViewStore:
    """The views of one :class:`~stages.geometry.raycache.RayCache` as :class:`CachedView`, built
    on first use and kept on ``device``, shaded with the ``normals`` a field was trained with
    (:attr:`~stages.model.field.StyleField.normals`), with the image targets of a
    :class:`~stages.imaging.targets.TargetSet` attached when one is given.

    Normals are oriented by the *face* the viewer sees (two-sided surfaces: the inside of an open
    vase), then a smooth normal that still faces away from the eye (near a silhouette, where it
    leans past the face) is bent just into view (:func:`~stages.render.shading.face_viewer`),
    as renderers with shading normals do."""

    def __init__(
        self, cache: RayCache, device, normals: NormalSpec, targets: TargetSet | None = None, shadows: bool = False
    ) -> None:
        """``shadows``: attach each view's :class:`~stages.model.shadows.ShadowCache` when the cache
        holds visibility (for a field that casts shadows: :attr:`StyleField.shadows`)."""
        self.cache = cache
        self.device = device
        self.normals = normals
        self.targets = targets
        self.shadows = shadows and cache.visibility_directions > 0
        self._tracer = None
        self._views: dict[int, CachedView] = {}

    def __len__(self) -> int:
        return len(self.cache)

    @property
    def largest(self) -> int:
        """The most hits any view holds: the most points a step shades per view."""
        return int(np.diff(self.cache.arrays["offsets"]).max(initial=0))

    @property
    def width(self) -> int:
        return self.cache.width

    def global_points(self, out_size: int, supersample: int = 1, view: int = 0) -> int:
        """The points ``view``'s global image of ``out_size`` pixels (``supersample`` rays each)
        gathers: about as many as a step's call of the field shades (its crops add some)."""
        return len(gather_points([global_spec(self.width, out_size, supersample)], self[view].index)[0])

    def azimuths(self) -> np.ndarray:
        """Distinct azimuths of a grid of views (contact sheets of it have one column each)."""
        return np.unique(np.round(self.cache.arrays["azimuth"], 9))

    def __getitem__(self, i: int) -> CachedView:
        if i not in self._views:
            h = self.cache.view(i, self.normals)
            idx = index_map(h.pixel, self.cache.width)
            view = torch.from_numpy(-h.direction).to(self.device)
            back = (torch.from_numpy(h.face_normal).to(self.device) * view).sum(-1, keepdim=True) < 0
            shading = torch.from_numpy(h.normal).to(self.device)
            normals = face_viewer(torch.where(back, -shading, shading), view)
            target = coverage = None
            if self.targets is not None:
                target = torch.from_numpy(self.targets.view(i)).to(self.device)
                coverage = torch.from_numpy(self.targets.view(i, "coverage")).to(self.device)
            self._views[i] = CachedView(
                torch.from_numpy(h.point).to(self.device),
                normals,
                view,
                idx,
                target,
                coverage,
                self._shadows(i, h) if self.shadows else None,
            )
        return self._views[i]

    @functools.cached_property
    def senders(self) -> FaceSides:
        """The face sides of the cache's mesh as the senders of a bounce
        (:class:`~stages.model.bounce.FaceSides`, their visibility of the cache's directions), built
        at the first use."""
        if self._tracer is None:
            self._tracer = EmbreeTracer(self.cache.mesh())
        return FaceSides(self.cache.mesh(), self.cache.visibility_directions, self._tracer)

    def light_of(self, field, light: Light) -> Light:
        """``light`` with ``field``'s transport on these views: where the field models a bounce, its
        table refreshed under ``light`` (:func:`~stages.model.bounce.bounce_table` of the field's
        material at :attr:`senders`), so that a relit render bounces as training did; else
        ``light`` as it is."""
        samples = bounce_samples(field)
        if samples is None or not self.shadows:
            return light
        device = next(field.parameters()).device
        table = bounce_table(self.senders, field_shading(field, self.senders, device), light, samples)
        return with_bounce(light, table)

    def _shadows(self, i: int, h) -> ShadowCache:
        mesh = self.cache.mesh()
        if self._tracer is None:
            self._tracer = EmbreeTracer(mesh)
        oriented = viewer_side_normals(h.face_normal, h.direction)
        directions = self.cache.visibility_directions
        # the quadrature for every lobe (samples 0): see ShadowCache
        return ShadowCache(mesh, h.point, oriented, self._tracer, directions, samples=0, bits=self.cache.visibility(i))


@torch.no_grad()
def render_view(field: StyleField, v: CachedView, width: int, out_width: int, chunk: int = 65536) -> dict:
    """All render kinds of one cached view at ``out_width`` (nearest sampling), black background.
    Returns ``{kind: (3, out, out)}`` in display space (sRGB for radiance, [0, 1] for data)."""
    spec = global_spec(width, out_width)
    needed, (lookup,) = gather_points([spec], v.index)
    sel = torch.from_numpy(needed).to(v.points.device)
    outs = {k: [] for k in RENDER_KINDS}
    for lo in range(0, len(sel), chunk):
        idx = sel[lo : lo + chunk]
        pts, nrm, view = v.points[idx], v.normals[idx], v.view[idx]
        o = v.shade(field, idx)
        outs["rgb"].append(linear_to_srgb(o.shading.rgb))
        outs["diffuse"].append(linear_to_srgb(o.shading.diffuse))
        outs["specular"].append(linear_to_srgb(o.shading.specular))
        r = o.material.roughness if o.material.roughness is not None else torch.ones_like(pts[:, :1])
        outs["roughness"].append(r.expand(-1, 3))
        outs["normal"].append(0.5 + 0.5 * o.normal)
        flip = (nrm * view).sum(-1, keepdim=True) < 0
        outs["normal_original"].append(0.5 + 0.5 * torch.where(flip, -nrm, nrm))
    bg = torch.zeros(3, out_width, out_width, device=v.points.device)
    empty = torch.zeros(0, 3, device=v.points.device)
    return {k: compose(torch.cat(c) if c else empty, lookup, spec, bg) for k, c in outs.items()}


@torch.no_grad()
def render_views(field, store, background: str) -> torch.Tensor:
    """Every view of ``store`` rendered through the field at the cache's resolution: ``(V, 3, S, S)`` sRGB in [0, 1]."""

    def colors(v, sel):
        return linear_to_srgb(v.shade(field, sel).shading.rgb)

    bg = 1.0 if background == "white" else 0.0
    return torch.stack([render_cached_view(store[i], store.width, store.width, colors, bg) for i in range(len(store))])


@torch.no_grad()
def radiance_at_hits(field, store: ViewStore) -> list[torch.Tensor]:
    """The field's linear radiance at every hit of every view of ``store``: per view ``(N, 3)``, in
    the ray cache's hit order (the reference that baked renders are compared with)."""
    return [store[i].shade(field).shading.rgb for i in range(len(store))]
