"""The input's own surface as its file holds it: an OBJ's ``v``/``vt``/``vn``/``f`` lines or a glTF
document's triangle primitives, with their texture coordinates, normals, tangents, material slots,
vertex order and face order, so that the bake can write into the input's own UV layout and the
export can hand the input's own topology back (``bake.uv``).

Vertices. A vertex is what the format's consumers see as one: in a glTF primitive, an index of its
attribute arrays (primitives of several nodes or meshes follow each other in scene order); in an
OBJ, each distinct ``(v, vt, vn)`` corner, in the order the ``f`` lines first use it (what a glTF
or USD file can hold of an OBJ). Faces keep the file's order; an OBJ polygon is split into the fan
``(0, i, i + 1)``, the split trimesh and Blender make of a quad.

Texture coordinates are glTF's (``v`` down): an OBJ's ``vt`` is ``(u, 1 - v)``. Normals are the
file's, in the frame of the positions; where a file has none, what its consumers assume: the glTF
specification's flat normals, or for an OBJ smooth normals per position (the angle-weighted mean of
the faces around it, Thürmer & Wüthrich 1998: what an OBJ's smoothing group gives), which the glTF
and USD exports then write out.

Positions are in the file's units; a glTF node's transforms (matrix or TRS, down the scene graph)
are applied, as the traced mesh's reader applies them (a skinned mesh is read in its node's frame,
its bind pose). Only what the traced mesh holds is read: triangle primitives (mode 4); points,
lines and strips are not surface.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from .normals import unit_face_normals

#: the formats whose UV layout can be kept (bake.uv)
LAYOUT_SUFFIXES = (".obj", ".glb", ".gltf")


@dataclass(frozen=True)
class SourceMesh:
    """The input's own triangles: per vertex ``positions (V, 3)``, ``uv (V, 2)`` (glTF convention;
    NaN where the file gives none), ``normals (V, 3)`` (NaN where none) and ``tangents (V, 4)`` or
    None (glTF ``TANGENT``); per triangle ``triangles (T, 3)`` (file order), ``slot (T,)`` (index
    into ``slot_names``, the input's materials in first-use order) and ``part (T,)`` (the OBJ
    polygon, or the glTF primitive instance of ``parts``); ``kind`` is ``obj`` or ``gltf``."""

    path: Path
    kind: str
    positions: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray | None
    triangles: np.ndarray
    slot: np.ndarray
    slot_names: tuple[str, ...]
    part: np.ndarray
    parts: tuple[dict, ...] = ()

    @property
    def corner_uv(self) -> np.ndarray:
        """``(T, 3, 2)`` texture coordinates per triangle corner."""
        return self.uv[self.triangles]

    @property
    def mapped(self) -> np.ndarray:
        """``(T,) bool``: triangles whose three corners have texture coordinates."""
        return np.isfinite(self.corner_uv).all(axis=(1, 2))

    def corner_normals(self) -> np.ndarray:
        """``(T, 3, 3)`` unit normals per corner: the file's, or where it has none what its
        consumers assume (module docstring): flat for glTF, smooth per vertex for OBJ."""
        faces = unit_face_normals(self.positions, self.triangles)
        given = self.normals[self.triangles]
        missing = ~np.isfinite(given).all(-1)
        if not missing.any():
            return _unit(given)
        if self.kind == "gltf":
            fill = np.broadcast_to(faces[:, None, :], given.shape)
        else:
            fill = self.vertex_normals()[self.triangles]
        return _unit(np.where(missing[..., None], fill, given))

    def vertex_normals(self) -> np.ndarray:
        """``(V, 3)``: the file's normals, or where none the angle-weighted mean of the unit normals
        of the faces around the vertex's position (vertices at one position, split at a UV seam,
        share it: an OBJ's smoothing by ``v``; zero where they cancel, then any unit vector)."""
        p = self.positions[self.triangles]
        e1 = p[:, [1, 2, 0]] - p
        e2 = p[:, [2, 0, 1]] - p
        cos = (_unit(e1) * _unit(e2)).sum(-1)
        angle = np.arccos(np.clip(cos, -1.0, 1.0))
        _, where = np.unique(self.positions, axis=0, return_inverse=True)
        where = where.reshape(-1)
        acc = np.zeros((int(where.max(initial=-1)) + 1, 3))
        weighted = angle[..., None] * unit_face_normals(self.positions, self.triangles)[:, None]
        np.add.at(acc, where[self.triangles.reshape(-1)], weighted.reshape(-1, 3))
        acc = _unit(acc)[where]
        acc[np.linalg.norm(acc, axis=1) == 0] = (0.0, 1.0, 0.0)
        given = np.isfinite(self.normals).all(1)
        acc[given] = _unit(self.normals[given])
        return acc


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(n > 0, x / np.where(n > 0, n, 1.0), 0.0)


