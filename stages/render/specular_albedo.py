"""Directional albedo of a BRDF's microfacet specular lobe, tabulated: the "split-sum" factor
[Karis13] that makes a specular lobe's energy exact whatever shape approximates it.

For a BRDF of :mod:`stages.render.brdf` (TANGO's: SG normal distribution ``D`` with ``alpha =
r^2``, Schlick's Fresnel, Smith-Schlick shadowing with ``k = (r + 1)^2 / 8``; glTF's: GGX and the
separable Smith-GGX), the reflected energy under a uniform white light is linear in ``F0`` because
Schlick's Fresnel is:

    E(n.v, r, F0) = int f_r(l, v) (n . l) dl = F0 * A(n.v, r) + B(n.v, r),

    A = int D(h) G (v.h) / (n.v) (1 - (1 - v.h)^5) dh,   B = the same with (1 - v.h)^5,

over half vectors ``h`` whose reflection ``l = 2 (v.h) h - v`` is above the surface (the
change of variables ``dl = 4 (v.h) dh`` cancels the BRDF's ``4 (n.l)(n.v)`` but for ``n.v``).
:func:`build_table` integrates ``A`` and ``B`` by quadrature on a grid of ``n.v`` and ``r``, over
the BRDF's own normal distribution and shadowing (its object's ``ndf_quadrature`` and
``shadowing``); :func:`directional_albedo` interpolates the BRDF's shipped table (its
``table_path``: ``data/specular_albedo.npz`` for TANGO's, written by ``python -m
stages.render.brdf.table``) bilinearly, differentiably in ``n.v`` and ``r``.
Accuracy: the quadrature is within 0.3% of a Monte Carlo estimate written from the textbook
formula, and the interpolation within 1% of the quadrature between grid nodes (both tested).

References:
  [Karis13] B. Karis. Real shading in Unreal Engine 4. SIGGRAPH 2013 course notes.
  [Zhang21] PhySG (the SG normal distribution and the shadowing term TANGO uses).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ..core.safefiles import DATA_LIMIT, open_read

if TYPE_CHECKING:  # (the BRDFs' package imports this module)
    from .brdf.base import Brdf

#: the folder of the shipped tables, one per BRDF model (each BRDF's ``table_path``)
DATA_DIR = Path(__file__).with_name("data")
#: the table's grid: n.v from NV_MIN (the shading keeps n.v >= 5e-4, see ``face_viewer``) to 1,
#: uniform in log(n.v), and the table holds log A and log B: near grazing a sharp lobe's albedo
#: follows a power of n.v that changes where the horizon starts to cut the lobe, which a lookup
#: linear in n.v or sqrt(n.v) misses by 50-70% and one in log-log follows; roughness uniform in
#: log(r) on [R_MIN, 1] (a lobe's width goes as r^2: uniform in r missed sharp lobes by 16% near grazing)
NV_MIN = 5e-4
R_MIN = 0.01
NV_NODES = 96
R_NODES = 64
#: values below this are looked up as this (B at normal incidence on the sharpest lobes is ~0)
LOG_FLOOR = 1e-30
#: quadrature of one table entry: Gauss-Legendre nodes in the BRDF's own variable of the half
#: vector's polar angle (its ``ndf_quadrature``) and in phi_h
U_NODES = 192
PHI_NODES = 256


def nv_grid() -> np.ndarray:
    """The table's ``n . v`` nodes ``(NV_NODES,)``, uniform in ``log(n . v)``."""
    return np.exp(np.linspace(math.log(NV_MIN), 0.0, NV_NODES))


def roughness_grid() -> np.ndarray:
    """The table's roughness nodes ``(R_NODES,)``, uniform in ``log(r)``."""
    return np.exp(np.linspace(math.log(R_MIN), 0.0, R_NODES))


