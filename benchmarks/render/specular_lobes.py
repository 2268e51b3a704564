"""The specular models side by side: cost per shaded point and error against quadrature of the BRDF.

For each model of ``optimize.specular_lobe`` (``isotropic``: TANGO's closed form; ``split_sum``:
exact energy, the isotropic lobe's shape; ``fitted``: exact energy, a lobe fitted to the BRDF's
first moment, corrected by the BRDF at each light lobe) it prints

- the time per point of a forward and backward pass in float32 (``--points`` random surface
  points, normals and views; a light of ``--lobes`` SG lobes; the best of ``--repeats``), and its
  ratio to the isotropic model's, measured in the same run;
- the worst relative error per light over roughness 0.05..1 and n.v 0.05..1 (F0 0.04 / 0.3 /
  0.9), against a reference written here from the textbook BRDF (``D F G / (4 (n.l)(n.v))`` with
  TANGO's SG NDF, Schlick's Fresnel, Smith-Schlick) integrated against the light by Gauss-Legendre
  quadrature over half vectors (the NDF's own variable ``u = lam (1 - cos theta_h)``), never
  through the renderer. The lights: 32 lobes of sharpness 5 (smooth) and of 30 (spotty), the
  procedural studio light, and a sky with a sun of sharpness 300 to the side of the lobe and at
  its mirror direction (the worst case: a highlight as wide as the lobe).

    python -m benchmarks.render.specular_lobes
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

ROUGHNESS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 1.0)
COS_NV = (1.0, 0.5, 0.3, 0.1, 0.05)
F0 = np.array([0.04, 0.3, 0.9])


def reference(cos_nv: float, r: float, axis: np.ndarray, sharpness: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
    """``int f_r(l, v) (n . l) L(l) dl`` per channel of F0, ``n = z``, ``v = (sqrt(1 - c^2), 0, c)``, by
    quadrature over half vectors: ``D(h) dh = exp(-u) / (2 pi) du dphi`` with ``u = lam (1 - cos
    theta_h)`` and ``dl = 4 (v.h) dh``, which cancels the BRDF's ``4 (n.l)(n.v)`` but for ``n.v``."""
    lam = 2.0 / r**4
    k = (r + 1.0) ** 2 / 8.0
    xu, wu = np.polynomial.legendre.leggauss(256)
    top = min(2.0 * lam, 60.0)
    u, wu = 0.5 * top * (xu + 1.0), 0.5 * top * wu
    xp, wp = np.polynomial.legendre.leggauss(384)
    phi, wp = math.pi * (xp + 1.0), math.pi * wp
    sin_t = np.sqrt(np.clip(u / lam * (2.0 - u / lam), 0.0, None))
    h = np.stack(
        [
            sin_t[:, None] * np.cos(phi)[None],
            sin_t[:, None] * np.sin(phi)[None],
            np.broadcast_to((1.0 - u / lam)[:, None], (len(u), len(phi))),
        ],
        -1,
    )
    v = np.array([math.sqrt(1.0 - cos_nv**2), 0.0, cos_nv])
    vh = h @ v
    light_dir = 2.0 * vh[..., None] * h - v
    nl = light_dir[..., 2]
    ok = (vh > 0) & (nl > 0)
    g1_l = np.where(ok, nl / (nl * (1 - k) + k), 0.0)
    weight = (np.exp(-u) * wu)[:, None] * wp[None] / (2.0 * math.pi)
    common = np.where(ok, weight * g1_l * vh / (cos_nv * (1 - k) + k), 0.0)
    schlick = np.clip(1.0 - vh, 0.0, 1.0) ** 5
    radiance = np.exp((light_dir @ axis.T - 1.0) * sharpness[:, 0]) @ amplitude  # (U, P, C)
    fres = F0 + (1.0 - F0) * schlick[..., None]
    return (common[..., None] * fres * radiance).sum((0, 1))


