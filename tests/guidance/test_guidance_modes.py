"""One class per guidance mode behind one interface: chosen once from the settings, each with its
own loss, evaluation score and origin record."""

from __future__ import annotations

import pytest
import torch

from stages.config.sections import OptimizeSettings
from stages.core.errors import ConfigError
from stages.geometry.raycache import RayCache
from stages.guidance.clip import load_clip
from stages.guidance.objective import (
    ClipGuidance,
    Guidance,
    ImageBatch,
    ImageGuidance,
    SGTargetGuidance,
    choose_guidance,
)
from stages.imaging.views import ViewStore, render_view
from stages.model.field import StyleField
from stages.render.color import linear_to_srgb

CLIP = {"guidance": "clip", "clip_tiny_test": True, "image_size": 64}
SG = {"guidance": "image", "target_renderer": "sg"}
MITSUBA = {"guidance": "image", "target_renderer": "mitsuba"}


def _images(gen, n, size=16):
    return [torch.rand(3, size, size, generator=gen) for _ in range(n)]


def test_the_settings_choose_one_class_and_its_origin():
    clip = choose_guidance(OptimizeSettings(**CLIP), "a vase", "cpu")
    sg = choose_guidance(OptimizeSettings(**SG), "a vase", "cpu")
    mitsuba = choose_guidance(OptimizeSettings(**MITSUBA), "a vase", "cpu", targets="Mitsuba wood, 32 spp")
    assert (type(clip), type(sg), type(mitsuba)) == (ClipGuidance, SGTargetGuidance, ImageGuidance)
    assert all(isinstance(g, Guidance) for g in (clip, sg, mitsuba))
    assert clip.test_only and clip.origin["test_only"] and not clip.origin["image_guided"]
    assert sg.origin["image_guided"] and "our own SG renderer" in sg.weights_id
    assert mitsuba.origin["image_guided"] and mitsuba.weights_id == "image targets: Mitsuba wood, 32 spp"
    assert clip.clip_precision is not None and sg.clip_precision is None
    with pytest.raises(ConfigError, match="no Mitsuba targets were given"):
        choose_guidance(OptimizeSettings(**MITSUBA), "a vase", "cpu")


def test_the_clip_loss_is_minus_the_similarity_of_the_globals_and_of_the_crops(monkeypatch):
    gen = torch.Generator().manual_seed(0)
    guide = load_clip(OptimizeSettings(**CLIP).clip_spec(), device="cpu")
    g = ClipGuidance(OptimizeSettings(**CLIP), "a vase made of wood", "cpu", guide)
    globals_, crops = _images(gen, 2, 64), _images(gen, 3, 64)
    # TANGO's similarity: the cosine of the averaged image embedding with the text's
    text = guide.embed_text("a vase made of wood")

    def cosine(images):
        mean = guide.embed_images(torch.stack(images)).mean(0)
        return (mean @ text) / (mean.norm() * text.norm())

    loss, stats = g.loss(ImageBatch(globals_, crops), None)
    assert float(loss) == pytest.approx(-float(cosine(globals_) + cosine(crops)), abs=1e-5)
    assert set(stats) == {"similarity_global", "similarity_crops"}
    # the globals and the crops go through the tower as one batch, with the gradients of two
    calls, encode = [], guide.model.encode_image
    monkeypatch.setattr(guide.model, "encode_image", lambda x: calls.append(len(x)) or encode(x))
    leaves = [x.clone().requires_grad_() for x in globals_ + crops]
    g.loss(ImageBatch(leaves[:2], leaves[2:]), None)[0].backward()
    assert calls == [5]
    monkeypatch.undo()
    apart = [x.clone().requires_grad_() for x in globals_ + crops]
    (-cosine(apart[:2]) - cosine(apart[2:])).backward()
    for a, b in zip(leaves, apart, strict=True):
        assert float((a.grad - b.grad).norm() / b.grad.norm()) < 1e-4
    alone, stats = g.loss(ImageBatch(globals_, []), None)
    assert float(alone) == pytest.approx(-float(cosine(globals_)), abs=1e-5) and "similarity_crops" not in stats


