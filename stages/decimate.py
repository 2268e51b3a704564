"""decimate: quadric edge collapse (MeshLab, via pymeshlab) to a target face count.

Used for the robustness study (TANGO Sec. 4.2: meshes decimated to 5,000 faces). The output stays
in the normalised mesh's frame, welds seams first, and relaxes boundaries when a preserved boundary
stops the collapse above the target; why, and what the stats record, is in
:mod:`stages.geometry.decimation`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from .config.sections import DecimateSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import Timer, atomic_path, metadata, write_json_atomic
from .geometry.decimation import decimate_mesh
from .geometry.meshio import load_ply, save_ply

log = logging.getLogger(__name__)


def run(in_mesh: Path, out_mesh: Path, out_meta: Path, settings: DecimateSettings) -> dict:
    timer = Timer()
    with timer("load"):
        if not Path(in_mesh).is_file():
            raise StageInputError(in_mesh, "file not found", "Run the normalize stage first.")
        mesh = load_ply(in_mesh)
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
            settings=settings.to_dict(),
            inputs={"mesh": in_mesh},
            outputs={"mesh": out_mesh},
            timings={**timer.seconds, "total": timer.total()},
            extra={"stats": s, "frame": "same as the input (normalised mesh); reuse its transform"},
        ),
    )
    return s


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--input", required=True, type=Path, help="normalised mesh (.ply)")
        parser.add_argument("--mesh", required=True, type=Path, help="output decimated mesh (.ply)")
        parser.add_argument("--meta", required=True, type=Path, help="output metadata (.json)")
        parser.add_argument("--settings", default="{}", help="JSON of the decimate settings")

    def body(args):
        run(args.input, args.mesh, args.meta, DecimateSettings.from_json(args.settings))

    return stage_main("decimate", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
