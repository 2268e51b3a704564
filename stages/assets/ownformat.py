"""The input's own asset back, with new materials: what the export writes where the bake kept the
input's UV layout (``bake.uv``; :mod:`stages.assets.layouts`).

* **glTF input** (GLB or glTF): ``model.glb`` is the input document itself, its buffers merged into
  the one binary chunk; only materials, textures and images change. Each material that a textured
  triangle primitive used is replaced, at its index and under its name, by one reading the baked
  texture set (primitives without a material get one, named ``default``); the textures and images
  no other material reads are dropped; the baked images and a repeating sampler are added. Nodes,
  names, meshes, skins, joints, weights, animations, morph targets, cameras, extras and other
  primitives are untouched; the provenance joins ``asset.extras``.
* **OBJ input**: ``model.obj`` is the input's own lines (``v``, ``vt``, ``vn``, ``f``, groups,
  smoothing, ``usemtl``) with ``mtllib model.mtl`` in place of the input's material library, and
  ``model.mtl`` one material per input material name reading the texture set. MTL has no
  packed-channel convention, so the roughness and metallic channels are written as their own
  grey images beside the set (``roughness.png``, ``metallic.png``), which Blender's importer reads
  as ``map_Pr``/``map_Pm``.
* **USD and, for OBJ input, glTF**: the input's vertices as :func:`kept_geometry` holds them, one
  material per input material.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..core.provenance import ORIGIN_METADATA_KEY, atomic_path
from ..geometry.normalization import Similarity
from ..geometry.sourcemesh import ObjLines, SourceMesh, load_gltf_document
from ..geometry.tangents import mikktspace
from .formats import ExportMesh, GlbBuffer, export_mesh, glb_material, glb_sampler

log = logging.getLogger(__name__)

#: grey images the OBJ's material library reads, from the metallic-roughness texture's channels
OBJ_CHANNELS = {"roughness": 1, "metallic": 2}


def kept_geometry(source: SourceMesh, transform: Similarity | None = None, materials=None) -> ExportMesh:
    """The input's vertices (:mod:`stages.geometry.sourcemesh`: a glTF primitive's own, an OBJ's
    distinct corners in first-use order) and triangles in file order, its UVs and normals (its
    own; where it has none, smooth vertex normals) and materials (``materials``: per triangle, the
    names and the texture sets' folders, :func:`~stages.assets.layouts.kept_materials`; None: the
    input's slots, one set), in its own units and position, or with ``transform`` in the
    normalised frame. Tangents: MikkTSpace's on its normals and UVs (the frame the bake used) where
    every corner of a vertex has the same one, else none (viewers then compute the same
    MikkTSpace themselves)."""
    pos = source.positions if transform is None else transform.forward(source.positions)
    normals = source.vertex_normals()
    if transform is not None:
        normals = normals @ transform.rotation.T
    material, names, folders = materials or (source.slot, source.slot_names, ())
    return ExportMesh(
        pos.astype(np.float32),
        normals.astype(np.float32),
        source.uv.astype(np.float32),
        vertex_tangents(pos, normals, source.uv, source.triangles),
        source.triangles.astype(np.int64),
        material,
        names,
        repeat=True,
        slot_textures=folders,
    )


def vertex_tangents(positions: np.ndarray, normals: np.ndarray, uv: np.ndarray, triangles: np.ndarray) -> np.ndarray | None:
    """MikkTSpace tangents ``(V, 4)`` (xyz and handedness) per vertex, or None where two corners of
    one vertex get different ones (a vertex shared across a mirrored UV seam)."""
    st = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=-1)[triangles]
    t, w = mikktspace(positions[triangles], normals[triangles], st)
    corner = np.concatenate([t, np.repeat(w[:, None, None], 3, axis=1)], axis=-1).reshape(-1, 4)
    out = np.zeros((len(positions), 4))
    out[triangles.reshape(-1)] = corner
    if np.abs(out[triangles.reshape(-1)] - corner).max(initial=0.0) > 1e-4:
        return None
    return out.astype(np.float32)


@dataclass(frozen=True)
class AssetGeometry:
    """What an asset's files hold: ``geom`` (its geometry in export space), the input's own
    surface where the bake kept its layout (``kept``), the metres per unit the files state, and
    ``own_frame``: positions are the input's own (``x_original``; a glTF input's document always,
    an OBJ's with ``export.units: original``) rather than the export space of a new atlas
    (``R x_original``, +Y up: :mod:`stages.assets.formats`) or the normalised frame."""

    geom: ExportMesh
    kept: SourceMesh | None
    meters_per_unit: float
    own_frame: bool


def asset_geometry(mesh, atlas: dict, transform: Similarity, settings, kept: SourceMesh | None, materials=None) -> AssetGeometry:
    """The geometry the export writes (and the round trip checks) for the traced ``mesh`` and the
    bake's ``atlas`` arrays, with the export ``settings`` (units, weld, metres per unit): the
    traced mesh welded (:func:`~stages.assets.formats.export_mesh`), or the input's own topology
    where the bake kept its layout (:func:`kept_geometry`, with its ``materials``). A glTF input's
    document keeps its own units (metres, by the specification) and position: ``units`` and
    ``meters_per_unit`` do not apply to it."""
    original = settings.units == "original"
    if kept is None:
        geom = export_mesh(mesh, atlas, transform if original else None, settings.weld)
        return AssetGeometry(geom, None, settings.meters_per_unit, False)
    if kept.kind == "gltf":
        return AssetGeometry(kept_geometry(kept, None, materials), kept, 1.0, True)
    geom = kept_geometry(kept, None if original else transform, materials)
    return AssetGeometry(geom, kept, settings.meters_per_unit, original)


def kept_corner_tangents(atlas: dict, transform: Similarity | None = None) -> np.ndarray:
    """The baked frame's tangents per corner of the input's own triangles (file order), ``(3T, 4)``
    (xyz and handedness), from the bake's ``atlas`` arrays of a kept layout; with ``transform`` in
    the input's own frame (the normalised frame's directions turned back by its rotation), else in
    the normalised frame (whose directions an export space shares)."""
    order = np.argsort(atlas["source_face"])  # input triangle -> traced face
    t = np.asarray(atlas["tangent"], np.float64)[order]
    if transform is not None:
        t = t @ transform.rotation  # R^T t per corner
    w = np.repeat(np.asarray(atlas["handedness"], np.float64)[order], 3)
    return np.concatenate([t.reshape(-1, 3), w[:, None]], axis=1)


# ------------------------------------------------------------------------------------------ OBJ
def write_obj(folder: Path, geom: ExportMesh, source: SourceMesh, transform: Similarity | None, brdf: str) -> list[str]:
    """``model.obj`` and ``model.mtl`` in ``folder`` (which holds ``textures/``), and the grey
    channel images the MTL reads (module docstring), for ``geom`` (:func:`kept_geometry` of
    ``source``: its slots and texture sets); returns the files written (relative)."""
    folder = Path(folder)
    written = ["model.obj", "model.mtl"]
    for sub in sorted(set(geom.slot_textures) | {""}):
        textures = folder / "textures" / sub
        for key, channel in OBJ_CHANNELS.items():
            with Image.open(textures / "metallic_roughness.png") as img:
                grey = np.asarray(img.convert("RGB"))[..., channel]
            with atomic_path(textures / f"{key}.png") as tmp:
                Image.fromarray(grey).save(tmp, format="PNG")
            written.append(str(Path("textures", sub, f"{key}.png")))
    with atomic_path(folder / "model.obj") as tmp:
        tmp.write_text("\n".join(obj_lines(source, transform, geom)) + "\n", encoding="utf-8")
    with atomic_path(folder / "model.mtl") as tmp:
        tmp.write_text(mtl_text(geom.slot_names, [geom.texture_folder(n) for n in geom.slot_names], brdf), encoding="utf-8")
    return written


def obj_lines(source: SourceMesh, transform: Similarity | None, geom: ExportMesh | None = None) -> list[str]:
    """The input OBJ's lines with the new material library (module docstring); with ``transform``
    the ``v`` lines are moved into the normalised frame (the only lines that change). The
    ``usemtl`` lines name ``geom``'s materials (:func:`kept_geometry`): an input slot's own
    ``usemtl`` line stays where it names a material; where a slot spans several UDIM tiles a
    ``usemtl <slot>.<tile>`` line goes before each run of its faces in one tile (faces before any
    ``usemtl``: ``default``)."""
    names = geom.slot_names if geom is not None and geom.slot_names else source.slot_names
    per_face = geom.slots if geom is not None and geom.slots is not None else source.slot
    first = np.unique(source.part, return_index=True)[1]  # each polygon's first triangle
    polygon_material = per_face[first]
    out = ["mtllib model.mtl"]
    current, polygon = None, 0
    for line in ObjLines.read(source.path).lines:
        words = line.split()
        head = words[0] if words else ""
        if head == "mtllib":
            continue
        if head == "usemtl":
            name = line.split(None, 1)[1].strip() if len(words) > 1 else ""
            if name in names:
                out.append(line)
                current = name
            continue
        if head == "f":
            want = names[polygon_material[polygon]]
            polygon += 1
            if want != current:
                out.append(f"usemtl {want}")
                current = want
        if head == "v" and transform is not None:
            x = transform.forward(np.array([float(w) for w in words[1:4]]))
            line = "v " + " ".join(f"{c:.9g}" for c in x)
        out.append(line)
    return out


def mtl_text(names: tuple[str, ...], folders: list[str], brdf: str) -> str:
    """One material per name reading its texture set (in ``textures/<folder>``): base colour,
    roughness, normal map, and TANGO's specular colour or glTF's metallic."""
    blocks = []
    for name, sub in zip(names, folders, strict=True):
        t = "/".join(p for p in ("textures", sub) if p)
        lines = [f"newmtl {name}", "Kd 1 1 1", "Pr 1", f"map_Kd {t}/basecolor.png", f"map_Pr {t}/roughness.png"]
        if brdf == "gltf":
            lines += ["Pm 1", "Ks 0 0 0", f"map_Pm {t}/metallic.png"]
        else:
            lines += ["Pm 0", "Ks 1 1 1", f"map_Ks {t}/specular.png"]
        lines += [f"map_Bump -bm 1 {t}/normal.png", f"norm {t}/normal.png"]
        blocks.append("\n".join(lines))
    return "# tango-stylize: the baked texture sets, one material per input material\n" + "\n\n".join(blocks) + "\n"


# ----------------------------------------------------------------------------------------- glTF
def write_document_glb(
    path: Path, source: SourceMesh, textures_dir: Path, origin: dict, brdf: str, occlusion: bool, folders: tuple[str, ...] = ()
) -> None:
    """``model.glb``: the input glTF document with its textured primitives' materials replaced by
    ones reading the baked texture sets (module docstring; ``folders``: each slot's set below
    ``textures_dir``)."""
    import pygltflib as g

    doc, blobs = load_gltf_document(source.path)
    buffer = GlbBuffer(g)
    _merge_buffers(doc, blobs, buffer)
    buffer.images, buffer.textures = list(doc.images or []), list(doc.textures or [])
    doc.samplers = [*(doc.samplers or []), glb_sampler(g, True)]
    firsts: dict[str, int] = {}
    doc.materials = list(doc.materials or [])
    replaced: dict[int | None, int] = {}
    for k, part in enumerate(source.parts):
        old = part["material"]
        if old not in replaced:
            name = source.slot_names[source.slot[source.part == k][0]]
            sub = folders[source.slot_names.index(name)] if folders else ""
            if sub not in firsts:
                firsts[sub] = buffer.texture_set(Path(textures_dir) / sub, brdf, sampler=len(doc.samplers) - 1)
            new = glb_material(g, name, firsts[sub], brdf, occlusion)
            if old is None:
                doc.materials.append(new)
                replaced[old] = len(doc.materials) - 1
            else:
                new.extras = doc.materials[old].extras
                doc.materials[old] = new
                replaced[old] = old
        doc.meshes[part["mesh"]].primitives[part["primitive"]].material = replaced[old]
    doc.images, doc.textures = buffer.images, buffer.textures
    _drop_unread_textures(doc)
    used = set(doc.extensionsUsed or [])
    if brdf != "gltf":
        used.add("KHR_materials_specular")
    doc.extensionsUsed = sorted(used)
    extras = doc.asset.extras if isinstance(doc.asset.extras, dict) else {}
    doc.asset.extras = {**extras, ORIGIN_METADATA_KEY: origin}
    blob = b"".join(buffer.blobs)
    doc.buffers = [g.Buffer(byteLength=len(blob))]
    doc.bufferViews = buffer.views
    doc.set_binary_blob(blob)
    with atomic_path(path) as tmp:
        doc.save_binary(str(tmp))


def _merge_buffers(doc, blobs: list[bytes], buffer: GlbBuffer) -> None:
    """Every buffer of ``doc`` into ``buffer``'s one blob, its views moved accordingly (keeping
    each view's offset alignment: every buffer starts at a multiple of 8)."""
    starts = []
    offset = 0
    for blob in blobs:
        starts.append(offset)
        pad = b"\x00" * ((-len(blob)) % 8)
        buffer.blobs.append(blob + pad)
        offset += len(blob) + len(pad)
    for view in doc.bufferViews or []:
        view.byteOffset = starts[view.buffer] + (view.byteOffset or 0)
        view.buffer = 0
        buffer.views.append(view)