def concentration_of(mean_length: np.ndarray) -> np.ndarray:
    """The vMF concentration ``kappa`` whose mean resultant length ``coth(kappa) - 1/kappa`` is
    ``mean_length`` in (0, 1): Newton's method from Banerjee et al.'s start (2005), and
    ``1 / (1 - R)`` where ``R > 1 - 1e-3`` (there ``coth`` is 1 to within ``exp(-2000)``)."""
    rbar = np.clip(np.asarray(mean_length, dtype=np.float64), 1e-9, 1.0 - 1e-15)
    near_one = rbar > 1.0 - 1e-3
    r = np.where(near_one, 0.5, rbar)
    k = r * (3.0 - r * r) / (1.0 - r * r)
    for _ in range(50):
        e = np.exp(-2.0 * k)  # coth k = (1 + e) / (1 - e), 1 / sinh^2 k = 4 e / (1 - e)^2
        f = (1.0 + e) / (1.0 - e) - 1.0 / k - r
        fp = 1.0 / k**2 - 4.0 * e / (1.0 - e) ** 2
        k = np.maximum(k - f / fp, 1e-9)
    return np.where(near_one, 1.0 / (1.0 - rbar), k)


def _half_vector_nodes(roughness: float, brdf: Brdf) -> tuple[np.ndarray, ...]:
    """Quadrature of ``int g(h) D(h) dh`` over half vectors: ``(cos_t, sin_t, phi, weight)`` with
    ``weight = D(h) dh`` at Gauss-Legendre nodes ``(U_NODES, PHI_NODES)``: in the polar angle, the
    BRDF's own change of variables (:meth:`~stages.render.brdf.Brdf.ndf_quadrature`, which
    resolves its sharpest lobes as well as its broadest), uniform in the azimuth."""
    xu, wu = np.polynomial.legendre.leggauss(U_NODES)
    xp, wp = np.polynomial.legendre.leggauss(PHI_NODES)
    phi = math.pi * (xp + 1.0)
    wp = math.pi * wp
    cos_t, sin_t, dens = brdf.ndf_quadrature(xu, wu, roughness)
    weight = dens[:, None] * wp[None, :] / (2.0 * math.pi)  # D(h) dh
    return cos_t, sin_t, phi, weight


def _entry_terms(nv: np.ndarray, roughness: float, brdf: Brdf) -> dict[str, np.ndarray]:
    """``A`` and ``B`` for every ``nv (M,)`` at one roughness of the BRDF ``brdf`` (its object,
    :mod:`stages.render.brdf`), by quadrature over ``h`` (:func:`_half_vector_nodes`), with the
    moments of each
    part's lobe ``f_r (n.l)`` over reflected directions ``l``: the angle ``theta`` of its mean
    direction from ``n`` (towards the mirror side) and the concentration ``kappa`` of the vMF with
    the same mean resultant length (:func:`concentration_of`)."""
    cos_t, sin_t, phi, weight = _half_vector_nodes(roughness, brdf)
    hx = sin_t[:, None] * np.cos(phi)[None, :]
    hz = np.broadcast_to(cos_t[:, None], hx.shape)
    out = {key: np.empty_like(nv) for key in ("a", "b", "theta_a", "kappa_a", "theta_b", "kappa_b")}
    for i, c in enumerate(nv):
        s = math.sqrt(max(1.0 - c * c, 0.0))
        vh = s * hx + c * hz  # v = (s, 0, c), h = (hx, hy, hz): v . h has no y part
        nl = 2.0 * vh * hz - c  # l = 2 (v.h) h - v, n = z
        lx = 2.0 * vh * hx - s  # the y part of l averages to 0 by symmetry
        ok = (vh > 0.0) & (nl > 0.0)
        shadow = brdf.shadowing(np.where(ok, nl, 1.0), c, roughness)
        common = np.where(ok, weight * shadow * vh, 0.0)  # D G (v.h) / (n.v) dh
        fres = np.clip(1.0 - vh, 0.0, 1.0) ** 5
        for part, w in (("a", common * (1.0 - fres)), ("b", common * fres)):
            total = float(w.sum())
            out[part][i] = total
            if total > 0.0:
                mx, mz = float((w * lx).sum()) / total, float((w * nl).sum()) / total
            else:  # no energy in this part (B of the sharpest lobes at normal view): a mirror lobe
                mx, mz = -s, c
            out["theta_" + part][i] = math.atan2(-mx, mz)
            out["kappa_" + part][i] = float(concentration_of(np.array(math.hypot(mx, mz))))
    return out


