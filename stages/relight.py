"""relight: re-render a finished result under another environment map, and edit its material.

The environment map (an equirectangular ``.hdr`` or ``.exr``, or ``builtin:<name>`` for a
procedural one, see :mod:`stages.envmap`) is fitted by SG lobes (least squares over the sphere),
so the same closed-form renderer applies. Outputs: ``relit.png`` (the evaluation views under the
new light), ``material_edit.png`` (TANGO's material-editing figure: one view, rows = roughness
scales, columns = specular scales, under the new light), ``light_fit.png`` (the map and its SG fit)
and ``meta.json`` (fit error, mean brightness of each image).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .errors import StageInputError, stage_errors
from .provenance import (
    ORIGIN_KEY,
    Timer,
    add_torch_arguments,
    apply_torch_arguments,
    metadata,
    staged_outputs,
    write_json_atomic,
)
from .settings import Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class RelightSettings(Settings):
    """Settings of the relight stage (config section ``relight``)."""

    section = "relight"
    #: environment map: a .hdr/.exr path or builtin:sunset | builtin:overcast | builtin:night
    envmap: str = "builtin:sunset"
    #: SG lobes fitted to the map, and fitting iterations
    lobes: int = 64
    fit_iterations: int = 400
    #: material editing grid (TANGO Fig. 6): rows scale roughness, columns scale specular
    roughness_scales: tuple[float, ...] = (0.5, 1.0, 2.0)
    specular_scales: tuple[float, ...] = (0.0, 1.0, 2.0)
    width: int = 256


def load_env(spec: str) -> np.ndarray:
    from .envmap import PROCEDURAL, procedural_envmap
    from .hdrio import read_envmap

    if spec.startswith("builtin:"):
        name = spec.split(":", 1)[1]
        if name not in PROCEDURAL:
            raise StageInputError(spec, f"no procedural environment {name!r}", f"Use one of {', '.join(PROCEDURAL)}.")
        return procedural_envmap(name)
    return read_envmap(spec)


@torch.no_grad()
def render_edit(field, view, width: int, out: int, light, rough_scale: float = 1.0, spec_scale: float = 1.0):
    """One cached view rendered with ``light`` and scaled roughness/specular -> ``(3, out, out)``."""
    from .imaging import linear_to_srgb, render_cached_view
    from .render.shading import face_viewer, shade

    def colors(pts, nrm, v):
        flip = (nrm * v).sum(-1, keepdim=True) < 0
        n = torch.where(flip, -nrm, nrm)
        p = field.symmetric_points(pts)
        if field.normal_net is not None:
            n = field.normal_net(p, n)
        n = face_viewer(n, v)
        mat = field.svbrdf(p)
        s = r = None
        if mat.specular is not None:
            s = (mat.specular * spec_scale).clamp(0.0, 1.0)
            r = (mat.roughness * rough_scale).clamp(field.svbrdf.min_roughness, 1.0)
        return linear_to_srgb(shade(n, v, mat.albedo, light, s, r).rgb)

    return render_cached_view(view, width, out, colors)


def run(field_path: Path, eval_path: Path, out_dir: Path, settings: RelightSettings, device: str = "cpu") -> dict:
    from .envmap import fit_sg_light
    from .networks import equirect_directions
    from .optimize import ViewStore, contact_sheet, load_field, save_png, settings_eval_azimuths
    from .raycache import RayCache

    timer = Timer()
    for p in (field_path, eval_path):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the optimize stage first.")
    with timer("fit"):
        env = load_env(settings.envmap)
        light, rel_err = fit_sg_light(env, settings.lobes, settings.fit_iterations)
    dev = torch.device(device)
    light = type(light)(light.axis.to(dev), light.sharpness.to(dev), light.amplitude.to(dev))
    field, _ = load_field(field_path, dev)
    store = ViewStore(RayCache(eval_path), dev)
    out_dir = Path(out_dir)
    with staged_outputs(out_dir) as staging:
        with timer("render"):
            views = [render_edit(field, store[i], store.width, settings.width, light) for i in range(len(store))]
            save_png(staging / "relit.png", contact_sheet(views, len(settings_eval_azimuths(store))))
            front = _front_view(store)
            grid = [
                render_edit(field, store[front], store.width, settings.width, light, rs, ss)
                for rs in settings.roughness_scales
                for ss in settings.specular_scales
            ]
            save_png(staging / "material_edit.png", contact_sheet(grid, len(settings.specular_scales)))
            h, w = env.shape[:2]
            fit = light.radiance(equirect_directions(h, w).to(dev).reshape(-1, 3)).reshape(h, w, 3).cpu().numpy()
            top = max(float(env.max()), 1e-12)
            both = np.concatenate([env, fit], axis=0) / top
            from .bake import srgb_encode, to_u8

            save_png(staging / "light_fit.png", to_u8(srgb_encode(both)))
        stats = {
            "envmap": settings.envmap,
            "sg_fit_relative_rms": rel_err,
            "mean_relit": float(torch.stack(views).mean()),
            "mean_material_edit": [float(g.mean()) for g in grid],
            "front_view": front,
        }
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="relight",
                settings=settings.to_dict(),
                inputs={"field": field_path, "eval": eval_path},
                outputs={k: out_dir / f"{k}.png" for k in ("relit", "material_edit", "light_fit")},
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, ORIGIN_KEY: field.origin},
            ),
        )
    return stats


def _front_view(store) -> int:
    """The evaluation view closest to TANGO's front (anchor) direction."""
    from .cameras import camera_positions

    a = store.cache.arrays
    eyes = a["c2w"][:, :3, 3]
    front = camera_positions(1.96, 0.4, 1.0)
    return int(np.argmax(eyes @ front / np.linalg.norm(eyes, axis=1)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.relight", description=__doc__.split("\n")[0])
    parser.add_argument("--field", required=True, type=Path)
    parser.add_argument("--eval", required=True, type=Path)
    parser.add_argument("--out-dir", required=True, type=Path)
    parser.add_argument("--settings", default="{}")
    add_torch_arguments(parser, "cpu")
    args = parser.parse_args(argv)
    apply_torch_arguments(args)
    with stage_errors("relight") as status:
        run(args.field, args.eval, args.out_dir, RelightSettings.from_json(args.settings), args.device)
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