def _drop_unread_textures(doc) -> None:
    """Remove the textures no material reads and the images no texture shows, renumbering the
    references that remain (texture infos in materials and their extensions, texture sources)."""
    read = set()
    for m in doc.materials:
        _texture_refs(m, lambda i: read.add(i) or i)
    keep_tex = sorted(read)
    tex_map = {old: new for new, old in enumerate(keep_tex)}
    textures = [doc.textures[i] for i in keep_tex]
    shown = sorted({t.source for t in textures if t.source is not None})
    img_map = {old: new for new, old in enumerate(shown)}
    for m in doc.materials:
        _texture_refs(m, lambda i: tex_map[i])
    for t in textures:
        if t.source is not None:
            t.source = img_map[t.source]
    doc.textures = textures
    doc.images = [doc.images[i] for i in shown]


def _texture_refs(node, visit) -> None:
    """Call ``visit(index)`` on every texture reference (an ``index`` under a key ending in
    ``Texture``) in a material (pygltflib objects and extension dictionaries), storing its result."""
    items = node.items() if isinstance(node, dict) else vars(node).items() if hasattr(node, "__dict__") else ()
    for key, value in list(items):
        if value is None:
            continue
        if str(key).endswith("Texture"):
            if isinstance(value, dict) and "index" in value:
                value["index"] = visit(value["index"])
            elif hasattr(value, "index") and value.index is not None:
                value.index = visit(value.index)
            continue
        if isinstance(value, dict) or hasattr(value, "__dict__"):
            _texture_refs(value, visit)