def build_table(brdf: Brdf) -> dict[str, np.ndarray]:
    """``{"nv", "roughness", "a", "b", "theta_a", "kappa_a", "theta_b", "kappa_b"}``: the grids and
    each column ``(NV_NODES, R_NODES)`` by quadrature (:func:`_entry_terms`) for ``brdf``."""
    nv, rough = nv_grid(), roughness_grid()
    columns = {key: np.empty((len(nv), len(rough))) for key in TABLE_COLUMNS}
    for j, r in enumerate(rough):
        for key, values in _entry_terms(nv, float(r), brdf).items():
            columns[key][:, j] = values
    return {"nv": nv, "roughness": rough, **columns}


#: the table's columns (each ``(NV_NODES, R_NODES)``); ``a, b`` and ``kappa_*`` are interpolated in
#: the log, ``theta_*`` as the tilts ``acos(n . v) - theta_*`` (:func:`lobe_moments`)
TABLE_COLUMNS = ("a", "b", "theta_a", "kappa_a", "theta_b", "kappa_b")


#: the tables read so far, by (device, dtype, BRDF name); a plain dict, not ``functools.cache``:
#: torch.compile traces a cached function's body (and breaks its graph at the file read), while a
#: lookup in a dict that already holds the table is a constant to it
_TABLES: dict[tuple[str, torch.dtype, str], dict[str, Tensor]] = {}


def _table(device: str, dtype: torch.dtype, brdf: Brdf) -> dict[str, Tensor]:
    """The table of ``brdf`` as tensors on ``device`` in ``dtype`` (read once per process)."""
    key = (device, dtype, brdf.name)
    table = _TABLES.get(key)
    if table is None:
        table = _TABLES[key] = _read_table(device, dtype, brdf)
    return table


def preload_table(device: torch.device | str, brdf: Brdf) -> None:
    """Read ``brdf``'s table for ``device`` now (as a lookup on that device would: float32, the
    device's full name), so that a compiled renderer finds it in memory."""
    _table(str(torch.empty(0, device=device).device), torch.float32, brdf)


def _read_table(device: str, dtype: torch.dtype, brdf: Brdf) -> dict[str, Tensor]:
    path = brdf.table_path
    rebuild = f"`python -m stages.render.brdf.table --brdf {brdf.name}`"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the specular albedo table is missing; rebuild it with {rebuild}")
    with open_read(path, DATA_LIMIT) as fh, np.load(fh) as z:
        missing = [key for key in TABLE_COLUMNS if key not in z.files]
        if missing:
            raise ValueError(f"{path} lacks the columns {missing} (an older table); rebuild it with {rebuild}")
        grids = {key: z[key] if key.startswith("theta") else np.log(np.maximum(z[key], LOG_FLOOR)) for key in TABLE_COLUMNS}
        view_angle = np.arccos(np.clip(z["nv"], 0.0, 1.0))[:, None]
    for part in ("a", "b"):
        # the mean's angle counted from the mirror direction (see lobe_moments), in float64 here
        grids["tilt_" + part] = view_angle - grids.pop("theta_" + part)
    return {key: torch.as_tensor(value, dtype=dtype, device=device) for key, value in grids.items()}


