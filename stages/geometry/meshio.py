"""Reading meshes (OBJ, PLY, STL, OFF, GLB/GLTF, or built-in) with checks that explain failures.

The reader keeps the mesh as it is (no vertex merging, no repair: non-manifold edges, boundaries
and duplicate faces are normal in real data); it only triangulates, flattens scenes into one mesh
and drops unreferenced vertices. Anything that cannot be a surface fails with a
:class:`~stages.core.errors.StageInputError` naming the file, the problem and a remedy.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.safefiles import DATA_LIMIT, atomic_stream, open_read, read_bytes, require_plain_file, user_file
from ..core.shipped import ensure_unpacked
from .normals import unit_face_normals
from .shapes import BUILTIN_NAMES, builtin_mesh
from .sourcemesh import read_gltf_file

log = logging.getLogger(__name__)

SUPPORTED_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
BUILTIN_PREFIX = "builtin:"


@dataclass(frozen=True)
class TriMesh:
    """A plain triangle mesh: ``vertices (V, 3) float64``, ``faces (F, 3) int64``."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def face_normals(self) -> np.ndarray:
        """``(F, 3) float64`` unit normals by the right-hand rule; zero for degenerate faces."""
        return unit_face_normals(self.vertices, self.faces)

    @property
    def face_areas(self) -> np.ndarray:
        tri = self.vertices[self.faces]
        return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def _trimesh():
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - exercised only without the dependency
        raise ImportError("reading meshes needs trimesh: pip install trimesh scipy") from exc
    return trimesh


def load_mesh(source: str | Path, given_in: str = "the config") -> TriMesh:
    """Load ``source`` (a mesh file, or ``builtin:<name>``) as one triangle mesh, checked.
    ``given_in``: where the user named it, for the errors' advice ("the config", "the command").

    Raises:
        StageInputError: missing or unreadable file, unsupported format, a GLB or glTF file that
            fails :func:`~stages.geometry.sourcemesh.read_gltf_file`'s checks, no faces (empty mesh
            or point cloud), faces indexing missing vertices, NaN/inf vertex coordinates, or only
            zero-area faces.
    """
    source_str = str(source)
    if source_str.startswith(BUILTIN_PREFIX):
        name = source_str[len(BUILTIN_PREFIX) :]
        if name not in BUILTIN_NAMES:
            raise StageInputError(
                source_str,
                f"no built-in mesh called {name!r}",
                f"Use one of: {', '.join(BUILTIN_NAMES)}.",
            )
        v, f = builtin_mesh(name)
        return check_mesh(TriMesh(v, f), source_str)

    path = Path(source)
    ensure_unpacked(path)  # a mesh that travels with the project compressed (meshes/*.obj.xz)
    if not path.exists():
        raise StageInputError(path, "file not found", f"Check the mesh path in {given_in}.")
    if not path.is_file():
        raise StageInputError(path, "is not a file", f"Point {given_in} at a mesh file.")
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise StageInputError(
            path,
            f"unsupported mesh format {suffix or '(no suffix)'!r}",
            f"Convert it to one of {', '.join(SUPPORTED_SUFFIXES)}.",
        )
    if path.stat().st_size == 0:
        raise StageInputError(path, "file is empty (0 bytes)", "Re-export or re-download the mesh.")
    require_plain_file(user_file(path), remedy=f"Point {given_in} at the mesh file itself.")
    if suffix in (".glb", ".gltf"):
        read_gltf_file(path)  # the container, buffers and accessors checked before trimesh parses them
    trimesh = _trimesh()
    try:
        loaded = trimesh.load(path, process=False, force=None)
    except Exception as exc:  # noqa: BLE001 - any parser failure is an unreadable file
        raise StageInputError(
            path,
            f"could not be read as {suffix[1:].upper()} ({type(exc).__name__}: {exc})",
            "Check that the file is a valid mesh, e.g. by opening it in MeshLab or Blender.",
        ) from exc
    mesh = _flatten(loaded, path)
    return check_mesh(mesh, str(path))


def _flatten(loaded, path: Path) -> TriMesh:
    """Turn whatever trimesh returned into one TriMesh (scenes: transforms applied, a mirroring
    one with its faces' winding turned back as viewers turn it, concatenated)."""
    trimesh = _trimesh()
    if isinstance(loaded, trimesh.Scene):
        parts = []
        for node in loaded.graph.nodes_geometry:
            transform, geom_name = loaded.graph[node]
            geom = loaded.geometry[geom_name]
            if isinstance(geom, trimesh.Trimesh) and len(geom.faces):
                v = trimesh.transform_points(np.asarray(geom.vertices, np.float64), transform)
                f = np.asarray(geom.faces, np.int64)
                # a mirroring node turns the winding back, as viewers do (the normals stay outward)
                parts.append((v, f[:, [0, 2, 1]] if np.linalg.det(np.asarray(transform)[:3, :3]) < 0 else f))
        if not parts:
            kinds = sorted({type(g).__name__ for g in loaded.geometry.values()}) or ["nothing"]
            raise StageInputError(
                path,
                f"has no faces (the scene holds only {', '.join(kinds)})",
                "A point cloud or line set cannot be stylised; supply a surface mesh.",
            )
        offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
        vertices = np.concatenate([v for v, _ in parts])
        faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)])
        return TriMesh(vertices, faces)
    if isinstance(loaded, trimesh.Trimesh):
        return TriMesh(np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64))
    kind = type(loaded).__name__
    if kind == "PointCloud":
        kind = f"a point cloud of {len(loaded.vertices)} points"
    raise StageInputError(
        path,
        f"has no faces (read as {kind})",
        "A point cloud or line set cannot be stylised; supply a surface mesh.",
    )


