"""normalize: put a mesh into the unit sphere (TANGO Sec. 3.1) and record the inverse transform.

The transform and its conventions are :mod:`stages.geometry.normalization`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from .config.records import NormalizeRecord
from .config.sections import NormalizeSettings
from .core.cli import stage_main
from .core.provenance import Timer, atomic_path, metadata, write_json_atomic
from .geometry.meshio import save_ply
from .geometry.normalization import normalize_mesh

log = logging.getLogger(__name__)


def run(source: str, out_mesh: Path, out_transform: Path, out_meta: Path, settings: NormalizeSettings) -> None:
    """Normalise ``source`` and write mesh, inverse transform and metadata, each atomically."""
    timer = Timer()
    with timer("normalize"):
        result = normalize_mesh(source, settings)
    with timer("write"):
        with atomic_path(out_mesh) as tmp:
            save_ply(tmp, result.mesh)
        write_json_atomic(out_transform, {"source": str(source), **result.transform.to_json()})
    log.info(
        "%s: %d vertices, %d faces; radius %.6g -> 1, centroid -> 0",
        source,
        result.stats["vertices"],
        result.stats["faces"],
        result.stats["original_radius"],
    )
    timings = {**timer.seconds, "total": timer.total()}
    inputs = {"mesh": source}
    write_json_atomic(
        out_meta,
        metadata(
            stage="normalize",
            settings=settings.to_dict(),
            inputs=inputs,
            outputs={"mesh": out_mesh, "transform": out_transform},
            timings=timings,
            extra={"stats": {**result.stats, **NormalizeRecord(faces=result.stats["faces"]).stats()}},
        ),
    )


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--input", required=True, help="mesh file (OBJ/PLY/STL/OFF/GLB/GLTF) or builtin:<name>")
        parser.add_argument("--mesh", required=True, type=Path, help="output normalised mesh (.ply)")
        parser.add_argument("--transform", required=True, type=Path, help="output inverse transform (.json)")
        parser.add_argument("--meta", required=True, type=Path, help="output metadata (.json)")
        parser.add_argument("--settings", default="{}", help="JSON of the normalize settings")

    def body(args):
        run(args.input, args.mesh, args.transform, args.meta, NormalizeSettings.from_json(args.settings))

    return stage_main("normalize", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