def _bilinear(grid: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """Bilinear lookup of ``grid (H, W)`` at continuous indices ``x`` (rows) and ``y`` (columns)
    clamped to the grid; differentiable in ``x`` and ``y``."""
    h, w = grid.shape
    # integer bounds: under torch.compile(dynamic=True) the grid's sizes are symbolic, and a
    # float made of them (h - 1.0) restarts the compilation once per process
    x = x.clamp(0, h - 1)
    y = y.clamp(0, w - 1)
    x0 = x.detach().floor().clamp(max=h - 2).long()
    y0 = y.detach().floor().clamp(max=w - 2).long()
    fx, fy = x - x0, y - y0
    g00, g01 = grid[x0, y0], grid[x0, y0 + 1]
    g10, g11 = grid[x0 + 1, y0], grid[x0 + 1, y0 + 1]
    return (g00 * (1 - fy) + g01 * fy) * (1 - fx) + (g10 * (1 - fy) + g11 * fy) * fx


def _lookup(cos_nv: Tensor, roughness: Tensor, keys: tuple[str, ...], brdf: Brdf) -> list[Tensor]:
    """The table's columns ``keys`` at ``cos_nv`` and ``roughness`` (any matching shapes): bilinear in
    ``log(n . v)`` and ``log(r)``, computed in float32 at least, returned in the input's dtype."""
    work = torch.float32 if cos_nv.dtype in (torch.float16, torch.bfloat16) else cos_nv.dtype
    table = _table(str(cos_nv.device), work, brdf)
    t = (1.0 - torch.log(cos_nv.to(work).clamp(NV_MIN, 1.0)) / math.log(NV_MIN)) * (NV_NODES - 1)
    s = (1.0 - torch.log(roughness.to(work).clamp(R_MIN, 1.0)) / math.log(R_MIN)) * (R_NODES - 1)
    out = []
    for key in keys:
        value = _bilinear(table[key], t, s)
        out.append((value if key.startswith("tilt") else torch.exp(value)).to(cos_nv.dtype))
    return out


def directional_albedo(cos_nv: Tensor, roughness: Tensor, brdf: Brdf) -> tuple[Tensor, Tensor]:
    """``A, B`` of ``brdf``'s table at ``cos_nv (...)`` in ``[5e-4, 1]`` and ``roughness (...)`` in
    ``[0.01, 1]`` (clamped to the table) -> two tensors of the same shape; the specular albedo is
    ``F0 A + B``. Bilinear in ``log(n . v)`` and ``log(r)`` on ``log A`` and ``log B``; gradients flow
    to both."""
    a, b = _lookup(cos_nv, roughness, ("a", "b"), brdf)
    return a, b


def lobe_moments(cos_nv: Tensor, roughness: Tensor, brdf: Brdf) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``tilt_a, kappa_a, tilt_b, kappa_b`` at ``cos_nv`` and ``roughness`` (as
    :func:`directional_albedo`): for the ``A`` part (weighted by ``1 - (1 - v.h)^5``) and the ``B``
    part (by ``(1 - v.h)^5``) of the BRDF's lobe ``f_r (n . l)``, the angle from the mirror
    direction to its mean direction, towards the normal (the mean's angle from the normal is
    ``acos(n . v) - tilt``, in [0, pi/2]; the ``B`` part's mean can lie beyond the mirror direction,
    a negative tilt), and the concentration of the vMF with the same mean resultant length (0.3 for
    the broadest lobe to ~1e8 for the sharpest). The tilt rather than the angle, so that the
    renderer measures the lobe from the view it reflects: a glossy lobe's mean is within a small
    tilt of the mirror direction, and the half vector between them, which a sharp NDF amplifies,
    is then that tilt's to float precision, not the difference of two rounded angles near pi/2 (in
    float32 the fitted lobe's gradient erred by 1.4% at n.v 0.01, roughness 0.05)."""
    tilt_a, kappa_a, tilt_b, kappa_b = _lookup(cos_nv, roughness, ("tilt_a", "kappa_a", "tilt_b", "kappa_b"), brdf)
    return tilt_a, kappa_a, tilt_b, kappa_b