def lights(dtype):
    import torch

    from stages.model.lights.sg import fibonacci_sphere
    from stages.model.procedural import procedural_light
    from stages.render.shading import SGLight

    g = torch.Generator().manual_seed(0)

    def uniform(k, lam):
        amplitude = torch.rand(k, 3, generator=g, dtype=dtype)
        return SGLight(fibonacci_sphere(k).to(dtype), torch.full((k, 1), lam, dtype=dtype), amplitude)

    def sun_sky(elevation, azimuth):
        sky = uniform(32, 3.0)
        d = torch.tensor(
            [[math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]], dtype=dtype
        )
        return SGLight(
            torch.cat([sky.axis, d]),
            torch.cat([sky.sharpness, torch.tensor([[300.0]], dtype=dtype)]),
            torch.cat([0.2 * sky.amplitude, torch.full((1, 3), 50.0, dtype=dtype)]),
        )

    studio = procedural_light("studio", dtype=dtype)  # y up: turned so that its key light is above z
    return {
        "smooth (32 x 5)": uniform(32, 5.0),
        "spotty (32 x 30)": uniform(32, 30.0),
        "studio": SGLight(studio.axis[:, [0, 2, 1]], studio.sharpness, studio.amplitude),
        "sun to the side": sun_sky(0.5, 1.2),
        "sun at the mirror": sun_sky(0.3, math.pi),
    }


def main() -> None:
    import torch

    from stages.config.sections import SPECULAR_LOBES
    from stages.model.networks import Material
    from stages.render.brdf.tango import TANGO
    from stages.render.shading import SGLight, face_viewer

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=65536)
    parser.add_argument("--lobes", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")

    n = torch.nn.functional.normalize(torch.randn(args.points, 3), dim=-1)
    v = torch.nn.functional.normalize(n + 0.8 * torch.randn(args.points, 3), dim=-1)
    n = face_viewer(n, v)
    light = SGLight(
        torch.nn.functional.normalize(torch.randn(args.lobes, 3), dim=-1),
        torch.rand(args.lobes, 1) * 30 + 0.5,
        torch.rand(args.lobes, 3),
    )
    albedo = torch.rand(args.points, 3)
    cost = {}
    for lobe in SPECULAR_LOBES:
        best = math.inf
        for _ in range(args.repeats):
            spec = torch.rand(args.points, 3, requires_grad=True)
            rough = (torch.rand(args.points, 1) * 0.95 + 0.05).requires_grad_()
            t0 = time.perf_counter()
            out = TANGO.shade(n, v, Material(albedo, spec, rough), light, lobe).specular
            out.sum().backward()
            best = min(best, time.perf_counter() - t0)
        cost[lobe] = best / args.points * 1e9
    print(f"\ncost per point, specular forward + backward, float32, {args.lobes} light lobes, best of {args.repeats}:")
    for lobe in SPECULAR_LOBES:
        print(f"  {lobe:10s} {cost[lobe]:7.0f} ns   x{cost[lobe] / cost['isotropic']:.2f} of isotropic")

    print("\nworst |ours / reference - 1| over roughness 0.05..1, n.v 0.05..1, F0 0.04/0.3/0.9:")
    print(f"  {'light':20s}" + "".join(f"{lobe:>12s}" for lobe in SPECULAR_LOBES))
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    f0 = torch.tensor(F0, dtype=torch.float64)[None]
    for name, sg in lights(torch.float64).items():
        worst = dict.fromkeys(SPECULAR_LOBES, 0.0)
        for r in ROUGHNESS:
            for c in COS_NV:
                ref = reference(c, r, sg.axis.numpy(), sg.sharpness.numpy(), sg.amplitude.numpy())
                view = torch.tensor([[math.sqrt(1 - c * c), 0.0, c]], dtype=torch.float64)
                rough = torch.tensor([[r]], dtype=torch.float64)
                for lobe in SPECULAR_LOBES:
                    got = TANGO.shade(normal, view, Material(f0, f0, rough), sg, lobe).specular[0].numpy()
                    worst[lobe] = max(worst[lobe], float(np.max(np.abs(got / ref - 1.0))))
        print(f"  {name:20s}" + "".join(f"{100 * worst[lobe]:11.1f}%" for lobe in SPECULAR_LOBES))


if __name__ == "__main__":
    main()
