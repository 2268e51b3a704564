"""Shadows for a fixed set of surface points: their visibility of a direction set, traced once,
and each light lobe's visible share at any subset of them (issue 32).

Broad lobes take the quadrature of the stored directions
(:func:`~stages.render.visibility.lobe_visibility_bits`: differentiable in the lobe's axis and
sharpness); lobes too sharp for the set (a sun) take shadow rays drawn from the lobe with fixed
seeds (:func:`~stages.geometry.visibility.trace_lobe_visibility`), traced lazily for the points
asked for and traced again once the lobe's axis has moved by more than ``tolerance`` of its width
``1 / sqrt(lam)`` or its sharpness by more than a factor ``2 ** tolerance``; between the two, a
blend continuous in the sharpness (:func:`~stages.render.visibility.blend_traced`).
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import Tensor

from ..geometry.visibility import (
    blocked_share,
    fibonacci_directions,
    sample_lobe_directions,
    surface_offset,
    trace_lobe_visibility,
    trace_visibility,
    unpack_visibility,
)
from ..render.light.bounce import BounceLight, cosine_directions, face_side, indirect_irradiance
from ..render.light.sun import SunLight, solid_angle
from ..render.shading import SGLight
from ..render.visibility import blend_traced, lobe_visibility_bits, resolvable_sharpness


class _TracedLobe:
    """One sharp lobe's traced shares at every point, valid where traced since the lobe last
    moved by more than the tolerance."""

    def __init__(self, count: int) -> None:
        self.axis = np.zeros(3)
        self.sharpness = 0.0
        self.values = np.ones(count, np.float32)
        self.valid = np.zeros(count, bool)
        self.traces = 0

    def stale(self, axis: np.ndarray, sharpness: float, tolerance: float) -> bool:
        if self.sharpness <= 0.0:
            return True
        angle = math.acos(float(np.clip(axis @ self.axis, -1.0, 1.0)))
        return angle > tolerance / math.sqrt(sharpness) or abs(math.log2(sharpness / self.sharpness)) > tolerance


class _TracedSun:
    """The suns' directions' visibility at every point (one shadow ray each), valid where traced
    since the directions last moved by more than the tolerance."""

    def __init__(self, count: int, rays: int) -> None:
        self.directions = np.zeros((rays, 3))
        self.values = np.ones((count, rays), np.float32)
        self.valid = np.zeros(count, bool)
        self.traces = 0

    def stale(self, directions: np.ndarray, allowed: float) -> bool:
        if directions.shape != self.directions.shape or not self.directions.any():
            return True
        cos = np.clip((directions * self.directions).sum(-1), -1.0, 1.0)
        return float(np.arccos(cos).max()) > allowed


class _TracedBounce:
    """The face side each point's bounce directions meet first (``sides (N, K)``, -1 a miss),
    valid where traced; each point's lattice shift drawn once from the cache's seed."""

    def __init__(self, count: int, samples: int, seed: int) -> None:
        self.samples = samples
        self.sides = np.full((count, samples), -1, np.int64)
        self.valid = np.zeros(count, bool)
        self.shift = np.random.default_rng(seed).random((count, 2))
        self.traces = 0


class ShadowCache:
    """Visibility of ``directions`` directions from ``points (N, 3)`` with ``normals (N, 3)``
    (unit, oriented to the side each point is seen from) on ``mesh``, traced once at
    construction, or ``bits`` already traced (a ray cache's ``visibility``, of ``directions``
    directions); :meth:`shares` gives each lobe's visible share. ``samples`` shadow rays per point
    for a sharp lobe, drawn with ``seed``; 0: the quadrature for every lobe (a sharp lobe then sees
    the stored directions nearest its axis: the training's path, where lobes move at every step and
    would be traced again at every step)."""

    def __init__(
        self,
        mesh,
        points: np.ndarray,
        normals: np.ndarray,
        tracer,
        directions: int = 1024,
        samples: int = 64,
        seed: int = 0,
        tolerance: float = 0.25,
        bits: np.ndarray | None = None,
    ) -> None:
        t0 = time.perf_counter()
        self.points = np.asarray(points, np.float64)
        self.normals = np.asarray(normals, np.float64)
        self.tracer = tracer
        self.offset = surface_offset(mesh.vertices)
        self.mesh = mesh
        self.directions = fibonacci_directions(directions)
        if bits is None:
            bits = trace_visibility(tracer, self.points, self.normals, self.directions, self.offset)
        elif bits.shape != (len(self.points), (directions + 7) // 8):
            raise ValueError(f"visibility bits of shape {bits.shape} for {len(self.points)} points and {directions} directions")
        self.bits = bits
        self.samples, self.seed, self.tolerance = samples, seed, tolerance
        self.resolvable = resolvable_sharpness(directions)
        self._lobes: dict[int, _TracedLobe] = {}
        self._sun: _TracedSun | None = None
        self._bounce: _TracedBounce | None = None
        self._face_normals: np.ndarray | None = None
        self._dirs = torch.from_numpy(self.directions).float()
        self._normals = torch.from_numpy(self.normals).float()
        self._bits = torch.from_numpy(self.bits)
        #: seconds the visibility took to trace
        self.seconds = time.perf_counter() - t0

    def __len__(self) -> int:
        return len(self.points)

    def quadrature(self, light: SGLight, index: Tensor | None = None) -> Tensor:
        """Each lobe's share by quadrature alone at the points ``index`` (all when None) -> ``(n, K)``."""
        dev, dtype = light.axis.device, light.axis.dtype
        idx = None if index is None else index.cpu()  # the stored bits stay on the CPU
        bits = (self._bits if idx is None else self._bits[idx]).to(dev)
        normal = (self._normals if idx is None else self._normals[idx]).to(dev, dtype)
        return lobe_visibility_bits(normal, bits, self._dirs.to(dev, dtype), light.axis, light.sharpness)

    def traced(self, light: SGLight, index: Tensor | None = None) -> Tensor:
        """Each lobe's share from shadow rays drawn from it -> ``(n, K)`` (no gradient): ones for the
        lobes the quadrature resolves, traced (lazily, see the module) for the sharper ones."""
        idx = np.arange(len(self)) if index is None else index.cpu().numpy()
        out = np.ones((len(idx), light.axis.shape[0]), np.float32)
        axes = light.axis.detach().double().cpu().numpy()
        sharp = light.sharpness.detach().double().cpu().numpy()[:, 0]
        for k in np.flatnonzero(sharp > self.resolvable):
            lobe = self._lobes.setdefault(int(k), _TracedLobe(len(self)))
            axis = axes[k] / np.linalg.norm(axes[k])
            if lobe.stale(axis, float(sharp[k]), self.tolerance):
                lobe.axis, lobe.sharpness, lobe.valid[:] = axis, float(sharp[k]), False
            todo = idx[~lobe.valid[idx]]
            if len(todo):
                rays = sample_lobe_directions(lobe.axis, lobe.sharpness, self.samples, self.seed + int(k))
                lobe.values[todo] = trace_lobe_visibility(self.tracer, self.points[todo], self.normals[todo], rays, self.offset)
                lobe.valid[todo] = True
                lobe.traces += len(todo)
            out[:, k] = lobe.values[idx]
        return torch.from_numpy(out).to(light.axis.device)

    def shares(self, light: SGLight, index: Tensor | None = None) -> Tensor:
        """Each lobe's visible share at the points ``index`` (all when None) -> ``(n, K)`` in [0, 1]:
        the quadrature for the lobes it resolves, shadow rays for sharper ones, blended between."""
        quad = self.quadrature(light, index)
        if self.samples == 0 or not bool((light.sharpness > self.resolvable).any()):
            return quad
        return blend_traced(quad, self.traced(light, index), light.sharpness, self.resolvable)

    def sun_shares(self, sun: SunLight, index: Tensor | None = None) -> Tensor:
        """Each sun direction's visibility at the points ``index`` (all when None) -> ``(n, S M)``
        in {0, 1} (no gradient: a shadow's edge moves no parameter): one shadow ray per point per
        direction of :meth:`~stages.render.light.sun.SunLight.directions`, traced lazily for the
        points asked for and traced again once a direction has moved by more than ``tolerance``
        of its cell's radius (``sqrt(Omega / (pi M))``, or 1e-3 radians where the disc is smaller),
        so that a sun that stays put (a known light) is traced once per point."""
        idx = np.arange(len(self)) if index is None else index.cpu().numpy()
        directions = sun.directions().detach().double().cpu().numpy().reshape(-1, 3)
        cell = float(solid_angle(sun.radius.detach().double()).max()) / (math.pi * sun.samples)
        allowed = self.tolerance * max(math.sqrt(cell), 1e-3)
        if self._sun is None or self._sun.stale(directions, allowed):
            self._sun = _TracedSun(len(self), len(directions))
            self._sun.directions = directions
        traced = self._sun
        todo = idx[~traced.valid[idx]]
        if len(todo):
            bits = trace_visibility(self.tracer, self.points[todo], self.normals[todo], traced.directions, self.offset)
            traced.values[todo] = unpack_visibility(bits, len(directions))
            traced.valid[todo] = True
            traced.traces += len(todo)
        return torch.from_numpy(traced.values[idx]).to(sun.direction.device)

    def bounce_irradiance(self, bounce: BounceLight, index: Tensor | None = None) -> Tensor:
        """Each point's indirect irradiance ``(n, C)`` from the mesh at the points ``index`` (all
        when None): :func:`~stages.render.light.bounce.indirect_irradiance` of the bounce's table at
        the face sides its ``samples`` cosine-distributed directions meet first, traced once per
        point (lazily, for the points asked for; a point's directions are fixed by the cache's
        seed). Differentiable in the table; a ray that leaves the mesh adds nothing."""
        idx = np.arange(len(self)) if index is None else index.cpu().numpy()
        table = bounce.table
        if len(table) == 0:  # not yet refreshed: no bounce
            return torch.zeros(len(idx), table.shape[-1], dtype=table.dtype, device=table.device)
        if len(table) != 2 * len(self.mesh.faces):
            raise ValueError(f"a bounce table of {len(table)} face sides for a mesh of {len(self.mesh.faces)} faces")
        if self._bounce is None or self._bounce.samples != bounce.samples:
            self._bounce = _TracedBounce(len(self), bounce.samples, self.seed + 7919)
        traced = self._bounce
        todo = idx[~traced.valid[idx]]
        if len(todo):
            normals = torch.from_numpy(self.normals[todo])
            dirs = cosine_directions(normals, traced.samples, torch.from_numpy(traced.shift[todo])).numpy()
            starts = np.repeat(self.points[todo] + self.offset * self.normals[todo], traced.samples, axis=0)
            flat = dirs.reshape(-1, 3)
            hit = self.tracer.trace(starts, flat)
            if self._face_normals is None:  # (once: a step traces new points, not a new mesh)
                self._face_normals = self.mesh.face_normals
            sides = face_side(hit.face, flat, self._face_normals)
            traced.sides[todo] = sides.reshape(len(todo), traced.samples)
            traced.valid[todo] = True
            traced.traces += len(todo)
        sides = torch.from_numpy(traced.sides[idx]).to(bounce.table.device)
        return indirect_irradiance(bounce.table, sides)

    def blocked_share(self) -> np.ndarray:
        """Per point, the share of its hemisphere the mesh blocks (uniform over directions)."""
        return blocked_share(self.bits, self.normals, self.directions)
