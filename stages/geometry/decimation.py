"""Quadric edge collapse (MeshLab, via pymeshlab) to a target face count, with welding first.

Used for the robustness study (TANGO Sec. 4.2: meshes decimated to 5,000 faces). The input is the
*normalised* mesh and the output stays in that same frame: the decimated mesh shares the
normalised mesh's inverse transform, so both levels overlay exactly, the same cameras see the same
object, and exports of either level return to the same original units.

Why not normalise again after decimating: the paper's normalisation uses the *vertex* centroid,
which depends on where vertices are dense, and decimation redistributes them. Measured on the
built-in candle at 5,000 faces, the vertex centroid moves by 0.18 (18% of the radius) while the
surface itself moves by at most the Hausdorff distance (0.002). Re-normalising would shift the
decimated object against the original and spoil the side-by-side comparison. Instead the stage
records, and the tests check, what sharing the frame needs: the two-sided Hausdorff distance
``h``, the radius of the decimated mesh (within ``[1 - h, 1 + h]``) and the shift of the
area-weighted surface centroid (below ``h`` on every mesh we tried).

Welding. Meshes exported from DCC tools and glTF files are split at UV and normal seams: a vertex
on a seam is stored once per side, so the faces on either side share positions but no vertex,
and every seam edge is a boundary edge. With boundaries preserved, the collapse may not touch an
edge at a boundary vertex, so such a mesh stops far above the target (a mesh whose every face has
its own three vertices does not decimate at all). The stage therefore welds coincident vertices
first (``weld``): exact duplicates, and near duplicates closer than ``weld_tolerance`` times the
bounding-box diagonal (rounding on export; clusters are merged transitively, at the position of
their first vertex). Faces that welding makes degenerate are dropped; a mesh without duplicates
is left exactly as it was. Only the decimation input is welded: the original, unwelded mesh is
what the Hausdorff distances are measured against, and nothing downstream needs the seam split
(the bake charts the traced mesh itself, and the export splits vertices where its attributes differ). A mesh
already at or below the target is kept exactly as is.

The collapse. Boundaries are preserved (``preserveboundary``) and face flips are prevented
(``preservenormal``). If the collapse stops more than 1% above the target it is repeated on its
result while that still removes faces (re-initialised quadrics allow some collapses that were
refused). If it is still above the target on a mesh that is open after welding, and
``relax_boundary`` allows it, the welded mesh is collapsed again from scratch with boundary
vertices free to move (held near their boundary lines by MeshLab's boundary quadric) and with
topology preserved, so that no hole is closed and no component deleted (without topology
preservation MeshLab reaches any target by deleting whole triangles of a triangle soup). The
relaxed result is kept only if it reaches the target; otherwise the boundary-preserving one is,
and the stats record the choice and its reason. Why relax rather than fail: a mesh that is open
after welding (a terrain, a garment, a cut-away model) has boundaries by design, and with them
fixed it stops at about one face per boundary edge (a 200x200 grid: 796 faces for a target of
500). When the target still cannot be reached (a triangle soup, more holes than the face budget
allows, or welding or relaxation switched off), the stage logs a WARNING naming the mesh, the
target, the faces reached and the reason, and sets ``stats.target_reached = false`` and
``stats.target_shortfall_reason``. The two-sided Hausdorff distance between the original and the
decimated mesh is measured by MeshLab's sampler and recorded.

The face budget (``mode: budget``, :func:`face_budget`). A mesh with far more faces than its views
have pixels carries detail no view resolves: each face then covers a fraction of a pixel, the
ray cache stores the same hits, and only the bake (xatlas charts every face), the exports and
the tracing pay for it. The budget is the surface area over the area that ``pixels_per_face``
pixels cover where the surface can come nearest to the cameras of the finest of the cache's view
sets; a mesh above it is decimated to it, one within it passes unchanged. TANGO's robustness result (Sec. 4.2) is
that the normal network restores detail lost to decimation; docs/measurements/geometry.md measures the trade.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..config.sections import DecimateSettings, RaycacheSettings
from .meshio import TriMesh
from .normals import unit_face_normals, weld_positions

log = logging.getLogger(__name__)


def pixel_footprint(resolution: int, fov_deg: float, depth: float) -> float:
    """Side of one pixel, in scene units, on a surface facing a pinhole camera at ``depth`` (square
    image of ``resolution`` pixels across a full field of view of ``fov_deg``):
    ``2 depth tan(fov / 2) / resolution``. A pinhole maps a plane parallel to the image uniformly,
    so this holds for every pixel at that depth; surfaces tilted away from the camera, or
    deeper, get more scene per pixel, never less."""
    return 2.0 * depth * np.tan(np.radians(fov_deg) / 2.0) / resolution


@dataclass(frozen=True)
class FaceBudget:
    faces: int  # the budget
    area: float  # the mesh's surface area (normalised frame)
    footprint: float  # the finest pixel side over the cache's view sets
    depth: float  # the nearest the surface comes to that view set's cameras
    view_set: str  # which view set sets it
    pixels_per_face: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def face_budget(area: float, cache: RaycacheSettings, pixels_per_face: float = 1.0, extent: float = 1.0) -> FaceBudget:
    """The faces a mesh of surface ``area`` needs for the views of ``cache`` to resolve it:
    ``ceil(area / (pixels_per_face s^2))`` with ``s`` the finest :func:`pixel_footprint` any of
    its views (training, evaluation, metric) can have on the surface. Each view set's cameras lie
    on a sphere of its radius ``r`` around the origin, and the surface within ``extent`` of the
    origin (1 for a normalised mesh), so no surface point is nearer a camera than ``r - extent``:
    the footprint at that depth is a lower bound, and a face of budgeted size covers at least
    ``pixels_per_face`` pixels in every view. At least 4 faces. A view set whose cameras are
    within ``extent`` of the origin can come arbitrarily close to the surface: no budget then
    (``ValueError``; decimate to a face count instead)."""
    sets = {
        "training": (cache.resolution, cache.fov_deg, cache.radius),
        "evaluation": (cache.eval_resolution, cache.eval_fov_deg, cache.eval_radius),
        "metrics": (cache.metrics_resolution, cache.metrics_fov_deg, cache.metrics_radius),
    }
    inside = [name for name, (_, _, radius) in sets.items() if radius <= extent]
    if inside:
        raise ValueError(
            f"the {' and '.join(inside)} cameras are within the mesh's extent ({extent:.3g}) of its centre: "
            "they can come arbitrarily close to the surface, so no face budget bounds what they resolve; "
            "use decimate.mode: faces with a target_faces, or a larger camera radius"
        )
    footprint = {name: pixel_footprint(res, fov, radius - extent) for name, (res, fov, radius) in sets.items()}
    view_set = min(footprint, key=footprint.get)
    s = footprint[view_set]
    faces = max(4, int(np.ceil(area / (pixels_per_face * s * s))))
    return FaceBudget(faces, float(area), float(s), float(sets[view_set][2] - extent), view_set, float(pixels_per_face))


def mesh_face_budget(mesh: TriMesh, cache: RaycacheSettings, pixels_per_face: float = 1.0) -> FaceBudget:
    """:func:`face_budget` of ``mesh``: its surface area, its extent the farthest vertex from the origin."""
    extent = float(np.linalg.norm(mesh.vertices, axis=1).max())
    return face_budget(float(mesh.face_areas.sum()), cache, pixels_per_face, extent)


#: the collapse counts as having reached the target when it leaves at most this fraction more faces
TARGET_TOLERANCE = 0.01
#: boundary quadric weight of the relaxed collapse: MeshLab's default. Boundary vertices may move, and
#: this quadric (planes through the boundary edges, normal to their faces) keeps them near their boundary
#: lines. Heavier is worse, not better: on a 200x200 height-field grid decimated to 500 faces the
#: Hausdorff distance was 0.005 / 0.010 / 0.020 / 0.051 for weights 1 / 3 / 10 / 100
RELAXED_BOUNDARY_WEIGHT = 1.0
#: at most this many collapse calls per attempt (each further one needs >= 1% progress)
MAX_PASSES = 4


def _pymeshlab():
    try:
        import pymeshlab
    except ImportError as exc:  # pragma: no cover
        raise ImportError("the decimate stage needs pymeshlab: pip install pymeshlab") from exc
    return pymeshlab


@dataclass(frozen=True)
class DecimateResult:
    mesh: TriMesh
    stats: dict


@dataclass(frozen=True)
class WeldResult:
    """A welded mesh and what welding did: ``tolerance`` (absolute), vertices merged as exact and
    as near duplicates, faces dropped because welding made them degenerate."""

    mesh: TriMesh
    tolerance: float
    exact_merged: int
    near_merged: int
    faces_dropped: int


def weld_vertices(mesh: TriMesh, relative_tolerance: float = 1e-6) -> WeldResult:
    """Merge coincident vertices of ``mesh``: exact duplicates, then vertices closer than
    ``relative_tolerance`` times the bounding-box diagonal (transitively, at the position of the
    member that comes first in the input). Faces with a repeated vertex afterwards are dropped, and
    so are vertices no face uses; the order of vertices and faces is kept otherwise, so a mesh
    without duplicates comes back unchanged."""
    vertices = np.asarray(mesh.vertices, np.float64)
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0))) if len(vertices) else 0.0
    tolerance = float(relative_tolerance) * diagonal
    unique, inverse, exact_merged = weld_positions(vertices, relative_tolerance)
    near_merged = len(vertices) - exact_merged - len(unique)
    faces = inverse[mesh.faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    faces = faces[keep]
    used = np.unique(faces)
    remap = np.full(len(unique), -1, np.int64)
    remap[used] = np.arange(len(used))
    welded = TriMesh(unique[used], remap[faces])
    return WeldResult(welded, tolerance, int(exact_merged), int(near_merged), int((~keep).sum()))


def edge_counts(faces: np.ndarray) -> dict:
    """Boundary edges (one face), non-manifold edges (more than two faces) and connected
    components (through shared vertices) of a face array ``(F, 3)``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return {"boundary_edges": 0, "nonmanifold_edges": 0, "components": 0}
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    n = int(faces.max()) + 1
    _, counts = np.unique(edges[:, 0] * n + edges[:, 1], return_counts=True)
    graph = coo_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return {
        "boundary_edges": int((counts == 1).sum()),
        "nonmanifold_edges": int((counts > 2).sum()),
        "components": len(np.unique(labels[np.unique(faces)])),
    }


