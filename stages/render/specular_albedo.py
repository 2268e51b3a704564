"""Directional albedo of TANGO's microfacet specular BRDF, tabulated: the "split-sum" factor
[Karis13] that makes a specular lobe's energy exact whatever shape approximates it.

For the BRDF of :mod:`stages.render.shading` (SG normal distribution ``D`` with ``alpha = r^2``,
Schlick's Fresnel, Smith-Schlick shadowing with ``k = (r + 1)^2 / 8``), the reflected energy under
a uniform white light is linear in ``F0`` because Schlick's Fresnel is:

    E(n.v, r, F0) = int f_r(l, v) (n . l) dl = F0 * A(n.v, r) + B(n.v, r),

    A = int D(h) G (v.h) / (n.v) (1 - (1 - v.h)^5) dh,   B = the same with (1 - v.h)^5,

over half vectors ``h`` whose reflection ``l = 2 (v.h) h - v`` is above the surface (the
change of variables ``dl = 4 (v.h) dh`` cancels the BRDF's ``4 (n.l)(n.v)`` but for ``n.v``).
:func:`build_table` integrates ``A`` and ``B`` by quadrature on a grid of ``n.v`` and ``r``;
:func:`directional_albedo` interpolates the shipped table (``data/specular_albedo.npz``, written by
``python -m stages.render.specular_albedo``) bilinearly, differentiably in ``n.v`` and ``r``.
Accuracy: the quadrature is within 0.3% of a Monte Carlo estimate written from the textbook
formula, and the interpolation within 1% of the quadrature between grid nodes (both tested).

References:
  [Karis13] B. Karis. Real shading in Unreal Engine 4. SIGGRAPH 2013 course notes.
  [Zhang21] PhySG (the SG normal distribution and the shadowing term TANGO uses).
"""

from __future__ import annotations

import argparse
import functools
import logging
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

log = logging.getLogger(__name__)

TABLE_PATH = Path(__file__).with_name("data") / "specular_albedo.npz"
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
#: quadrature of one table entry: Gauss-Legendre nodes in u = lam (1 - cos theta_h) and in phi_h
U_NODES = 192
PHI_NODES = 256
#: the NDF's exponent beyond which exp(-u) is below 1e-26: the u range is [0, min(2 lam, U_MAX)]
U_MAX = 60.0


def nv_grid() -> np.ndarray:
    """The table's ``n . v`` nodes ``(NV_NODES,)``, uniform in ``log(n . v)``."""
    return np.exp(np.linspace(math.log(NV_MIN), 0.0, NV_NODES))


def roughness_grid() -> np.ndarray:
    """The table's roughness nodes ``(R_NODES,)``, uniform in ``log(r)``."""
    return np.exp(np.linspace(math.log(R_MIN), 0.0, R_NODES))


def _entry_terms(nv: np.ndarray, roughness: float) -> tuple[np.ndarray, np.ndarray]:
    """``A`` and ``B`` for every ``nv (M,)`` at one roughness, by quadrature over ``h``.

    With ``lam = 2 / r^4`` and the NDF amplitude ``1 / (pi r^4) = lam / (2 pi)``, the substitution
    ``u = lam (1 - cos theta_h)`` turns ``D(h) dh`` into ``exp(-u) / (2 pi) du dphi`` exactly, which
    resolves the sharpest lobes as well as the broadest."""
    lam = 2.0 / roughness**4
    k = (roughness + 1.0) ** 2 / 8.0
    xu, wu = np.polynomial.legendre.leggauss(U_NODES)
    top = min(2.0 * lam, U_MAX)
    u = 0.5 * top * (xu + 1.0)
    wu = 0.5 * top * wu
    xp, wp = np.polynomial.legendre.leggauss(PHI_NODES)
    phi = math.pi * (xp + 1.0)
    wp = math.pi * wp
    cos_t = 1.0 - u / lam
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    hx = sin_t[:, None] * np.cos(phi)[None, :]
    hz = np.broadcast_to(cos_t[:, None], hx.shape)
    weight = (np.exp(-u) * wu)[:, None] * wp[None, :] / (2.0 * math.pi)  # D(h) dh
    a_out = np.empty_like(nv)
    b_out = np.empty_like(nv)
    for i, c in enumerate(nv):
        s = math.sqrt(max(1.0 - c * c, 0.0))
        vh = s * hx + c * hz  # v = (s, 0, c), h = (hx, hy, hz): v . h has no y part
        nl = 2.0 * vh * hz - c  # l = 2 (v.h) h - v, n = z
        ok = (vh > 0.0) & (nl > 0.0)
        g1_l = np.where(ok, nl / (nl * (1.0 - k) + k), 0.0)
        common = np.where(ok, weight * g1_l * vh / (c * (1.0 - k) + k), 0.0)  # D G (v.h) / (n.v) dh
        fres = np.clip(1.0 - vh, 0.0, 1.0) ** 5
        a_out[i] = float((common * (1.0 - fres)).sum())
        b_out[i] = float((common * fres).sum())
    return a_out, b_out


