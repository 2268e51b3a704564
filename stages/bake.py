"""bake: bake the trained field into PBR textures, in the input's own UV layout, a second UV set made
beside it, or a new xatlas atlas.

The layout is ``bake.uv``'s (:mod:`stages.assets.layouts`): the input's own where it is usable,
else a second set where the input holds one (a glTF document), else an atlas (``auto``, the
default, records why); always the input's (``keep``), always a second set (``second``) or always
an atlas (``atlas``).

The field is evaluated at every covered texel centre (base colour, roughness, specular colour and
the predicted normal in tangent space), the ambient occlusion is written into the
metallic-roughness texture's red channel where the field was trained with shadows
(``bake.occlusion``; :func:`~stages.assets.baking.occlusion_decision`), the learned light's
environment (its SG lobes) is written as an equirectangular image (``light.exr`` and ``light.hdr``)
and its suns as distant lights (``meta.json``'s ``distant_lights``), and the baked asset is
rendered back from the evaluation views and compared with the field's own renders (PSNR over object
pixels). Conventions (texel centres,
``st``, the tangent frame) are in :mod:`stages.assets.baking`.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import torch

from .assets.baking import (
    bake_field,
    decode_textures,
    occlusion_decision,
    occlusion_samples,
    render_baked_views,
    render_texture_sets,
    texel_density,
)
from .assets.layouts import SECOND, InputMesh, choose_layout, second_layout
from .config.records import BakeRecord
from .config.sections import UV_LAYOUT_WORDS, BakeSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.progress import heartbeat, job_label
from .core.provenance import ORIGIN_KEY, Timer, metadata, staged_outputs, write_json_atomic
from .core.safefiles import atomic_stream
from .geometry.meshio import load_ply
from .geometry.raycache import RayCache
from .geometry.uvlayout import density_percentiles
from .imaging.images import compose, gather_points, global_spec
from .imaging.quality import psnr
from .imaging.sheets import save_png
from .imaging.views import ViewStore, radiance_at_hits
from .model.checkpoint import load_field
from .render.color import linear_to_srgb, to_u8
from .render.hdrio import write_exr, write_hdr

log = logging.getLogger(__name__)


def run(
    mesh_path: Path,
    field_path: Path,
    eval_path: Path,
    out_dir: Path,
    settings: BakeSettings,
    device: str = "cpu",
    source: InputMesh | None = None,
) -> dict:
    """Bake ``field_path`` onto ``mesh_path`` (normalised from ``source``, whose UV layout
    ``bake.uv`` may keep) and write textures, light, atlas and metadata."""
    timer = Timer()
    for p in (mesh_path, field_path, eval_path):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the earlier stages first.")
    with timer("load"):
        mesh = load_ply(mesh_path)
        field, opt_settings = load_field(field_path, device)
        eval_cache = RayCache(eval_path)
    with timer("layout"):
        source = source or InputMesh(None, None)
        size = settings.size_for(len(mesh.faces))
        uv, layout = choose_layout(settings.uv, source.path, source.transform(), mesh, size, settings.uv_max_overlap)
        if uv.layout == SECOND:
            layout = second_layout(layout, mesh, size, settings.padding, settings.max_chart_share)
            uv = dataclasses.replace(uv, made=layout.check)
    job = job_label("bake", out_dir)
    occlusion = occlusion_decision(settings.occlusion, field, eval_cache)
    with timer("occlusion"), heartbeat(job, "tracing the ambient occlusion"):
        ao = occlusion_samples(mesh, occlusion, settings)
    verb = {"kept": "baking the input's own layout of", SECOND: "unwrapping and baking a second UV set of"}.get(
        uv.layout, "unwrapping and baking"
    )
    with timer("bake"), heartbeat(job, f"{verb} {len(mesh.faces)} faces"):
        res = bake_field(mesh, field, settings, device, ao, layout)
    out_dir = Path(out_dir)
    with staged_outputs(out_dir) as staging:
        with timer("write"):
            for folder, images in {"": res.textures, **res.sets}.items():
                for name, img in images.items():
                    save_png(staging / "textures" / folder / f"{name}.png", img)
            write_exr(staging / "light.exr", res.light_equirect)
            write_hdr(staging / "light.hdr", res.light_equirect)
            with atomic_stream(staging / "atlas.npz") as fh:
                kept = {} if layout is None else {"source_face": layout.source_face}
                np.savez(fh, uv=res.atlas.uv.astype(np.float32), **res.frames.arrays(), **kept)
        # fidelity: baked asset vs neural field from the evaluation views
        with timer("fidelity"), heartbeat(job, "rendering the baked asset for the fidelity check"):
            bake_psnr = fidelity(res, layout, field, eval_cache, settings.eval_width, device, staging / "preview.png")
        stats = {
            **BakeRecord(
                texture_size=res.atlas.size, bake_psnr_db=bake_psnr, uv_layout=uv.record()["layout"], uv_why=uv.why
            ).stats(),
            "charts": res.atlas.charts,
            "atlas_utilization": res.atlas.utilization,
            "texel_coverage": res.coverage,
            "faces": len(mesh.faces),
            # which UV layout the textures use, and why (bake.uv)
            "uv": uv.record(),
            "texels_per_area": texel_density(res, mesh),
            # how evenly the layout spends them: per face, at percentiles of the surface area
            "texels_per_area_percentiles": density_percentiles(mesh.vertices, mesh.faces, res.atlas.uv, res.atlas.size),
            # the BRDF the textures hold (optimize.brdf): the exporters map them accordingly
            "brdf": field.brdf.name,
            # the learned suns, which light.exr leaves out: the assets carry them as lights
            "distant_lights": [d.record() for d in res.distant],
            # the ambient occlusion map in metallic_roughness.png's red channel (bake.occlusion)
            "occlusion": {**occlusion, **(ao.summary() if ao is not None else {})},
            "bake_psnr_pixels": "object pixels of the evaluation views, sRGB, baked textures vs neural field",
        }
        log.info(
            "baked %d faces into %d^2 textures (%s, %s; %.0f%% texels used), fidelity %.1f dB",
            len(mesh.faces),
            res.atlas.size,
            UV_LAYOUT_WORDS[uv.layout],
            uv.why,
            100 * res.coverage,
            bake_psnr,
        )
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="bake",
                settings=settings.to_dict(),
                inputs={"mesh": mesh_path, "field": field_path, "eval": eval_path},
                outputs={
                    "textures": out_dir / "textures",
                    "light": out_dir / "light.exr",
                    "atlas": out_dir / "atlas.npz",
                },
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, "optimize_settings": opt_settings.to_dict(), ORIGIN_KEY: field.origin},
            ),
        )
    return stats


def fidelity(res, layout, field, eval_cache: RayCache, width: int, device: str, preview: Path) -> float:
    """The bake's PSNR (sRGB, object pixels of the evaluation views) against the neural field, both
    unshadowed, with the baked asset's front view written to ``preview`` (``width`` pixels): the
    textures read as a viewer reads them (a kept layout's repeating, one set per group of slots)."""
    store = ViewStore(eval_cache, torch.device(device), field.normals, shadows=False)
    light = field.light()
    if layout is None:
        tex = decode_textures(res.textures)
        baked = render_baked_views(eval_cache, res.atlas.uv, tex, res.frames, light, device, field.specular_lobe, field.brdf)
    else:
        sets = [decode_textures(res.textures), *(decode_textures(res.sets[ts.folder]) for ts in layout.sets[1:])]
        lobe, brdf = field.specular_lobe, field.brdf
        baked = render_texture_sets(eval_cache, res.atlas.uv, sets, layout.face_set, res.frames, light, device, lobe, brdf)
    preds = [linear_to_srgb(b) for b in baked]
    refs = [linear_to_srgb(r) for r in radiance_at_hits(field, store)]
    # the preview: the baked asset from the evaluation view nearest the anchor (front) view
    front = eval_cache.front_view()
    spec = global_spec(store.width, width)
    needed, (lookup,) = gather_points([spec], store[front].index)
    bg = torch.ones(3, width, width, device=preds[front].device)
    img = compose(preds[front][torch.from_numpy(needed)], lookup, spec, bg)
    save_png(preview, to_u8(img.permute(1, 2, 0).cpu().numpy()))
    return psnr(torch.cat(preds), torch.cat(refs))


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--mesh", required=True, type=Path, help="the traced mesh (.ply)")
        parser.add_argument("--field", required=True, type=Path, help="trained field (field.pt)")
        parser.add_argument("--eval", required=True, type=Path, help="evaluation ray cache (.npz)")
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--settings", default="{}", help="JSON of the bake settings")
        parser.add_argument("--source", help="the input mesh (file or builtin:<name>) whose UV layout bake.uv may keep")
        parser.add_argument("--transform", type=Path, help="the normalisation's transform.json (with --source)")

    def body(args):
        source = InputMesh(args.source, args.transform)
        run(args.mesh, args.field, args.eval, args.out_dir, BakeSettings.from_json(args.settings), args.device, source)

    return stage_main("bake", __doc__, arguments, body, argv, device="cpu")


if __name__ == "__main__":
    raise SystemExit(main())