#: a sliver: a face whose smallest angle is below this (degrees)
SLIVER_DEG = 10.0
#: a fold: an edge whose two faces' normals differ by more than this (degrees)
FOLD_DEG = 120.0


def shape_quality(mesh: TriMesh) -> dict:
    """What a collapse can do to a mesh's faces, as shares: ``slivers`` (faces whose smallest
    angle is below :data:`SLIVER_DEG`; degenerate faces count) and ``folds`` (manifold edges whose
    two faces' unit normals differ by more than :data:`FOLD_DEG`: a crease folded back on itself,
    or a flipped face), and ``min_angle_deg_p1`` (the 1st percentile of the faces' smallest
    angles)."""
    tri = np.asarray(mesh.vertices, np.float64)[mesh.faces]
    smallest = np.full(len(tri), 180.0)
    for i in range(3):
        a, b = tri[:, (i + 1) % 3] - tri[:, i], tri[:, (i + 2) % 3] - tri[:, i]
        norms = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
        cos = np.divide((a * b).sum(1), norms, out=np.ones(len(tri)), where=norms > 0)
        smallest = np.minimum(smallest, np.where(norms > 0, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), 0.0))
    normals = unit_face_normals(mesh.vertices, mesh.faces)
    edges = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    order = np.lexsort(edges.T[::-1])
    e, f = edges[order], np.repeat(np.arange(len(mesh.faces)), 3)[order]
    pair = np.all(e[1:] == e[:-1], axis=1)
    pair[1:] &= ~pair[:-1]  # an edge of three or more faces counts its first pair once
    cos = (normals[f[1:][pair]] * normals[f[:-1][pair]]).sum(1)
    return {
        "slivers": float((smallest < SLIVER_DEG).mean()) if len(tri) else 0.0,
        "folds": float((cos < np.cos(np.radians(FOLD_DEG))).mean()) if len(cos) else 0.0,
        "min_angle_deg_p1": float(np.percentile(smallest, 1)) if len(tri) else 0.0,
    }