def test_the_image_loss_is_the_squared_error_of_the_globals_plus_the_crops():
    gen = torch.Generator().manual_seed(1)
    g = choose_guidance(OptimizeSettings(**SG), "p", "cpu")
    r, t = ImageBatch(_images(gen, 2), _images(gen, 4, 8)), ImageBatch(_images(gen, 2), _images(gen, 4, 8))
    loss, stats = g.loss(r, t)
    mse_g = sum(float(((a - b) ** 2).sum()) for a, b in zip(r.globals, t.globals, strict=True)) / (2 * 3 * 16 * 16)
    mse_c = sum(float(((a - b) ** 2).sum()) for a, b in zip(r.crops, t.crops, strict=True)) / (4 * 3 * 8 * 8)
    assert float(loss) == pytest.approx(mse_g + mse_c, rel=1e-5) and stats == {}
    with pytest.raises(ValueError, match="needs the target images"):
        g.loss(r, None)


def test_each_guidance_scores_the_evaluation_views_its_own_way(cache):
    field = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    store = ViewStore(RayCache(cache / "eval.npz"), torch.device("cpu"), field.normals)
    views = [store[i] for i in range(len(store))]
    renders = [render_view(field, v, store.width, 32)["rgb"] for v in views]
    sg = choose_guidance(OptimizeSettings(**SG), "p", "cpu")
    score = sg.eval_score(renders, views, store.width, 32)
    assert len(score.targets) == len(views) and score.targets[0].shape == (3, 32, 32)
    assert 0 < score.figures["eval_psnr_db"] < 60 and "object pixels" in score.figures["eval_psnr_pixels"]
    # the target itself scores far higher than the untrained field
    perfect = sg.eval_score(score.targets, views, store.width, 32)
    assert perfect.figures["eval_psnr_db"] > score.figures["eval_psnr_db"] + 20
    # the target colours are the procedural material under the SG light, in the view's own hits
    v = views[0]
    sel = torch.arange(min(50, len(v.points)))
    assert torch.allclose(sg.target_colors(v, sel), sg.procedural_colors(v.points[sel], v.normals[sel], v.view[sel]))
    assert linear_to_srgb(sg.target_colors(v, sel)).max() <= 1.0
    clip = choose_guidance(OptimizeSettings(**CLIP), "p", "cpu")
    figures = clip.eval_score(renders, views, store.width, 32).figures
    assert len(figures["final_similarity_per_view"]) == len(views)
    assert figures["final_similarity"] == pytest.approx(sum(figures["final_similarity_per_view"]) / len(views))
    assert clip.target_colors(v, sel) is None
    # Mitsuba targets exist for the training and metric views only: nothing to score here
    mitsuba = choose_guidance(OptimizeSettings(**MITSUBA), "p", "cpu", targets="t")
    assert mitsuba.eval_score(renders, views, store.width, 32).figures == {}
    with pytest.raises(ConfigError, match="no Mitsuba targets attached"):
        mitsuba.target_colors(v, sel)


def test_each_guidance_scores_the_held_out_views_its_own_way(cache):
    """The metrics stage's figures come from the run's guidance class: the CLIP's similarity under
    ``guidance``, the image targets' PSNR, SSIM and highlights under ``image_target``."""
    from stages.guidance.objective import guidance_class

    field = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    store = ViewStore(RayCache(cache / "eval.npz"), torch.device("cpu"), field.normals)
    renders = torch.stack([render_view(field, store[i], store.width, store.width)["rgb"] for i in range(len(store))])
    sg_settings = OptimizeSettings(**SG)
    kind = guidance_class(sg_settings)
    assert kind is SGTargetGuidance and kind.held_out_key == "image_target"
    held = kind.for_metrics(sg_settings, "p", "cpu", None).held_out(renders, store, ["p"], 0.0)
    assert held.targets.shape == renders.shape and 0 < held.figures["psnr_db"] < 60
    assert {"ssim", "highlights", "pixels", "weights"} <= set(held.figures)
    assert (held.figures["target_renderer"], held.figures["target_light"]) == ("sg", "studio")
    perfect = kind.for_metrics(sg_settings, "p", "cpu", None).held_out(held.targets, store, ["p"], 0.0)
    assert perfect.figures["psnr_db"] > held.figures["psnr_db"] + 20
    clip_settings = OptimizeSettings(**CLIP)
    kind = guidance_class(clip_settings)
    assert kind is ClipGuidance and kind.held_out_key == "guidance"
    clip = kind.for_metrics(clip_settings, "p", "cpu", None)
    assert clip.clip_precision == "float32"  # the held-out figures of every run alike, whatever it trained in
    held = clip.held_out(renders, store, ["p", "q"], 1.0)
    assert held.targets is None and held.figures["test_only"] and -1 <= held.figures["similarity"] <= 1