def check_mesh(mesh: TriMesh, name: str) -> TriMesh:
    """Validate and tidy: faces must be triangles indexing existing, finite vertices; at least one
    face must have non-zero area. Unreferenced vertices are dropped; nothing else changes."""
    faces = np.asarray(mesh.faces)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if faces.size == 0:
        what = "a point cloud" if len(vertices) else "empty"
        raise StageInputError(
            name,
            f"has no faces ({len(vertices)} vertices, 0 faces: {what})",
            "Supply a triangle mesh; a point cloud must be meshed first (e.g. MeshLab's screened Poisson reconstruction).",
        )
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise StageInputError(name, f"faces have shape {faces.shape}, expected (F, 3)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise StageInputError(
            name,
            f"faces index vertices outside 0..{len(vertices) - 1}",
            "The file is corrupt or truncated; re-export it.",
        )
    used = np.unique(faces)
    bad = ~np.isfinite(vertices[used]).all(axis=1)
    if bad.any():
        raise StageInputError(
            name,
            f"{int(bad.sum())} of {len(used)} vertices used by faces have NaN or infinite coordinates",
            "Repair or re-export the mesh (e.g. MeshLab: Remove Duplicate/Unreferenced Vertices after fixing the exporter).",
        )
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    out = TriMesh(vertices[used], remap[faces])
    dropped = len(vertices) - len(used)
    if dropped:
        log.info("%s: dropped %d unreferenced vertices", name, dropped)
    extent = float(np.ptp(out.vertices, axis=0).max())
    areas = out.face_areas
    if extent == 0.0 or not (areas > (1e-12 * extent) ** 2).any():
        raise StageInputError(
            name,
            f"all {len(faces)} faces have zero area (every triangle is degenerate)",
            "The mesh has no surface to stylise; check the export (collapsed or 2D geometry).",
        )
    return out


def save_ply(path: str | Path, mesh: TriMesh) -> None:
    """Write a binary little-endian PLY with float64 vertices and int32 faces (exact round trip)."""
    v = np.ascontiguousarray(mesh.vertices, dtype="<f8")
    f = np.ascontiguousarray(mesh.faces, dtype="<i4")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment tango-stylize\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    face_rec = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face_rec["n"] = 3
    face_rec["idx"] = f
    with atomic_stream(path) as fh:
        fh.write(header)
        fh.write(v.tobytes())
        fh.write(face_rec.tobytes())


def load_ply(path: str | Path) -> TriMesh:
    """Read a PLY written by :func:`save_ply` (or any triangle PLY, through trimesh)."""
    path = Path(path)
    with open_read(path, DATA_LIMIT, remedy="Run the stage that writes it again.") as fh:
        head = fh.read(512)
    marker = b"end_header\n"
    if head.startswith(b"ply\nformat binary_little_endian 1.0\ncomment tango-stylize\n") and marker in head:
        data = read_bytes(path, DATA_LIMIT, remedy="Run the stage that writes it again.")
        try:
            lines = head[: head.index(marker)].decode("ascii").splitlines()
            nv = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[-1])
            nf = int(next(ln for ln in lines if ln.startswith("element face")).split()[-1])
        except (UnicodeDecodeError, StopIteration, ValueError, IndexError):
            raise StageInputError(path, "has a malformed PLY header", "Run the stage that writes it again.") from None
        offset = head.index(marker) + len(marker)
        if nv < 0 or nf < 0 or offset + nv * 24 + nf * 13 != len(data):
            raise StageInputError(
                path,
                f"holds {len(data) - offset:,} bytes of data, not the {nv:,} vertices and {nf:,} faces its header says",
                "Run the stage that writes it again.",
            )
        body = np.frombuffer(data, np.uint8, offset=offset)
        v = body[: nv * 24].view("<f8").reshape(nv, 3).astype(np.float64)
        rec = body[nv * 24 :].view([("n", "u1"), ("idx", "<i4", (3,))])
        return TriMesh(v, rec["idx"].astype(np.int64))
    return load_mesh(path)
