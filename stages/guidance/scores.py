"""CLIP-based evaluation figures: the CLIP score of a prompt and R-precision among the grid's prompts."""

from __future__ import annotations

import torch
from torch.nn import functional as F


def _resize(imgs: torch.Tensor, size: int) -> torch.Tensor:
    if imgs.shape[-1] == size:
        return imgs
    return F.interpolate(imgs, size=(size, size), mode="bicubic", align_corners=False).clamp(0, 1)


@torch.no_grad()
def clip_metrics(guide, imgs: torch.Tensor, prompt: str, candidates: list[str]) -> dict:
    """CLIP score of ``prompt`` and R-precision among ``candidates`` (which include ``prompt``)."""
    x = _resize(imgs, guide.image_size)
    emb = F.normalize(guide.embed_images(x), dim=-1)  # (V, D)
    texts = torch.stack([guide.embed_text(t) for t in candidates])  # (P, D)
    sims = emb @ texts.T  # (V, P)
    own = candidates.index(prompt)
    top = sims.argmax(1)
    return {
        "weights": guide.weights_id,
        "test_only": guide.test_only,
        "clip_score": float(100.0 * sims[:, own].mean()),
        "similarity_mean_embedding": float(F.cosine_similarity(emb.mean(0), texts[own], dim=0)),
        "r_precision": float((top == own).float().mean()),
        "candidates": len(candidates),
        "views": int(len(imgs)),
    }
