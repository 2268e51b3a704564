"""A second UV set written into the input's own glTF document (``bake.uv: second``).

Where the input's first set cannot hold a bake (overlapping, tiled, degenerate or missing UVs),
the bake goes into a new layout made for it (:mod:`stages.assets.layouts`) and ``model.glb`` stays
the input's document: :func:`add_uv_set` gives every textured triangle primitive a new
``TEXCOORD_n`` (``n`` one past the highest set any of them has, ``TEXCOORD_1`` for most assets;
glTF 2.0, section 3.7.2.1) and the baked materials read it (``texCoord: n``, section 5.33).

A vertex whose corners lie on different sides of one of the new layout's seams needs one vertex
per side (:func:`stages.geometry.uvsets.second_uv_set`). The document's vertices are kept at
their indices; the further sides are appended after them, copying every other attribute of the
vertex they split (normals, colours, joints, weights, further UV sets, morph target deltas, and
any application-specific ``_NAME`` attribute) in its own component type. Primitives that share
vertex attributes (several materials over one vertex set, a line primitive over a surface's
positions) are rewritten together, so they still share them; an index buffer is rewritten only
where a corner now reads an appended vertex, and widened to 32 bits where 16 no longer count
the vertices. A mesh drawn by several nodes has one layout: its first instance's (the bake gives
the others the same texels). glTF numbers a primitive's sets without gaps, so a primitive with
fewer sets than ``n`` (one without UVs) reads the new set under each missing number too. The
input's own ``TANGENT`` is for its first set; where a rewritten
primitive has one, it is replaced by MikkTSpace's on the document's normals and the new set (the
frame the bake wrote the normal map in), and morph targets' tangent deltas are dropped. Nodes,
skins, animations, cameras, extras and every other primitive stay as they are.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..geometry.sourcemesh import COMPONENTS, accessor_array, accessor_elements
from ..geometry.tangents import vertex_tangents
from ..geometry.uvsets import second_uv_set

#: a vertex attribute that is a UV set, and its number
TEXCOORD = re.compile(r"^TEXCOORD_(\d+)$")
#: extensions whose vertex data lie elsewhere, compressed (a primitive's Draco data, a buffer view's
#: meshopt data): no set can be appended
COMPRESSED = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")
#: the component type of glTF's unsigned indices by the largest index they must hold (the type's
#: largest value is reserved for primitive restart, which glTF forbids)
INDEX_TYPES = ((254, np.uint8, 5121), (65534, np.uint16, 5123), (4294967294, np.uint32, 5125))


@dataclass
class UvSetWritten:
    """What :func:`add_uv_set` did: the set's number ``texcoord``, the ``primitives`` that read it,
    the document's ``vertices`` of those primitives, the ``appended`` seam vertices, the corners
    ``rewritten`` to read them, and one line per change besides (``notes``)."""

    texcoord: int
    primitives: int = 0
    vertices: int = 0
    appended: int = 0
    rewritten: int = 0
    #: primitives that had fewer sets and read the new one under the missing numbers too
    filled: int = 0
    notes: list[str] = field(default_factory=list)

    def record(self) -> dict:
        return {
            "attribute": f"TEXCOORD_{self.texcoord}",
            "primitives": self.primitives,
            "input_vertices": self.vertices,
            "appended_vertices": self.appended,
            "rewritten_corners": self.rewritten,
            "primitives_given_lower_sets": self.filled,
        }


@dataclass
class SecondSet:
    """A second UV set to write: ``corner_uv (T, 3, 2)`` per triangle of the input's
    :class:`~stages.geometry.sourcemesh.SourceMesh`, and once written what was done (``written``)."""

    corner_uv: np.ndarray
    written: UvSetWritten | None = None


def set_refusal(doc) -> str | None:
    """Why a second set cannot be appended to ``doc``'s triangle primitives, or None: compressed
    vertex data, or a sparse vertex attribute (whose elements would have to be rewritten in place)."""
    compressed = {e for v in doc.bufferViews or [] for e in (v.extensions or {})} | set(doc.extensionsRequired or [])
    if compressed & set(COMPRESSED):
        return f"its buffers are compressed ({', '.join(sorted(compressed & set(COMPRESSED)))}): no UV set can be appended"
    for m, mesh in enumerate(doc.meshes or []):
        for p, prim in enumerate(mesh.primitives):
            ext = set(prim.extensions or {}) & set(COMPRESSED)
            if ext:
                return f"mesh {m}, primitive {p} is compressed ({', '.join(sorted(ext))}): its vertices cannot take a new UV set"
            for name, index in _vertex_accessors(prim):
                if doc.accessors[index].sparse is not None:
                    return f"mesh {m}, primitive {p}: its {name} (accessor {index}) is sparse"
    return None


def add_uv_set(doc, buffer, blob: bytes, source, corner_uv: np.ndarray) -> UvSetWritten:
    """Give ``doc``'s textured triangle primitives (``source``'s parts:
    :class:`~stages.geometry.sourcemesh.SourceMesh`) the UV set ``corner_uv (T, 3, 2)`` (per
    triangle of ``source``, glTF's convention), as the module docstring says. ``blob``: the
    document's one buffer; new data go into ``buffer``
    (:class:`~stages.assets.formats.gltf.GlbBuffer`, whose views are the document's). A mesh's
    instances after its first must have been given the first's coordinates.

    Raises:
        ValueError: a document :func:`set_refusal` refuses."""
    why = set_refusal(doc)
    if why is not None:
        raise ValueError(why)
    first = _first_instances(source)
    n = 1 + max((_texcoord(doc.meshes[m].primitives[p]) for m, p in first), default=-1)
    written = UvSetWritten(n)
    for members, accessors in _shared_groups(doc, first):
        _rewrite_group(doc, buffer, [blob], members, accessors, first, corner_uv, written)
    return written


def _first_instances(source) -> dict[tuple[int, int], tuple[np.ndarray, bool]]:
    """``(mesh, primitive) -> (rows, mirrored)``: the source triangles of each primitive's first
    instance, and whether its node turned their winding."""
    out = {}
    for k, part in enumerate(source.parts):
        key = (part["mesh"], part["primitive"])
        if key not in out:
            out[key] = (np.flatnonzero(source.part == k), bool(part.get("mirrored", False)))
    return out


def _vertex_accessors(prim) -> list[tuple[str, int]]:
    """``(name, accessor)`` of a primitive's attributes and its morph targets' (``target k NAME``)."""
    out = [(name, i) for name, i in vars(prim.attributes).items() if isinstance(i, int)]
    for k, target in enumerate(prim.targets or []):
        out += [(f"target {k} {name}", i) for name, i in target.items() if isinstance(i, int)]
    return out


def _texcoord(prim) -> int:
    """The highest UV set a primitive has (-1: none)."""
    found = [int(m.group(1)) for name, _ in _vertex_accessors(prim) if (m := TEXCOORD.match(name))]
    return max(found, default=-1)


def _shared_groups(doc, first: dict) -> list[tuple[list[tuple[int, int]], set[int]]]:
    """The primitives that share vertex accessors, joined (union-find over the accessors), for each
    group with a textured triangle primitive: ``(primitives, accessors)``, every primitive of the
    group (its members of ``first`` and any other, e.g. lines over the same positions)."""
    prims = [(m, p) for m, mesh in enumerate(doc.meshes or []) for p in range(len(mesh.primitives))]
    parent = {}

    def root(x):
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for key in prims:
        for _, i in _vertex_accessors(doc.meshes[key[0]].primitives[key[1]]):
            parent[root(("a", i))] = root(("p", key))
    groups: dict = {}
    for key in prims:
        groups.setdefault(root(("p", key)), []).append(key)
    out = []
    for members in groups.values():
        if any(key in first for key in members):
            acc = {i for m, p in members for _, i in _vertex_accessors(doc.meshes[m].primitives[p])}
            out.append((members, acc))
    return out


def _rewrite_group(doc, buffer, blobs, members, accessors, first, corner_uv, written: UvSetWritten) -> None:
    """One group of primitives sharing their vertices (:func:`_shared_groups`): the new set, its
    seam vertices appended to every shared accessor, the members' indices rewritten."""
    textured = [key for key in members if key in first]
    prim0 = doc.meshes[textured[0][0]].primitives[textured[0][1]]
    count = doc.accessors[prim0.attributes.POSITION].count
    tris, uvs = [], []
    for m, p in textured:
        rows, mirrored = first[(m, p)]
        tris.append(_file_triangles(doc, blobs, doc.meshes[m].primitives[p], count))
        uv = corner_uv[rows]
        uvs.append(uv[:, [0, 2, 1]] if mirrored else uv)  # back to the file's winding
    sizes = [len(t) for t in tris]
    new = second_uv_set(np.concatenate(tris), np.concatenate(uvs), count)
    normals = {doc.meshes[m].primitives[p].attributes.NORMAL for m, p in textured}
    tangents = _tangents(doc, blobs, prim0, new) if len(normals) == 1 else None  # one frame needs one set of normals
    for i in sorted(accessors):
        _append_vertices(doc, buffer, blobs, i, new.source)
    uv_acc = _add_accessor(doc, buffer, new.uv.astype(np.float32), "VEC2", 5126, 34962)
    for (m, p), tri in zip(textured, np.split(new.indices, np.cumsum(sizes)[:-1]), strict=True):
        prim = doc.meshes[m].primitives[p]
        written.filled += _texcoord(prim) < written.texcoord - 1
        for k in range(written.texcoord + 1):  # glTF numbers a primitive's sets without gaps
            if getattr(prim.attributes, f"TEXCOORD_{k}", None) is None:
                setattr(prim.attributes, f"TEXCOORD_{k}", uv_acc)
        if prim.indices is None or (tri != tris[textured.index((m, p))]).any():
            prim.indices = _index_accessor(doc, buffer, tri.reshape(-1), prim.indices)
        _set_tangents(doc, buffer, prim, tangents, written)
    for m, p in members:  # others over the same vertices: a draw without indices would now draw the appended
        prim = doc.meshes[m].primitives[p]
        if (m, p) not in first and prim.indices is None:
            prim.indices = _index_accessor(doc, buffer, np.arange(count), None)
    written.primitives += len(textured)
    written.vertices += count
    written.appended += new.appended
    written.rewritten += new.rewritten


def _file_triangles(doc, blobs, prim, count: int) -> np.ndarray:
    """A triangle primitive's ``(T, 3)`` vertex indices as its file stores them."""
    if prim.indices is None:
        return np.arange(count).reshape(-1, 3)
    return accessor_array(doc, blobs, prim.indices).reshape(-1, 3)


def _append_vertices(doc, buffer, blobs, index: int, source: np.ndarray) -> None:
    """Accessor ``index`` extended to ``len(source)`` elements, element ``k`` a copy of element
    ``source[k]`` (the first ones its own), in its own component type, in a new buffer view."""
    acc = doc.accessors[index]
    if acc.bufferView is None:  # all zeros (a morph target may say so): still all zeros
        acc.count = len(source)
        return
    elements = accessor_elements(doc, blobs, index)[source]
    _store(buffer, acc, elements, 34962)


def _store(buffer, acc, elements: np.ndarray, target: int | None) -> None:
    """``elements (count, width)`` as accessor ``acc``'s data, in a new buffer view (``target``);
    a vertex attribute's elements each start at a multiple of 4 bytes, as the specification asks."""
    dtype = np.dtype(COMPONENTS[acc.componentType]).newbyteorder("<")
    rows = np.ascontiguousarray(elements.astype(dtype)).view(np.uint8).reshape(len(elements), -1)
    size = rows.shape[1]
    stride = size + (-size) % 4 if target == 34962 else size
    padded = np.zeros((len(rows), stride), np.uint8)
    padded[:, :size] = rows
    acc.bufferView = buffer.view(padded.tobytes(), target)
    acc.byteOffset = None
    acc.count = len(elements)
    if target == 34962 and stride != size:
        buffer.views[acc.bufferView].byteStride = stride


def _add_accessor(doc, buffer, elements: np.ndarray, kind: str, component: int, target: int | None) -> int:
    """A new accessor holding ``elements``; returns its index."""
    import pygltflib as g

    acc = g.Accessor(componentType=component, count=len(elements), type=kind, min=None, max=None)
    _store(buffer, acc, elements.reshape(len(elements), -1), target)
    doc.accessors.append(acc)
    return len(doc.accessors) - 1


def _index_accessor(doc, buffer, indices: np.ndarray, old: int | None) -> int:
    """A new index accessor for ``indices``: the old one's component type where it still holds
    them, else the narrowest that does."""
    top = int(indices.max(initial=0))
    least = doc.accessors[old].componentType if old is not None else 5121
    _, dtype, component = next(t for t in INDEX_TYPES if t[0] >= top and t[2] >= least)
    return _add_accessor(doc, buffer, indices.astype(dtype), "SCALAR", component, 34963)


def _tangents(doc, blobs, prim, new) -> np.ndarray | None:
    """MikkTSpace tangents on the document's positions and normals (of ``prim``, copied to the
    appended vertices) and the new set; None where the primitive has no normals or two corners of one vertex
    disagree. Vertices no triangle reads get a unit tangent."""
    if prim.attributes.NORMAL is None:
        return None
    pos = accessor_array(doc, blobs, prim.attributes.POSITION)[new.source]
    normals = accessor_array(doc, blobs, prim.attributes.NORMAL)[new.source]
    out = vertex_tangents(pos, normals, new.uv.astype(np.float64), new.indices.reshape(-1, 3))
    if out is not None:  # a vertex no triangle reads, or only UV-degenerate ones: any unit tangent
        unread = np.ones(len(out), bool)
        unread[new.indices.reshape(-1)] = False
        out[unread | (np.linalg.norm(out[:, :3], axis=1) < 0.5)] = (1.0, 0.0, 0.0, 1.0)
    return out


def _set_tangents(doc, buffer, prim, tangents: np.ndarray | None, written: UvSetWritten) -> None:
    """A rewritten primitive's ``TANGENT``: replaced by ``tangents`` (a new accessor), or removed
    where there are none; its morph targets' tangent deltas removed."""
    if prim.attributes.TANGENT is None:
        return
    if tangents is None:
        prim.attributes.TANGENT = None
        written.notes.append("a primitive's TANGENT removed (its frame is its first UV set's): viewers compute MikkTSpace's")
    else:
        prim.attributes.TANGENT = _add_accessor(doc, buffer, tangents.astype(np.float32), "VEC4", 5126, 34962)
    for target in prim.targets or []:
        if target.pop("TANGENT", None) is not None:
            written.notes.append("a morph target's TANGENT deltas removed (they were for the first UV set's frame)")


__all__ = ["SecondSet", "UvSetWritten", "add_uv_set", "set_refusal"]