def read_source(path: str | Path) -> SourceMesh:
    """The input's own surface (module docstring) from an OBJ, GLB or glTF file.

    Raises:
        StageInputError: another format, or a file this reader cannot take (naming what).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".obj":
        return read_obj(path)
    if suffix in (".glb", ".gltf"):
        return read_gltf(path)
    raise StageInputError(path, f"{suffix or 'this'} files hold no UV layout the tool reads", "Use an OBJ, GLB or glTF file.")


# ------------------------------------------------------------------------------------------ OBJ
@dataclass
class ObjLines:
    """An OBJ's statements, continuation lines joined: ``lines`` (the text of each, without the
    line break) and the parsed records the reader needs."""

    lines: list[str]

    @classmethod
    def read(cls, path: Path) -> ObjLines:
        text = path.read_text(encoding="utf-8", errors="replace")
        joined: list[str] = []
        pending = ""
        for raw in text.splitlines():
            if raw.endswith("\\"):
                pending += raw[:-1] + " "
                continue
            joined.append(pending + raw)
            pending = ""
        if pending:
            joined.append(pending)
        return cls(joined)


def read_obj(path: Path) -> SourceMesh:
    """An OBJ's surface (module docstring): ``v``, ``vt``, ``vn``, ``f`` (negative indices
    relative, as the format allows) and ``usemtl``; other statements are kept by the writer, not
    read."""
    obj = ObjLines.read(path)
    v: list[list[float]] = []
    vt: list[list[float]] = []
    vn: list[list[float]] = []
    corners: list[tuple[int, int, int]] = []
    polygons: list[tuple[int, int, int]] = []  # (first corner, corner count, slot)
    slots: dict[str, int] = {}
    slot = -1
    for number, line in enumerate(obj.lines, 1):
        words = line.split()
        if not words:
            continue
        head = words[0]
        try:
            if head == "v":
                v.append([float(x) for x in words[1:4]])
            elif head == "vt":
                uv = [float(x) for x in words[1:3]]
                vt.append(uv + [0.0] * (2 - len(uv)))
            elif head == "vn":
                vn.append([float(x) for x in words[1:4]])
            elif head == "usemtl":
                slot = slots.setdefault(line.split(None, 1)[1].strip() if len(words) > 1 else "", len(slots))
            elif head == "f":
                if slot < 0:
                    slot = slots.setdefault("", len(slots))
                refs = [_obj_corner(w, len(v), len(vt), len(vn)) for w in words[1:]]
                if len(refs) < 3:
                    raise ValueError(f"a face needs 3 or more corners, got {len(refs)}")
                polygons.append((len(corners), len(refs), slot))
                corners.extend(refs)
        except (ValueError, IndexError) as exc:
            raise StageInputError(
                path, f"line {number} ({line.strip()[:60]!r}) cannot be read: {exc}", "Re-export the OBJ."
            ) from exc
    if not polygons:
        raise StageInputError(path, "has no faces", "Supply a triangle mesh.")
    keys, vertex_of = np.unique(np.array(corners, np.int64), axis=0, return_inverse=True)
    vertex_of = vertex_of.reshape(-1)
    # vertices in the order faces first use them
    first = np.full(len(keys), len(corners), np.int64)
    np.minimum.at(first, vertex_of, np.arange(len(corners)))
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    keys = keys[order]
    corner_vertex = rank[vertex_of]
    tris, slot_of, part_of = [], [], []
    for k, (start, count, s) in enumerate(polygons):
        for i in range(1, count - 1):
            tris.append((corner_vertex[start], corner_vertex[start + i], corner_vertex[start + i + 1]))
            slot_of.append(s)
            part_of.append(k)
    pos = np.asarray(v, np.float64)[keys[:, 0]]
    uv = _gather(vt, keys[:, 1], 2)
    uv[:, 1] = 1.0 - uv[:, 1]
    names = tuple(name or "default" for name in slots)
    return SourceMesh(
        path,
        "obj",
        pos,
        uv,
        _gather(vn, keys[:, 2], 3),
        None,
        np.array(tris, np.int64),
        np.array(slot_of, np.int64),
        names,
        np.array(part_of, np.int64),
    )


def _gather(values: list[list[float]], index: np.ndarray, width: int) -> np.ndarray:
    """Rows of ``values`` at ``index`` (-1: NaN)."""
    table = np.asarray(values, np.float64).reshape(-1, width) if values else np.zeros((0, width))
    out = np.full((len(index), width), np.nan)
    ok = index >= 0
    out[ok] = table[index[ok]]
    return out


def _obj_corner(word: str, nv: int, nvt: int, nvn: int) -> tuple[int, int, int]:
    """``v[/vt[/vn]]`` (1-based; negative: from the end) as 0-based indices, -1 where absent."""
    parts = word.split("/")
    if len(parts) > 3 or not parts[0]:
        raise ValueError(f"bad corner {word!r}")
    out = []
    for value, count in zip(parts + [""] * (3 - len(parts)), (nv, nvt, nvn), strict=True):
        if not value:
            out.append(-1)
            continue
        i = int(value)
        i = i - 1 if i > 0 else count + i
        if not 0 <= i < count:
            raise ValueError(f"corner {word!r} refers to an element that does not exist")
        out.append(i)
    return out[0], out[1], out[2]


# ----------------------------------------------------------------------------------------- glTF
COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def load_gltf_document(path: Path):
    """The pygltflib document of a GLB or glTF file with every buffer as bytes (``buffers``): the
    GLB's binary chunk, ``data:`` URIs, or files beside a glTF file (never outside its folder)."""
    import pygltflib

    try:
        doc = pygltflib.GLTF2().load(str(path))
    except Exception as exc:  # noqa: BLE001 - any parser failure is an unreadable file
        raise StageInputError(path, f"could not be read as glTF ({type(exc).__name__}: {exc})") from exc
    if doc is None:
        raise StageInputError(path, "could not be read as glTF")
    blobs = []
    for i, buf in enumerate(doc.buffers):
        if buf.uri is None:
            blobs.append(doc.binary_blob() or b"")
        elif buf.uri.startswith("data:"):
            blobs.append(base64.b64decode(buf.uri.split(",", 1)[1]))
        else:
            file = (path.parent / buf.uri).resolve()
            if path.parent.resolve() not in file.parents or not file.is_file():
                raise StageInputError(
                    path,
                    f"buffer {i} names {buf.uri!r}, not a file beside it",
                    "Keep the .bin beside the .gltf, or export a GLB.",
                )
            blobs.append(file.read_bytes())
    return doc, blobs