def surface_centroid(mesh: TriMesh) -> np.ndarray:
    """Area-weighted centroid ``(3,)`` of the surface (insensitive to vertex density)."""
    areas = mesh.face_areas
    return (mesh.vertices[mesh.faces].mean(axis=1) * areas[:, None]).sum(0) / areas.sum()


def _add(ms, mesh: TriMesh, name: str) -> int:
    """Add ``mesh`` to the MeshSet ``ms`` as its current mesh; returns its id."""
    pymeshlab = _pymeshlab()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=mesh.vertices, face_matrix=mesh.faces.astype(np.int32)), name)
    return ms.current_mesh_id()


def _collapse(ms, mesh: TriMesh, settings: DecimateSettings, limit: int, *, relaxed: bool) -> tuple[int, list[int]]:
    """Add ``mesh`` to ``ms`` and collapse it towards the target, repeating while above ``limit``
    faces and still making progress; returns its mesh id and the face count after each call."""
    mesh_id = _add(ms, mesh, "relaxed" if relaxed else "decimated")
    counts: list[int] = []
    faces = len(mesh.faces)
    for _ in range(MAX_PASSES):
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=int(settings.target_faces),
            qualitythr=float(settings.quality_threshold),
            preserveboundary=bool(settings.preserve_boundary) and not relaxed,
            boundaryweight=RELAXED_BOUNDARY_WEIGHT if relaxed else 1.0,
            preservenormal=bool(settings.preserve_normal),
            preservetopology=relaxed,
            optimalplacement=True,
            planarquadric=True,
            autoclean=True,
        )
        previous, faces = faces, ms.current_mesh().face_number()
        counts.append(faces)
        if faces <= limit or faces > previous - max(1, previous // 100):
            break
    ms.meshing_remove_unreferenced_vertices()
    return mesh_id, counts


def _shortfall_reason(
    mesh: TriMesh, settings: DecimateSettings, weld: dict, edges: dict, strict: list[int], relaxed: list[int]
) -> str:
    """Why the collapse stopped above the target, from what the attempts and the welded mesh show."""
    if not settings.weld and edges["boundary_edges"]:
        would = weld_vertices(mesh, settings.weld_tolerance)
        why = (
            f"welding is off (weld: false) and {edges['boundary_edges']} edges are boundary edges; welding would merge "
            f"{would.exact_merged + would.near_merged} vertices and leave {edge_counts(would.mesh.faces)['boundary_edges']} "
            "boundary edges: set weld: true"
        )
    elif edges["boundary_edges"] and settings.preserve_boundary and not settings.relax_boundary:
        why = (
            f"{edges['boundary_edges']} boundary edges remain after welding and boundary vertices may not move "
            "(preserve_boundary: true, relax_boundary: false): set relax_boundary: true"
        )
    elif relaxed:
        why = (
            f"with boundaries preserved the collapse stops at {strict[-1]} faces, and with them relaxed at {relaxed[-1]} "
            f"(topology kept: no hole closed, no component deleted); the welded mesh has {edges['components']} connected "
            f"components and {edges['boundary_edges']} boundary edges"
        )
    else:
        why = (
            f"MeshLab's collapse stops at {strict[-1]} faces (preserve_normal: {settings.preserve_normal}; "
            f"{edges['components']} connected components, {edges['boundary_edges']} boundary edges after welding)"
        )
    merged = weld["exact_duplicates_merged"] + weld["near_duplicates_merged"]
    if merged:
        why += f"; welding merged {merged} vertices"
    return why


def _weld_record(settings: DecimateSettings, welding, after: dict) -> dict:
    """What the statistics say of the welding (``welding``: None when it is off)."""
    return {
        "enabled": bool(settings.weld),
        "tolerance_relative": float(settings.weld_tolerance),
        "tolerance_absolute": welding.tolerance if welding else 0.0,
        "exact_duplicates_merged": welding.exact_merged if welding else 0,
        "near_duplicates_merged": welding.near_merged if welding else 0,
        "degenerate_faces_dropped": welding.faces_dropped if welding else 0,
        "nonmanifold_edges_after": after["nonmanifold_edges"],
        "components_after": after["components"],
    }


@dataclass
class Collapse:
    """The collapse's outcome: the decimated mesh's id in the MeshSet, the face counts of its
    passes with boundaries preserved (``strict``) and, where those stopped above the target, with
    them relaxed, whether the relaxed result was taken, and why the boundaries were relaxed."""

    mesh_id: int
    strict: list[int] = field(default_factory=list)
    relaxed: list[int] = field(default_factory=list)
    boundary_relaxed: bool = False
    relaxation_reason: str | None = None


def _collapse_to(ms, welded: TriMesh, settings: DecimateSettings, limit: int, boundary_edges: int, name: str) -> Collapse:
    """Collapse ``welded`` to ``limit`` faces with boundaries preserved; if that stops above it and
    ``relax_boundary`` allows, again with boundary vertices free to slide, keeping the relaxed
    result only where it reaches the target."""
    dec_id, strict = _collapse(ms, welded, settings, limit, relaxed=False)
    result = Collapse(dec_id, strict)
    if not (strict[-1] > limit and settings.preserve_boundary and settings.relax_boundary and boundary_edges):
        return result
    target = int(settings.target_faces)
    result.relaxation_reason = (
        f"with boundaries preserved the collapse stopped at {strict[-1]} faces (target {target}): "
        f"{boundary_edges} boundary edges remain after welding"
    )
    relaxed_id, result.relaxed = _collapse(ms, welded, settings, limit, relaxed=True)
    if result.relaxed[-1] <= limit:
        result.mesh_id, result.boundary_relaxed = relaxed_id, True
        log.info("%s: %s; collapsed again with boundaries relaxed: %d faces", name, result.relaxation_reason, result.relaxed[-1])
    else:
        result.relaxation_reason += (
            f"; with boundaries relaxed it stopped at {result.relaxed[-1]} faces, also above the target: "
            "the boundary-preserving result is kept"
        )
    return result


def decimate_mesh(mesh: TriMesh, settings: DecimateSettings, name: str = "mesh") -> DecimateResult:
    """Weld, then quadric edge collapse of ``mesh`` to ``settings.target_faces``; Hausdorff both ways.

    Returns the decimated mesh (``vertices (V', 3) float64, faces (F', 3) int64``) in the same
    frame as the input, and statistics: faces before/after, Hausdorff max/mean/RMS from the
    original (unwelded) to the decimated surface and back (in the normalised frame, radius 1),
    what welding did (vertices and boundary edges before/after), the collapse passes, and
    ``target_reached`` / ``target_shortfall_reason``. A shortfall is logged as a WARNING naming
    ``name``.
    """
    ms = _pymeshlab().MeshSet()
    original_id = _add(ms, mesh, "original")
    target = int(settings.target_faces)
    limit = int(np.floor(target * (1 + TARGET_TOLERANCE)))
    faces_before = len(mesh.faces)
    before = edge_counts(mesh.faces)
    if settings.weld:
        welding = weld_vertices(mesh, settings.weld_tolerance)
        welded = welding.mesh
    else:
        welding, welded = None, mesh
    after = edge_counts(welded.faces) if welding else before
    weld_stats = _weld_record(settings, welding, after)
    skipped = faces_before <= target
    if skipped:
        log.info("%s has %d faces <= target %d: kept as is", name, faces_before, target)
        collapse = Collapse(_add(ms, mesh, "decimated"))
    elif len(welded.faces) <= target:
        log.info("%s has %d faces <= target %d after welding: welded mesh kept", name, len(welded.faces), target)
        collapse = Collapse(_add(ms, welded, "decimated"))
    else:
        collapse = _collapse_to(ms, welded, settings, limit, after["boundary_edges"], name)
    dec_id, strict, relaxed = collapse.mesh_id, collapse.strict, collapse.relaxed
    dec = ms.mesh(dec_id)
    out = TriMesh(np.asarray(dec.vertex_matrix(), np.float64), np.asarray(dec.face_matrix(), np.int64))
    faces_after = len(out.faces)
    target_reached = faces_after <= limit
    reason = None if target_reached else _shortfall_reason(mesh, settings, weld_stats, after, strict, relaxed)
    if reason:
        log.warning(
            "%s: decimation did NOT reach the target: %d faces reached for a target of %d (from %d): %s",
            name,
            faces_after,
            target,
            faces_before,
            reason,
        )
    n = settings.hausdorff_samples
    fwd = ms.get_hausdorff_distance(sampledmesh=original_id, targetmesh=dec_id, samplevert=True, sampleface=True, samplenum=n)
    bwd = ms.get_hausdorff_distance(sampledmesh=dec_id, targetmesh=original_id, samplevert=True, sampleface=True, samplenum=n)
    radius = np.linalg.norm(out.vertices, axis=1)
    stats = {
        "faces_before": faces_before,
        "faces_after": faces_after,
        "vertices_before": len(mesh.vertices),
        "vertices_after": len(out.vertices),
        "skipped": skipped,
        "target_faces": target,
        "relative_error_to_target": (faces_after - target) / target,
        "target_reached": bool(target_reached),
        "target_shortfall_reason": reason,
        "vertices_before_weld": len(mesh.vertices),
        "vertices_after_weld": len(welded.vertices),
        "boundary_edges_before_weld": before["boundary_edges"],
        "boundary_edges_after_weld": after["boundary_edges"],
        "faces_after_weld": len(welded.faces),
        "weld": weld_stats,
        "collapse_passes": strict,
        "boundary_relaxed": collapse.boundary_relaxed,
        "boundary_relaxation_reason": collapse.relaxation_reason,
        "collapse_passes_relaxed": relaxed,
        "hausdorff_original_to_decimated": {k: float(fwd[k]) for k in ("max", "mean", "RMS")},
        "hausdorff_decimated_to_original": {k: float(bwd[k]) for k in ("max", "mean", "RMS")},
        "hausdorff_max": float(max(fwd["max"], bwd["max"])),
        "hausdorff_units": "normalised frame (unit sphere)",
        "vertex_centroid_after": out.vertices.mean(0).tolist(),
        "surface_centroid_shift": float(np.linalg.norm(surface_centroid(out) - surface_centroid(mesh))),
        "radius_after": float(radius.max()),
        "degenerate_faces_after": int((out.face_areas <= 1e-14).sum()),
        "shape_before": shape_quality(mesh),
        "shape_after": shape_quality(out),
    }
    return DecimateResult(out, stats)
