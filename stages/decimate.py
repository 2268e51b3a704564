"""decimate: quadric edge collapse (MeshLab, via pymeshlab) to a target face count.

Used for the robustness study (TANGO Sec. 4.2: meshes decimated to 5,000 faces), and with
``mode: budget`` to the face budget of the mesh's ray cache (a mesh within it passes unchanged). The output stays
in the normalised mesh's frame, welds seams first, and relaxes boundaries when a preserved boundary
stops the collapse above the target; why, and what the stats record, is in
:mod:`stages.geometry.decimation`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

from .config.records import DecimateRecord
from .config.sections import DecimateSettings, RaycacheSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import Timer, atomic_path, metadata, write_json_atomic
from .geometry.decimation import decimate_mesh, mesh_face_budget
from .geometry.meshio import load_ply, save_ply

log = logging.getLogger(__name__)


def run(
    in_mesh: Path, out_mesh: Path, out_meta: Path, settings: DecimateSettings, raycache: RaycacheSettings | None = None
) -> dict:
    """Decimate ``in_mesh`` to ``settings.target_faces``, with ``mode: share`` to
    ``settings.target_share`` of its faces, or with ``mode: budget`` to the face budget of the ray
    cache ``raycache`` (required then)."""
    timer = Timer()
    with timer("load"):
        if not Path(in_mesh).is_file():
            raise StageInputError(in_mesh, "file not found", "Run the normalize stage first.")
        mesh = load_ply(in_mesh)
    budget = None
    if settings.mode == "share":
        settings = dataclasses.replace(settings, target_faces=max(4, round(settings.target_share * len(mesh.faces))))
        log.info("%s: %d faces, target %.3g of them: %d", in_mesh, len(mesh.faces), settings.target_share, settings.target_faces)
    if settings.mode == "budget":
        if raycache is None:
            why = "decimate.mode is budget but no ray-cache settings were given"
            raise StageInputError(in_mesh, why, "Pass --raycache-settings (the workflow does).")
        try:
            budget = mesh_face_budget(mesh, raycache, settings.pixels_per_face)
        except ValueError as exc:
            raise StageInputError(in_mesh, str(exc), "Set decimate.mode: faces for this mesh.") from exc
        settings = dataclasses.replace(settings, target_faces=budget.faces)
        log.info(
            "%s: face budget %d (area %.4g over %.3g pixels of side %.4g, %s views at depth %.3g); the mesh has %d faces",
            in_mesh,
            budget.faces,
            budget.area,
            budget.pixels_per_face,
            budget.footprint,
            budget.view_set,
            budget.depth,
            len(mesh.faces),
        )
    with timer("decimate"):
        result = decimate_mesh(mesh, settings, name=str(in_mesh))
    with timer("write"):
        with atomic_path(out_mesh) as tmp:
            save_ply(tmp, result.mesh)
    s = result.stats
    log.info(
        "%s: %d -> %d faces (target %d, %s), Hausdorff max %.3g (unit sphere); welding: %d -> %d vertices, "
        "%d -> %d boundary edges",
        in_mesh,
        s["faces_before"],
        s["faces_after"],
        settings.target_faces,
        "reached" if s["target_reached"] else "NOT reached",
        s["hausdorff_max"],
        s["vertices_before_weld"],
        s["vertices_after_weld"],
        s["boundary_edges_before_weld"],
        s["boundary_edges_after_weld"],
    )
    write_json_atomic(
        out_meta,
        metadata(
            stage="decimate",
            settings={**settings.to_dict(), **({"raycache": raycache.to_dict()} if budget else {})},
            inputs={"mesh": in_mesh},
            outputs={"mesh": out_mesh},
            timings={**timer.seconds, "total": timer.total()},
            extra={
                "stats": {
                    **s,
                    **DecimateRecord(
                        faces_after=s["faces_after"],
                        target_faces=s.get("target_faces"),
                        target_reached=s.get("target_reached"),
                        target_shortfall_reason=s.get("target_shortfall_reason"),
                    ).stats(),
                },
                "face_budget": budget.to_dict() if budget else None,
                "frame": "same as the input (normalised mesh); reuse its transform",
            },
        ),
    )
    return s


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--input", required=True, type=Path, help="normalised mesh (.ply)")
        parser.add_argument("--mesh", required=True, type=Path, help="output decimated mesh (.ply)")
        parser.add_argument("--meta", required=True, type=Path, help="output metadata (.json)")
        parser.add_argument("--settings", default="{}", help="JSON of the decimate settings")
        parser.add_argument("--raycache-settings", default=None, help="JSON of the mesh's ray-cache settings (mode budget)")

    def body(args):
        raycache = RaycacheSettings.from_dict(json.loads(args.raycache_settings)) if args.raycache_settings else None
        run(args.input, args.mesh, args.meta, DecimateSettings.from_json(args.settings), raycache)

    return stage_main("decimate", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
