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

A glTF file is checked before any reader builds anything from it (:func:`read_gltf_file`, which
the traced mesh's reader calls too, so both read one document): the GLB container (one JSON chunk,
first; at most one binary chunk, second; every length within the file), every buffer view within
its buffer and every accessor within its view, every index between the document's parts in range.
A file that fails stops with one line saying what is wrong.
"""

from __future__ import annotations

import base64
import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.safefiles import DATA_LIMIT, plain_file, read_bytes, user_file
from .normals import unit_face_normals

#: the formats whose UV layout can be kept (bake.uv)
LAYOUT_SUFFIXES = (".obj", ".glb", ".gltf")
#: the kinds of input a :class:`SourceMesh` keeps (its ``kind``): an OBJ file's, a glTF document's
OBJ_SOURCE, GLTF_SOURCE = "obj", "gltf"


@dataclass(frozen=True)
class SourceMesh:
    """The input's own triangles: per vertex ``positions (V, 3)``, ``uv (V, 2)`` (glTF convention;
    NaN where the file gives none), ``normals (V, 3)`` (NaN where none) and ``tangents (V, 4)`` or
    None (glTF ``TANGENT``); per triangle ``triangles (T, 3)`` (file order), ``slot (T,)`` (index
    into ``slot_names``, the input's materials in first-use order) and ``part (T,)`` (the OBJ
    polygon, or the glTF primitive instance of ``parts``: its ``node``, ``mesh``, ``primitive``,
    ``material`` and whether the node's transform ``mirrored`` its winding); ``kind`` is :data:`OBJ_SOURCE` or
    :data:`GLTF_SOURCE`."""

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
        if self.kind == GLTF_SOURCE:
            fill = np.broadcast_to(faces[:, None, :], given.shape)
        else:
            fill = self.vertex_normals()[self.triangles]
        return _unit(np.where(missing[..., None], fill, given))

    def vertex_normals(self) -> np.ndarray:
        """``(V, 3)``: the file's normals, or where none what its consumers assume: for glTF the
        flat normal of a face that uses the vertex (the specification's flat shading; exact where
        faces do not share vertices), for OBJ the angle-weighted mean of the unit normals of the
        faces around the vertex's position (vertices at one position, split at a UV seam, share it:
        an OBJ's smoothing by ``v``; zero where they cancel, then any unit vector)."""
        if self.kind == GLTF_SOURCE:
            flat = np.tile((0.0, 1.0, 0.0), (len(self.positions), 1))
            flat[self.triangles.reshape(-1)] = np.repeat(unit_face_normals(self.positions, self.triangles), 3, axis=0)
            given = np.isfinite(self.normals).all(1)
            flat[given] = _unit(self.normals[given])
            return flat
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
        text = read_bytes(user_file(path), DATA_LIMIT, remedy="Name the mesh file itself.").decode("utf-8", errors="replace")
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
        OBJ_SOURCE,
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
#: the numbers an accessor's ``componentType`` names
COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
#: components per element of each accessor ``type`` glTF has
TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
#: the accessor types the reader takes (vertex attributes and indices)
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
#: the vertex attributes the reader takes, with the accessor type each must have
ATTRIBUTE_TYPES = {"POSITION": "VEC3", "NORMAL": "VEC3", "TEXCOORD_0": "VEC2", "TANGENT": "VEC4"}
#: index accessors: unsigned byte, short or int
INDEX_COMPONENTS = (5121, 5123, 5125)
#: the most elements an accessor without a buffer view (all zeros) may have: its array is made, not read
MAX_UNBACKED_COUNT = 1 << 24
#: the types of a GLB's chunks the format defines
JSON_CHUNK, BIN_CHUNK = b"JSON", b"BIN\0"
#: what to do about a glTF file the checks refuse
REEXPORT = "Re-export the file (e.g. from Blender) and check it with the Khronos glTF-Validator."


class _Refused(ValueError):
    """One thing wrong with a glTF file, as a phrase (the caller names the file)."""


@dataclass(frozen=True)
class GltfFile:
    """A GLB or glTF file as :func:`read_gltf_file` checked it: its JSON ``text``, the ``document``
    parsed from it and its ``buffers`` as bytes, each exactly the length the document declares."""

    path: Path
    text: str
    document: dict
    buffers: tuple[bytes, ...]


def read_gltf_file(path: str | Path) -> GltfFile:
    """Read and check a GLB or glTF file before any parser builds anything from it, so that every
    reader of the file (trimesh for the traced mesh, this module for the layout) reads the same
    document and nothing outside its buffers: the GLB container (:func:`glb_chunks`), the JSON,
    the buffers (the GLB's binary chunk, base64 ``data:`` URIs, or plain files beside the file,
    never outside its folder) and every buffer view, accessor and reference between them
    (:func:`check_gltf_document`).

    Raises:
        StageInputError: the first thing found wrong, in one line.
    """
    path = Path(path)
    data = read_bytes(user_file(path), DATA_LIMIT, remedy="Name the mesh file itself.")
    try:
        if path.suffix.lower() == ".glb":
            raw, binary = glb_chunks(data)
        elif data[:4] == b"glTF":
            raise _Refused("is a binary glTF (GLB) file with a .gltf name")
        else:
            raw, binary = data, None
        try:
            text = raw.rstrip(b"\0").decode("utf-8")
            document = json.loads(text)
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise _Refused(f"its JSON cannot be read ({_line(exc)})") from None
        if not isinstance(document, dict):
            raise _Refused("its JSON is not an object")
        buffers = _buffers(path, document, binary)
        check_gltf_document(document, buffers)
    except _Refused as exc:
        raise StageInputError(path, str(exc), REEXPORT) from None
    return GltfFile(path, text, document, tuple(buffers))


def glb_chunks(data: bytes) -> tuple[bytes, bytes | None]:
    """The JSON chunk and the binary chunk (None: none) of a GLB file's bytes, after checking its
    container: the ``glTF`` magic, version 2, the stated length the file's, each chunk's length a
    multiple of 4 and within the file, the JSON chunk first and the only one, at most one binary
    chunk and that one second (chunks of other types are ignored, as the format says).

    Raises:
        ValueError: the first thing wrong with the container, as a phrase (the file unnamed).
    """
    if len(data) < 12 or data[:4] != b"glTF":
        raise _Refused("could not be read as GLB (it does not start with the 'glTF' header)")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise _Refused(f"is GLB version {version}; the tool reads version 2")
    if length != len(data):
        raise _Refused(f"its header gives a length of {length:,} bytes, but the file has {len(data):,}")
    chunks: list[tuple[bytes, bytes]] = []
    at = 12
    while at < len(data):
        if at + 8 > len(data):
            raise _Refused(f"ends inside the header of chunk {len(chunks)} (byte {at:,})")
        size, kind = struct.unpack_from("<I4s", data, at)
        name = _chunk_name(kind)
        if size % 4:
            raise _Refused(f"chunk {len(chunks)} ({name}) is {size:,} bytes long, not a multiple of 4")
        if at + 8 + size > len(data):
            raise _Refused(f"chunk {len(chunks)} ({name}) runs {at + 8 + size - len(data):,} bytes past the end of the file")
        chunks.append((kind, data[at + 8 : at + 8 + size]))
        at += 8 + size
    kinds = [kind for kind, _ in chunks]
    if not chunks or kinds[0] != JSON_CHUNK:
        first = _chunk_name(kinds[0]) if chunks else "none"
        raise _Refused(f"its first chunk is {first}, not the JSON chunk")
    jsons, bins = kinds.count(JSON_CHUNK), kinds.count(BIN_CHUNK)
    if jsons > 1:
        raise _Refused(f"holds {jsons} JSON chunks; a GLB holds one (readers would differ on which is the document)")
    if bins > 1:
        raise _Refused(f"holds {bins} BIN chunks; a GLB holds at most one")
    if bins and kinds.index(BIN_CHUNK) != 1:
        raise _Refused(f"its BIN chunk is chunk {kinds.index(BIN_CHUNK)}; it must follow the JSON chunk")
    return chunks[0][1], chunks[1][1] if bins else None


def _chunk_name(kind: bytes) -> str:
    return repr(kind.rstrip(b"\0").decode("latin-1"))


def _line(exc: BaseException) -> str:
    """An exception as one short line."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())[:200]


def _shown(value) -> str:
    """A value from the file, quoted and short, for a message of one line."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _buffers(path: Path, doc: dict, binary: bytes | None) -> list[bytes]:
    """Each buffer's bytes, cut to its ``byteLength``: the GLB's binary chunk (buffer 0 without a
    ``uri``), a base64 ``data:`` URI, or a plain file in the file's folder (a relative ``uri``)."""
    out = []
    for i, buf in enumerate(_objects(doc, "buffers")):
        length = _whole(buf.get("byteLength"), f"buffer {i}'s byteLength", 1)
        uri = buf.get("uri")
        if uri is None:
            if i != 0:
                raise _Refused(f"buffer {i} has no uri; only the first buffer may be a GLB's binary chunk")
            if binary is None:
                raise _Refused("buffer 0 has no uri, but the file has no GLB binary chunk")
            blob = binary
        elif not isinstance(uri, str):
            raise _Refused(f"buffer {i}'s uri is {_shown(uri)}, not text")
        elif uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64"):
                raise _Refused(f"buffer {i} is a data: URI that is not base64")
            try:
                blob = base64.b64decode(payload, validate=True)
            except ValueError:
                raise _Refused(f"buffer {i}'s data: URI is not valid base64") from None
        else:
            file = path.parent / uri
            if Path(uri).is_absolute() or ".." in Path(uri).parts or not plain_file(file, path.parent):
                raise _Refused(
                    f"buffer {i} names {_shown(uri)}, not a plain file beside it (keep the .bin beside it, or export a GLB)"
                )
            blob = read_bytes(file, DATA_LIMIT, path.parent)
        if len(blob) < length:
            raise _Refused(f"buffer {i} declares {length:,} bytes but holds {len(blob):,}")
        out.append(blob[:length])
    return out


def _objects(doc: dict, key: str) -> list[dict]:
    """``doc[key]``, a list of JSON objects (empty where absent)."""
    return _listed(doc.get(key, []), f"its {key}")


def _listed(items, what: str) -> list[dict]:
    """``items``, a list of JSON objects."""
    if not isinstance(items, list) or not all(isinstance(item, dict) for item in items):
        raise _Refused(f"{what} is not a list of objects")
    return items


def _whole(value, what: str, low: int = 0) -> int:
    """``value``, an integer of at least ``low`` (a JSON number with a fraction, or a boolean, is not)."""
    if type(value) is not int or value < low:
        raise _Refused(f"{what} is {_shown(value)}, not a whole number of at least {low}")
    return value


def _ref(value, items: list, what: str, kind: str) -> int | None:
    """``value``, None or an index into ``items`` (the document's ``kind`` list)."""
    if value is None:
        return None
    if type(value) is not int or not 0 <= value < len(items):
        raise _Refused(f"{what} is {_shown(value)}, but the file has {len(items)} {kind}")
    return value


def element_bytes(component_type: int, kind: str) -> int:
    """Bytes of one accessor element; a matrix's columns each start on a 4-byte boundary."""
    size = np.dtype(COMPONENTS[component_type]).itemsize
    if kind in ("MAT2", "MAT3"):
        n = int(kind[3])
        return n * (-(-n * size // 4) * 4)
    return TYPES[kind] * size


def check_gltf_document(doc: dict, buffers: list[bytes]) -> None:
    """Check a glTF document against its ``buffers`` (each cut to its declared length): every
    buffer view within its buffer (``byteOffset`` and ``byteLength`` whole numbers, ``byteStride``
    4 to 252 and a multiple of 4); every accessor of a known ``componentType`` and ``type``, with a
    whole ``count``, its stride at least its element's size and its last element within its view
    (an accessor without a view: at most :data:`MAX_UNBACKED_COUNT` elements); sparse accessors'
    indices and values within their views; every index into the document's lists in range; node
    transforms of the right length and finite; nodes a forest (one parent each, no cycle).

    Raises:
        ValueError: the first thing wrong, as a phrase.
    """
    views = _objects(doc, "bufferViews")
    for i, view in enumerate(views):
        b = _ref(view.get("buffer"), buffers, f"buffer view {i}'s buffer", "buffers")
        if b is None:
            raise _Refused(f"buffer view {i} names no buffer")
        offset = _whole(view.get("byteOffset", 0), f"buffer view {i}'s byteOffset")
        length = _whole(view.get("byteLength"), f"buffer view {i}'s byteLength", 1)
        if offset + length > len(buffers[b]):
            raise _Refused(
                f"buffer view {i} (bytes {offset:,} to {offset + length:,}) runs past the end of buffer {b} "
                f"({len(buffers[b]):,} bytes)"
            )
        stride = view.get("byteStride")
        if stride is not None and (type(stride) is not int or not 4 <= stride <= 252 or stride % 4):
            raise _Refused(f"buffer view {i} has byteStride {_shown(stride)}; glTF allows 4 to 252, a multiple of 4")
    accessors = _objects(doc, "accessors")
    for i, acc in enumerate(accessors):
        _check_accessor(i, acc, views)
    _check_references(doc, accessors, views)


def _check_accessor(i: int, acc: dict, views: list[dict]) -> None:
    ctype, kind = acc.get("componentType"), acc.get("type")
    if type(ctype) is not int or ctype not in COMPONENTS:
        raise _Refused(f"accessor {i} has componentType {_shown(ctype)}; glTF's are {', '.join(map(str, COMPONENTS))}")
    if not isinstance(kind, str) or kind not in TYPES:
        raise _Refused(f"accessor {i} has type {_shown(kind)}; glTF's are {', '.join(TYPES)}")
    count = _whole(acc.get("count"), f"accessor {i}'s count")
    size = element_bytes(ctype, kind)
    v = _ref(acc.get("bufferView"), views, f"accessor {i}'s bufferView", "buffer views")
    if v is None:
        if count > MAX_UNBACKED_COUNT:
            raise _Refused(
                f"accessor {i} has no buffer view and {count:,} elements; the tool takes at most {MAX_UNBACKED_COUNT:,}"
            )
    else:
        offset = _whole(acc.get("byteOffset", 0), f"accessor {i}'s byteOffset")
        stride = views[v].get("byteStride") or size
        if stride < size:
            raise _Refused(
                f"accessor {i}'s elements ({kind}) take {size} bytes, more than buffer view {v}'s byteStride of {stride}"
            )
        end = offset + (count - 1) * stride + size if count else offset
        if end > views[v]["byteLength"]:
            raise _Refused(
                f"accessor {i} ({count:,} elements of {size} bytes, {stride} apart, from byte {offset:,}) "
                f"ends at byte {end:,} of buffer view {v}, which holds {views[v]['byteLength']:,}"
            )
    sparse = acc.get("sparse")
    if sparse is None:
        return
    if not isinstance(sparse, dict):
        raise _Refused(f"accessor {i}'s sparse is not an object")
    n = _whole(sparse.get("count"), f"accessor {i}'s sparse count", 1)
    if n > count:
        raise _Refused(f"accessor {i} has {n:,} sparse elements but only {count:,} elements")
    for part, width in (("indices", None), ("values", size)):
        block = sparse.get(part)
        if not isinstance(block, dict):
            raise _Refused(f"the sparse {part} of accessor {i} are not an object")
        if width is None:
            itype = block.get("componentType")
            if type(itype) is not int or itype not in INDEX_COMPONENTS:
                raise _Refused(f"accessor {i}'s sparse indices have componentType {_shown(itype)}, not an unsigned integer")
            width = np.dtype(COMPONENTS[itype]).itemsize
        sv = _ref(block.get("bufferView"), views, f"accessor {i}'s sparse {part} bufferView", "buffer views")
        if sv is None:
            raise _Refused(f"the sparse {part} of accessor {i} name no buffer view")
        end = _whole(block.get("byteOffset", 0), f"accessor {i}'s sparse {part} byteOffset") + n * width
        if end > views[sv]["byteLength"]:
            raise _Refused(
                f"the sparse {part} of accessor {i} end at byte {end:,} of buffer view {sv}, "
                f"which holds {views[sv]['byteLength']:,}"
            )


#: the lengths of a node's transform properties
NODE_TRANSFORMS = {"matrix": 16, "translation": 3, "rotation": 4, "scale": 3}


def _check_references(doc: dict, accessors: list[dict], views: list[dict]) -> None:
    """Every index of one part of the document into another in range; node transforms of the
    right length and finite; the nodes a forest."""
    nodes, meshes, scenes = _objects(doc, "nodes"), _objects(doc, "meshes"), _objects(doc, "scenes")
    materials, textures, images = _objects(doc, "materials"), _objects(doc, "textures"), _objects(doc, "images")
    samplers, skins, cameras = _objects(doc, "samplers"), _objects(doc, "skins"), _objects(doc, "cameras")
    for m, mesh in enumerate(meshes):
        for p, prim in enumerate(_listed(mesh.get("primitives", []), f"mesh {m}'s primitives")):
            where = f"mesh {m}, primitive {p}"
            targets = prim.get("targets") or []
            if not isinstance(targets, list):
                raise _Refused(f"{where}: its targets are not a list")
            for attrs in [prim.get("attributes", {}), *targets]:
                if not isinstance(attrs, dict):
                    raise _Refused(f"{where}: its attributes are not an object")
                for name, index in attrs.items():
                    _ref(index, accessors, f"{where}: attribute {_shown(name)}", "accessors")
            _ref(prim.get("indices"), accessors, f"{where}: its indices", "accessors")
            _ref(prim.get("material"), materials, f"{where}: its material", "materials")
            mode = prim.get("mode", 4)
            if type(mode) is not int or not 0 <= mode <= 6:
                raise _Refused(f"{where}: its mode is {_shown(mode)}, not 0 to 6")
    parent: dict[int, int] = {}
    for n, node in enumerate(nodes):
        _ref(node.get("mesh"), meshes, f"node {n}'s mesh", "meshes")
        _ref(node.get("skin"), skins, f"node {n}'s skin", "skins")
        _ref(node.get("camera"), cameras, f"node {n}'s camera", "cameras")
        for key, length in NODE_TRANSFORMS.items():
            value = node.get(key)
            if value is not None and not _numbers(value, length):
                raise _Refused(f"node {n}'s {key} is not {length} finite numbers")
        children = node.get("children", [])
        if not isinstance(children, list):
            raise _Refused(f"node {n}'s children are not a list")
        for c in children:
            _ref(c, nodes, f"node {n}'s child", "nodes")
            if c in parent:
                raise _Refused(f"node {c} is a child of nodes {parent[c]} and {n}; a node has one parent")
            parent[c] = n
    rooted: set[int] = set()  # nodes known to reach a root: each node is walked up once in all
    for n in range(len(nodes)):
        path, seen, at = [], set(), n
        while at in parent and at not in rooted:
            if at in seen:
                raise _Refused(f"node {n}'s ancestors form a cycle")
            seen.add(at)
            path.append(at)
            at = parent[at]
        rooted.update(path)
        rooted.add(at)
    _ref(doc.get("scene"), scenes, "the default scene", "scenes")
    for s, scene in enumerate(scenes):
        roots = scene.get("nodes", [])
        if not isinstance(roots, list):
            raise _Refused(f"scene {s}'s nodes are not a list")
        for r in roots:
            _ref(r, nodes, f"scene {s}'s node", "nodes")
    for k, skin in enumerate(skins):
        joints = skin.get("joints", [])
        if not isinstance(joints, list):
            raise _Refused(f"skin {k}'s joints are not a list")
        for j in [*joints, skin.get("skeleton")]:
            _ref(j, nodes, f"skin {k}'s joint", "nodes")
        _ref(skin.get("inverseBindMatrices"), accessors, f"skin {k}'s inverseBindMatrices", "accessors")
    for k, animation in enumerate(_objects(doc, "animations")):
        anim_samplers = _listed(animation.get("samplers", []), f"animation {k}'s samplers")
        for s in anim_samplers:
            for key in ("input", "output"):
                _ref(s.get(key), accessors, f"animation {k}'s sampler {key}", "accessors")
        for c in _listed(animation.get("channels", []), f"animation {k}'s channels"):
            target = c.get("target", {})
            if not isinstance(target, dict):
                raise _Refused(f"animation {k}'s channel target is not an object")
            _ref(c.get("sampler"), anim_samplers, f"animation {k}'s channel sampler", "samplers")
            _ref(target.get("node"), nodes, f"animation {k}'s channel node", "nodes")
    for t, texture in enumerate(textures):
        _ref(texture.get("source"), images, f"texture {t}'s source", "images")
        _ref(texture.get("sampler"), samplers, f"texture {t}'s sampler", "samplers")
    for k, image in enumerate(images):
        _ref(image.get("bufferView"), views, f"image {k}'s bufferView", "buffer views")
    for k, material in enumerate(materials):
        for index in texture_indices(material):
            _ref(index, textures, f"material {k}'s texture", "textures")


def _numbers(value, length: int) -> bool:
    return isinstance(value, list) and len(value) == length and all(type(x) in (int, float) and np.isfinite(x) for x in value)


def texture_indices(material: dict) -> list:
    """The ``index`` of every texture reference in a material's JSON (an object under a key
    ending in ``Texture``, its extensions' included), at any depth; ``extras`` (an application's
    own values, which may name textures of its own) are not looked into."""
    out, stack = [], [material]
    while stack:
        node = stack.pop()
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for key, value in items:
            if key == "extras":
                continue
            if isinstance(key, str) and key.endswith("Texture") and isinstance(value, dict):
                out.append(value.get("index"))
            if isinstance(value, (dict, list)):
                stack.append(value)
    return out


def load_gltf_document(path: Path):
    """The pygltflib document of a GLB or glTF file, parsed from the JSON that
    :func:`read_gltf_file` checked, with every buffer as bytes (``buffers``).

    Raises:
        StageInputError: a file the checks refuse, or one pygltflib cannot take (naming why).
    """
    import pygltflib

    checked = read_gltf_file(path)
    try:
        doc = pygltflib.GLTF2.gltf_from_json(checked.text)
    except Exception as exc:  # noqa: BLE001 - any parser failure is an unreadable file
        raise StageInputError(path, f"could not be read as glTF ({_line(exc)})", REEXPORT) from exc
    doc._path, doc._name = Path(path).parent, Path(path).name
    return doc, list(checked.buffers)


def accessor_array(doc, blobs: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index`` as ``(count, width)`` float64 (normalised integers scaled, as the
    specification says) or, for indices, int64 ``(count,)``. Its elements are copied out of the
    buffer's bytes, which :func:`read_gltf_file` checked hold them (checked again here)."""
    acc = doc.accessors[index]
    out = accessor_elements(doc, blobs, index)
    dtype = out.dtype
    if acc.type == "SCALAR" and np.issubdtype(dtype, np.integer) and not acc.normalized:
        return out.reshape(-1).astype(np.int64)
    out = out.astype(np.float64)
    if acc.normalized and np.issubdtype(dtype, np.integer):
        out = np.maximum(out / np.iinfo(dtype).max, -1.0)
    return out


def accessor_elements(doc, blobs: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index``'s elements as stored, ``(count, width)`` of its component type (zeros
    where it has no buffer view, as the specification says).

    Raises:
        ValueError: a sparse accessor, a matrix other than 4x4, or elements past the buffer."""
    acc = doc.accessors[index]
    if acc.sparse is not None:
        raise ValueError(f"accessor {index} is sparse")
    if acc.type not in WIDTHS:
        raise ValueError(f"accessor {index} is a {acc.type}")
    dtype = np.dtype(COMPONENTS[acc.componentType]).newbyteorder("<")
    width = WIDTHS[acc.type]
    size = dtype.itemsize * width
    count = acc.count
    if acc.bufferView is None:
        out = np.zeros((count, width), dtype)
    else:
        view = doc.bufferViews[acc.bufferView]
        stride = view.byteStride or size
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        end = start + (count - 1) * stride + size if count else start
        if stride < size or end > (view.byteOffset or 0) + view.byteLength or end > len(blobs[view.buffer]):
            raise ValueError(f"accessor {index} runs past its buffer view")
        rows = np.zeros(count * stride, np.uint8)
        rows[: end - start] = np.frombuffer(blobs[view.buffer], np.uint8, count=end - start, offset=start)
        out = rows.reshape(count, stride)[:, :size].copy().view(dtype).reshape(count, width)
    return out.astype(dtype.newbyteorder("="))


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
            mirrored = bool(np.linalg.det(world[:3, :3]) < 0)  # its triangles' winding turned (_triangles)
            part = {"node": node, "mesh": doc.nodes[node].mesh, "primitive": p, "material": prim.material}
            parts.append({**part, "mirrored": mirrored})
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
        GLTF_SOURCE,
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


def _attribute(doc, blobs, attrs, name: str, count: int | None = None) -> np.ndarray | None:
    """A vertex attribute's array (None: the primitive has none), of the accessor type the
    specification gives it and, with ``count``, as many elements as the positions."""
    index = getattr(attrs, name)
    if index is None:
        return None
    acc = doc.accessors[index]
    if acc.type != ATTRIBUTE_TYPES[name]:
        raise ValueError(f"its {name} (accessor {index}) is a {acc.type}, not a {ATTRIBUTE_TYPES[name]}")
    if count is not None and acc.count != count:
        raise ValueError(f"its {name} (accessor {index}) has {acc.count:,} elements for {count:,} positions")
    return accessor_array(doc, blobs, index)


def _vertices(doc, blobs, attrs, world: np.ndarray) -> dict:
    """One primitive's vertex attributes in the world frame (normals by the inverse transpose)."""
    pos = _attribute(doc, blobs, attrs, "POSITION")
    if pos is None:
        raise ValueError("it has no POSITION")
    n = len(pos)
    lin = world[:3, :3]
    normals = np.full((n, 3), np.nan)
    if attrs.NORMAL is not None:
        normals = _unit(_attribute(doc, blobs, attrs, "NORMAL", n) @ np.linalg.inv(lin))
    uv = np.full((n, 2), np.nan)
    if attrs.TEXCOORD_0 is not None:
        uv = _attribute(doc, blobs, attrs, "TEXCOORD_0", n)
    tangents = None
    if attrs.TANGENT is not None:
        t = _attribute(doc, blobs, attrs, "TANGENT", n)
        # a mirroring node transform flips the handedness, as it flips the winding
        sign = 1.0 if np.linalg.det(lin) >= 0 else -1.0
        tangents = np.concatenate([_unit(t[:, :3] @ lin.T), sign * t[:, 3:4]], axis=1)
    return {"positions": pos @ lin.T + world[:3, 3], "normals": normals, "uv": uv, "tangents": tangents}


def _triangles(doc, blobs, prim, count: int, world: np.ndarray) -> np.ndarray:
    """A triangle primitive's ``(T, 3)`` vertex indices (its index accessor, or 0, 1, 2, ...),
    their winding turned where the node transform mirrors (as viewers turn it)."""
    if prim.indices is None:
        tri = np.arange(count)
    else:
        acc = doc.accessors[prim.indices]
        if acc.type != "SCALAR" or acc.componentType not in INDEX_COMPONENTS or acc.normalized:
            raise ValueError(f"its indices (accessor {prim.indices}) are not unsigned integers")
        tri = accessor_array(doc, blobs, prim.indices)
    if len(tri) % 3 or (len(tri) and (tri.min() < 0 or tri.max() >= count)):
        raise ValueError(f"{len(tri)} indices that are not whole triangles of its {count} vertices")
    tri = tri.reshape(-1, 3).astype(np.int64)
    return tri[:, [0, 2, 1]] if np.linalg.det(world[:3, :3]) < 0 else tri
