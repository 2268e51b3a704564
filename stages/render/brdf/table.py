"""Rebuild a BRDF's shipped table of directional albedo and lobe moments by quadrature
(:func:`stages.render.specular_albedo.build_table`) into its ``table_path``:

    python -m stages.render.brdf.table --brdf gltf
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from ...core.safefiles import atomic_stream
from ..specular_albedo import NV_NODES, R_NODES, build_table
from . import get, names

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Rebuild the specular albedo table of a BRDF by quadrature.")
    parser.add_argument("--brdf", choices=names(), default=names()[0])
    parser.add_argument("--out", type=Path, default=None, help="default: the shipped table of --brdf")
    args = parser.parse_args(argv)
    brdf = get(args.brdf)
    out = args.out or brdf.table_path
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    table = build_table(brdf)
    with atomic_stream(out) as fh:
        np.savez_compressed(fh, **table)
    log.info("wrote %s (%d x %d)", out, NV_NODES, R_NODES)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
