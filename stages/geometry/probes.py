"""The smallest real use of each geometry tool, for the doctor (``python -m stages.doctor``): a
tool that imports but cannot do its job (a wheel built for another CPU, a missing shared
library) is found in a second, not three hours into a run. Each probe returns one line of what
it did and raises when the tool fails."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config.sections import DecimateSettings
from .atlas import unwrap
from .decimation import decimate_mesh
from .meshio import TriMesh
from .tracing import EmbreeTracer

#: the probes' sphere: radius and icosphere subdivisions (320 faces at 2)
PROBE_RADIUS = 0.8


def probe_sphere(subdivisions: int = 2) -> TriMesh:
    """An icosphere of radius :data:`PROBE_RADIUS` at the origin (``20 * 4**subdivisions`` faces)."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=PROBE_RADIUS)
    return TriMesh(np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64))


def probe_embree() -> str:
    """Rays from ``(0, 0, 3)`` towards the sphere's centre area: every ray hits at the depth of
    the ray-sphere intersection (within the facets' sagitta) and rays past it miss."""
    mesh = probe_sphere(3)
    xs = np.linspace(-0.5, 0.5, 8)
    origins = np.array([[x, y, 3.0] for x in xs for y in xs] + [[2.0, 2.0, 3.0]])
    directions = np.tile([0.0, 0.0, -1.0], (len(origins), 1))
    hits = EmbreeTracer(mesh).trace(origins, directions)
    r2 = (origins[:-1, :2] ** 2).sum(1)
    want = 3.0 - np.sqrt(PROBE_RADIUS**2 - r2)
    if (hits.face[:-1] < 0).any() or hits.face[-1] >= 0:
        raise RuntimeError("Embree missed the probe sphere or hit beside it")
    err = float(np.abs(hits.depth[:-1] - want).max())
    if err > 0.02:
        raise RuntimeError(f"Embree's hit depths are {err:.3g} off the sphere's")
    return f"{len(origins)} rays traced, depths within {err:.1e} of the analytic sphere"


def probe_pymeshlab() -> str:
    """Quadric edge collapse of a 1,280-face sphere to 200 faces."""
    result = decimate_mesh(probe_sphere(3), DecimateSettings(enabled=True, target_faces=200, hausdorff_samples=1000))
    faces = len(result.mesh.faces)
    if not 0 < faces <= 220:
        raise RuntimeError(f"pymeshlab decimated 1280 faces to {faces}, not about 200")
    return f"decimated 1,280 faces to {faces}"


def probe_xatlas() -> str:
    """A 320-face sphere unwrapped into a 64-texel atlas: every UV in [0, 1]."""
    atlas = unwrap(probe_sphere(2), 64, 2)
    if not (np.isfinite(atlas.uv).all() and atlas.uv.min() >= 0.0 and atlas.uv.max() <= 1.0):
        raise RuntimeError("xatlas returned texture coordinates outside [0, 1]")
    return f"unwrapped 320 faces into {atlas.charts} chart(s)"


def write_probe_glb(path: Path) -> Path:
    """A tiny binary glTF (a 320-face sphere with a metallic-roughness material) at ``path``,
    written by trimesh (not by our exporter: the probes test the tools, not our code)."""
    import trimesh

    mesh = probe_sphere(2)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    tm.visual = trimesh.visual.TextureVisuals(
        material=trimesh.visual.material.PBRMaterial(
            baseColorFactor=[200, 150, 100, 255], metallicFactor=0.0, roughnessFactor=0.6
        )
    )
    tm.export(path, file_type="glb")
    return path


#: faces of the probe GLB (for the probes that read it back)
PROBE_GLB_FACES = 320
#: a probe's time limit, seconds (Blender's first start reads a 370 MB module)
PROBE_TIMEOUT_S = 180.0