def build_table() -> dict[str, np.ndarray]:
    """``{"nv", "roughness", "a", "b"}``: the grids and ``A, B (NV_NODES, R_NODES)`` by quadrature."""
    nv, rough = nv_grid(), roughness_grid()
    a = np.empty((len(nv), len(rough)))
    b = np.empty_like(a)
    for j, r in enumerate(rough):
        a[:, j], b[:, j] = _entry_terms(nv, float(r))
    return {"nv": nv, "roughness": rough, "a": a, "b": b}


@functools.cache
def _table(device: str, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    if not TABLE_PATH.is_file():
        raise FileNotFoundError(
            f"{TABLE_PATH}: the specular albedo table is missing; rebuild it with `python -m stages.render.specular_albedo`"
        )
    with np.load(TABLE_PATH) as z:
        a, b = np.log(np.maximum(z["a"], LOG_FLOOR)), np.log(np.maximum(z["b"], LOG_FLOOR))
    return (torch.as_tensor(a, dtype=dtype, device=device), torch.as_tensor(b, dtype=dtype, device=device))


def _bilinear(grid: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """Bilinear lookup of ``grid (H, W)`` at continuous indices ``x`` (rows) and ``y`` (columns)
    clamped to the grid; differentiable in ``x`` and ``y``."""
    h, w = grid.shape
    x = x.clamp(0.0, h - 1.0)
    y = y.clamp(0.0, w - 1.0)
    x0 = x.detach().floor().clamp(max=h - 2).long()
    y0 = y.detach().floor().clamp(max=w - 2).long()
    fx, fy = x - x0, y - y0
    g00, g01 = grid[x0, y0], grid[x0, y0 + 1]
    g10, g11 = grid[x0 + 1, y0], grid[x0 + 1, y0 + 1]
    return (g00 * (1 - fy) + g01 * fy) * (1 - fx) + (g10 * (1 - fy) + g11 * fy) * fx


def directional_albedo(cos_nv: Tensor, roughness: Tensor) -> tuple[Tensor, Tensor]:
    """``A, B`` at ``cos_nv (...)`` in ``[5e-4, 1]`` and ``roughness (...)`` in ``[0.01, 1]``
    (clamped to the table) -> two tensors of the same shape; the specular albedo is
    ``F0 A + B``. Bilinear in ``log(n . v)`` and ``log(r)`` on ``log A`` and ``log B``; gradients flow
    to both."""
    a, b = _table(str(cos_nv.device), torch.float32 if cos_nv.dtype in (torch.float16, torch.bfloat16) else cos_nv.dtype)
    t = (1.0 - torch.log(cos_nv.to(a.dtype).clamp(NV_MIN, 1.0)) / math.log(NV_MIN)) * (NV_NODES - 1)
    s = (1.0 - torch.log(roughness.to(a.dtype).clamp(R_MIN, 1.0)) / math.log(R_MIN)) * (R_NODES - 1)
    return torch.exp(_bilinear(a, t, s)).to(cos_nv.dtype), torch.exp(_bilinear(b, t, s)).to(cos_nv.dtype)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Rebuild the specular albedo table by quadrature.")
    parser.add_argument("--out", type=Path, default=TABLE_PATH)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    table = build_table()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".part.npz")
    np.savez_compressed(tmp, **table)
    tmp.replace(args.out)
    log.info("wrote %s (%d x %d)", args.out, NV_NODES, R_NODES)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
