"""Image-quality figures: PSNR and SSIM, over object pixels (callers pass masks or masked values;
a frame's background never counts)."""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB of values in [0, 1], over every element given: callers
    pass object pixels only (``img[mask]``), never a frame with its background."""
    mse = float(F.mse_loss(a, b))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


#: the share of object pixels :func:`highlights` calls the highlights (the brightest 1% of the target's)
HIGHLIGHT_SHARE = 0.01


def highlights(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, share: float = HIGHLIGHT_SHARE) -> dict:
    """Whether a render shows the target's highlights: over the object pixels of images
    ``(B, 3, H, W)`` in [0, 1] (sRGB) where ``mask (B, 1, H, W)`` holds, the brightest ``share`` of
    the target's pixels by mean of the channels (at least one pixel). Returns their mean value in
    the target (``target``) and in ``pred`` at the same pixels (``recovered_at_target``), and the
    mean of ``pred``'s own brightest ``share`` (``recovered``): a blurred light leaves
    ``recovered_at_target`` well below ``target``."""
    m = mask.expand_as(target)[:, :1].reshape(-1)
    t = target.mean(1).reshape(-1)[m]
    p = pred.mean(1).reshape(-1)[m]
    if t.numel() == 0:
        return {"share": share, "pixels": 0, "target": None, "recovered_at_target": None, "recovered": None}
    k = max(1, int(round(share * t.numel())))
    top = torch.topk(t, k).indices
    return {
        "share": share,
        "pixels": k,
        "target": float(t[top].mean()),
        "recovered_at_target": float(p[top].mean()),
        "recovered": float(torch.topk(p, k).values.mean()),
    }


def ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None, window: int = 11, sigma: float = 1.5) -> float:
    """Mean structural similarity (Wang et al. 2004) of images ``(B, 3, H, W)`` in [0, 1]:
    Gaussian window 11 / 1.5, constants ``(0.01)^2`` and ``(0.03)^2``, per channel, 'valid'
    windows only, averaged over every window or, with ``mask (B, 1, H, W)`` bool, over the
    windows centred on object pixels (so the background does not count)."""
    c1, c2 = 0.01**2, 0.03**2
    x = torch.arange(window, dtype=a.dtype) - (window - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = (g / g.sum()).to(a.device)
    k = (g[:, None] * g[None, :])[None, None].repeat(a.shape[1], 1, 1, 1)

    def blur(t):
        return F.conv2d(t, k, groups=a.shape[1])

    mu_a, mu_b = blur(a), blur(b)
    saa = blur(a * a) - mu_a**2
    sbb = blur(b * b) - mu_b**2
    sab = blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * sab + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2)
    smap = num / den
    if mask is None:
        return float(smap.mean())
    h = (window - 1) // 2
    centre = mask[:, :, h : mask.shape[2] - h, h : mask.shape[3] - h].expand_as(smap)
    return float(smap[centre].mean())


#: a true albedo no larger than this everywhere is black (a metal): no albedo scale is estimated
ALBEDO_BLACK = 1e-6


def material_errors(pred: dict[str, torch.Tensor], truth: dict[str, torch.Tensor], energy: torch.Tensor, true_energy) -> dict:
    """Errors of a recovered material against the ground truth at the same hits, and of the
    recovered light's energy.

    ``pred`` and ``truth``: ``albedo (N, 3)``, ``specular (N, 3)`` (F0 colour), ``roughness
    (N, 1)``, ``normal (N, 3)`` (unit, facing the viewer); ``pred`` may lack the specular terms
    (a diffuse-only model). ``energy`` and ``true_energy``: ``int L dw`` per channel ``(3,)``.

    Albedo and light share a scale that images cannot pin down (twice the light and half the
    albedo render the same diffuse image), so the albedo error is given as is and after the one
    least-squares scale ``s = <a, t> / <a, a>`` of the recovered albedo, with ``s`` itself. A
    truth without diffuse albedo (a metal: black everywhere) has no such scale (``s = 0`` would
    grade any albedo as perfect): then ``albedo_scale`` and ``albedo_rmse_scaled`` are ``None``
    and the error as is is the figure.
    """
    a, t = pred["albedo"].double(), truth["albedo"].double()
    out = {"albedo_rmse": float(torch.sqrt(((a - t) ** 2).mean())), "albedo_scale": None, "albedo_rmse_scaled": None}
    if float(t.abs().max()) > ALBEDO_BLACK:
        scale = float((a * t).sum() / (a * a).sum().clamp(min=1e-30))
        out["albedo_scale"] = scale
        out["albedo_rmse_scaled"] = float(torch.sqrt(((scale * a - t) ** 2).mean()))
    if pred.get("roughness") is not None:
        r, rt = pred["roughness"].double(), truth["roughness"].double()
        out["roughness_rmse"] = float(torch.sqrt(((r - rt) ** 2).mean()))
        out["roughness_mae"] = float((r - rt).abs().mean())
        s, st = pred["specular"].double(), truth["specular"].double()
        out["specular_rmse"] = float(torch.sqrt(((s - st) ** 2).mean()))
    cos = (pred["normal"].double() * truth["normal"].double()).sum(-1).clamp(-1.0, 1.0)
    out["normal_angle_deg_mean"] = float(torch.rad2deg(torch.arccos(cos)).mean())
    e = energy.double().cpu()
    te = torch.as_tensor(true_energy, dtype=torch.float64)
    out["light_energy"] = e.tolist()
    out["light_energy_true"] = te.tolist()
    out["light_energy_ratio"] = (e / te.clamp(min=1e-30)).tolist()
    return out