def accessor_array(doc, blobs: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index`` as ``(count, width)`` float64 (normalised integers scaled, as the
    specification says) or, for indices, int64 ``(count,)``."""
    acc = doc.accessors[index]
    dtype = np.dtype(COMPONENTS[acc.componentType]).newbyteorder("<")
    width = WIDTHS[acc.type]
    if acc.sparse is not None:
        raise ValueError(f"accessor {index} is sparse")
    if acc.bufferView is None:
        out = np.zeros((acc.count, width), dtype)
    else:
        view = doc.bufferViews[acc.bufferView]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        stride = view.byteStride or dtype.itemsize * width
        data = np.frombuffer(blobs[view.buffer], np.uint8, count=(acc.count - 1) * stride + dtype.itemsize * width, offset=start)
        rows = np.lib.stride_tricks.as_strided(data, (acc.count, width * dtype.itemsize), (stride, 1))
        out = np.ascontiguousarray(rows).view(dtype).reshape(acc.count, width)
    if acc.type == "SCALAR" and np.issubdtype(dtype, np.integer) and not acc.normalized:
        return out.reshape(-1).astype(np.int64)
    out = out.astype(np.float64)
    if acc.normalized and np.issubdtype(dtype, np.integer):
        out = np.maximum(out / np.iinfo(dtype).max, -1.0)
    return out


def node_matrix(node) -> np.ndarray:
    """A node's local ``(4, 4)`` transform (column vectors): its matrix, or T * R * S."""
    if node.matrix is not None and len(node.matrix) == 16:
        return np.asarray(node.matrix, np.float64).reshape(4, 4).T
    m = np.eye(4)
    if node.scale is not None:
        m = np.diag([*node.scale, 1.0]) @ m
    if node.rotation is not None:
        x, y, z, w = node.rotation
        r = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        rot = np.eye(4)
        rot[:3, :3] = r
        m = rot @ m
    if node.translation is not None:
        t = np.eye(4)
        t[:3, 3] = node.translation
        m = t @ m
    return m


def mesh_instances(doc) -> list[tuple[int, np.ndarray]]:
    """``(node, world matrix)`` of every node with a mesh in the default scene (scene 0, or every
    root node where the document names no scene), depth first in document order."""
    if doc.scenes:
        roots = doc.scenes[doc.scene or 0].nodes or []
    else:
        children = {c for n in doc.nodes for c in (n.children or [])}
        roots = [i for i in range(len(doc.nodes)) if i not in children]
    out = []
    stack = [(r, np.eye(4)) for r in reversed(roots)]
    while stack:
        i, parent = stack.pop()
        node = doc.nodes[i]
        world = parent @ node_matrix(node)
        if node.mesh is not None:
            out.append((i, world))
        stack.extend((c, world) for c in reversed(node.children or []))
    return out


def read_gltf(path: Path) -> SourceMesh:
    """A glTF document's triangle primitives (module docstring), in scene order; primitives of one
    node that share their vertex attributes share their vertices."""
    doc, blobs = load_gltf_document(path)
    blocks: dict[tuple, int] = {}  # (node, attribute accessors) -> vertex block
    pieces, tris, parts = [], [], []
    slots: dict[str, int] = {}
    for node, world in mesh_instances(doc):
        for p, prim in enumerate(doc.meshes[doc.nodes[node].mesh].primitives):
            if (prim.mode if prim.mode is not None else 4) != 4:
                continue
            a = prim.attributes
            key = (node, a.POSITION, a.NORMAL, a.TEXCOORD_0, a.TANGENT)
            try:
                if key not in blocks:
                    blocks[key] = len(pieces)
                    pieces.append(_vertices(doc, blobs, a, world))
                tri = _triangles(doc, blobs, prim, len(pieces[blocks[key]]["positions"]), world)
            except (ValueError, KeyError, IndexError) as exc:
                raise StageInputError(path, f"node {node}, primitive {p} cannot be read: {exc}", "Re-export the file.") from exc
            slot = slots.setdefault(_material_name(doc, prim.material), len(slots))
            tris.append((blocks[key], tri, slot))
            parts.append({"node": node, "mesh": doc.nodes[node].mesh, "primitive": p, "material": prim.material})
    if not pieces:
        raise StageInputError(path, "has no triangle primitives", "Supply a triangle mesh.")
    offsets = np.cumsum([0] + [len(q["positions"]) for q in pieces[:-1]])
    tangents = None
    if any(q["tangents"] is not None for q in pieces):
        tangents = np.concatenate(
            [q["tangents"] if q["tangents"] is not None else np.full((len(q["positions"]), 4), np.nan) for q in pieces]
        )
    return SourceMesh(
        path,
        "gltf",
        np.concatenate([q["positions"] for q in pieces]),
        np.concatenate([q["uv"] for q in pieces]),
        np.concatenate([q["normals"] for q in pieces]),
        tangents,
        np.concatenate([t + offsets[b] for b, t, _ in tris]),
        np.concatenate([np.full(len(t), s) for _, t, s in tris]),
        tuple(slots),
        np.concatenate([np.full(len(t), k) for k, (_, t, _) in enumerate(tris)]),
        tuple(parts),
    )


def _material_name(doc, index: int | None) -> str:
    if index is None:
        return "default"
    return doc.materials[index].name or f"material_{index}"


def _vertices(doc, blobs, attrs, world: np.ndarray) -> dict:
    """One primitive's vertex attributes in the world frame (normals by the inverse transpose)."""
    pos = accessor_array(doc, blobs, attrs.POSITION)
    n = len(pos)
    lin = world[:3, :3]
    normals = np.full((n, 3), np.nan)
    if attrs.NORMAL is not None:
        normals = _unit(accessor_array(doc, blobs, attrs.NORMAL) @ np.linalg.inv(lin))
    uv = np.full((n, 2), np.nan)
    if attrs.TEXCOORD_0 is not None:
        uv = accessor_array(doc, blobs, attrs.TEXCOORD_0)
    tangents = None
    if attrs.TANGENT is not None:
        t = accessor_array(doc, blobs, attrs.TANGENT)
        # a mirroring node transform flips the handedness, as it flips the winding
        sign = 1.0 if np.linalg.det(lin) >= 0 else -1.0
        tangents = np.concatenate([_unit(t[:, :3] @ lin.T), sign * t[:, 3:4]], axis=1)
    return {"positions": pos @ lin.T + world[:3, 3], "normals": normals, "uv": uv, "tangents": tangents}


def _triangles(doc, blobs, prim, count: int, world: np.ndarray) -> np.ndarray:
    """A triangle primitive's ``(T, 3)`` vertex indices (its index accessor, or 0, 1, 2, ...),
    their winding turned where the node transform mirrors (as viewers turn it)."""
    tri = accessor_array(doc, blobs, prim.indices) if prim.indices is not None else np.arange(count)
    if len(tri) % 3 or (len(tri) and (tri.min() < 0 or tri.max() >= count)):
        raise ValueError(f"{len(tri)} indices that are not whole triangles of its {count} vertices")
    tri = tri.reshape(-1, 3).astype(np.int64)
    return tri[:, [0, 2, 1]] if np.linalg.det(world[:3, :3]) < 0 else tri
