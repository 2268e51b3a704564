"""The input's own asset back, with new materials: what the export writes where the bake kept the
input's UV layout (``bake.uv``; :mod:`stages.assets.layouts`).

* **glTF input** (GLB or glTF): ``model.glb`` is the input document itself, its buffers merged into
  the one binary chunk; only materials, textures and images change. Each material that a textured
  triangle primitive used is replaced, at its index and under its name, by one reading the baked
  texture set (primitives without a material get one, named ``default``); the textures and images
  no other material reads are dropped; the baked images and a repeating sampler are added. Nodes,
  names, meshes, skins, joints, weights, animations, morph targets, cameras, extras and other
  primitives are untouched; the provenance joins ``asset.extras``. The file stands alone and names
  nothing of the machine: an image the input keeps in a file beside it is embedded, one at a remote
  or absolute URI (which a viewer would fetch) is dropped, and texts in ``extras`` that hold a local
  file system path are removed; the log says what changed.
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

import dataclasses
import json
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np
from PIL import Image

from ..config.brdfs import BrdfSpec, brdf_spec
from ..config.layout import EXPORT_FILES, export_format_of
from ..core.provenance import ORIGIN_METADATA_KEY, atomic_path
from ..core.safefiles import IMAGE_LIMIT, open_read, plain_file, read_bytes
from ..geometry.normalization import Similarity
from ..geometry.sourcemesh import GLTF_SOURCE, ObjLines, SourceMesh, load_gltf_document
from ..geometry.tangents import vertex_tangents
from ..geometry.uvsets import second_uv_set
from ..render.distant import DistantLight
from .formats.base import message_key
from .formats.gltf import (
    LIGHTS_EXTENSION,
    GlbBuffer,
    add_distant_lights,
    glb_material,
    glb_sampler,
    punctual_lights,
    validate_glb,
)
from .formats.mesh import ExportMesh, export_mesh
from .gltfuvset import SecondSet, UvSetWritten, add_uv_set

log = logging.getLogger(__name__)

#: grey images the OBJ's material library reads, from the metallic-roughness texture's channels
OBJ_CHANNELS = {"roughness": 1, "metallic": 2}


def kept_geometry(
    source: SourceMesh, transform: Similarity | None = None, materials=None, second: np.ndarray | None = None
) -> ExportMesh:
    """The input's vertices (:mod:`stages.geometry.sourcemesh`: a glTF primitive's own, an OBJ's
    distinct corners in first-use order) and triangles in file order, its UVs and normals (its
    own; where it has none, smooth vertex normals) and materials (``materials``: per triangle, the
    names and the texture sets' folders, :func:`~stages.assets.layouts.kept_materials`; None: the
    input's slots, one set), in its own units and position, or with ``transform`` in the
    normalised frame. With a ``second`` UV set (``(T, 3, 2)``, the bake's) the UVs are that set's,
    its seam vertices appended (:func:`~stages.geometry.uvsets.second_uv_set`). Tangents:
    MikkTSpace's on its normals and UVs (the frame the bake used) where every corner of a vertex
    has the same one, else none (viewers then compute the same MikkTSpace themselves)."""
    pos = source.positions if transform is None else transform.forward(source.positions)
    normals = source.vertex_normals()
    if transform is not None:
        normals = normals @ transform.rotation.T
    uv, triangles = source.uv, source.triangles
    if second is not None:
        split = second_uv_set(triangles, second, len(pos))
        pos, normals, uv, triangles = pos[split.source], normals[split.source], split.uv.astype(np.float64), split.indices
    material, names, folders = materials or (source.slot, source.slot_names, ())
    return ExportMesh(
        pos.astype(np.float32),
        normals.astype(np.float32),
        uv.astype(np.float32),
        vertex_tangents(pos, normals, uv, triangles),
        triangles.astype(np.int64),
        material,
        names,
        repeat=True,
        slot_textures=folders,
    )


@dataclass(frozen=True)
class AssetGeometry:
    """What an asset's files hold: ``geom`` (its geometry in export space), the input's own
    surface where the bake kept its layout (``kept``), the metres per unit the files state, and
    ``own_frame``: positions are the input's own (``x_original``; a glTF input's document always,
    an OBJ's with ``export.units: original``) rather than the export space of a new atlas
    (``R x_original``, +Y up: :mod:`stages.assets.formats.mesh`) or the normalised frame."""

    geom: ExportMesh
    kept: SourceMesh | None
    meters_per_unit: float
    own_frame: bool


def asset_geometry(
    mesh, atlas: dict, transform: Similarity, settings, kept: SourceMesh | None, materials=None, second=None
) -> AssetGeometry:
    """The geometry the export writes (and the round trip checks) for the traced ``mesh`` and the
    bake's ``atlas`` arrays, with the export ``settings`` (units, weld, metres per unit): the
    traced mesh welded (:func:`~stages.assets.formats.export_mesh`), or the input's own topology
    where the bake kept its layout or made a ``second`` UV set for it (:func:`kept_geometry`,
    with its ``materials``). A glTF input's document keeps its own units (metres, by the
    specification) and position: ``units`` and ``meters_per_unit`` do not apply to it."""
    original = settings.units == "original"
    if kept is None:
        geom = export_mesh(mesh, atlas, transform if original else None, settings.weld)
        return AssetGeometry(geom, None, settings.meters_per_unit, False)
    if kept.kind == GLTF_SOURCE:
        return AssetGeometry(kept_geometry(kept, None, materials, second), kept, 1.0, True)
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
def write_obj(
    folder: Path, geom: ExportMesh, source: SourceMesh, transform: Similarity | None, brdf: BrdfSpec | str
) -> list[str]:
    """``model.obj`` and ``model.mtl`` in ``folder`` (which holds ``textures/``), and the grey
    channel images the MTL reads (module docstring), for ``geom`` (:func:`kept_geometry` of
    ``source``: its slots and texture sets); returns the files written (relative)."""
    folder = Path(folder)
    written = ["model.obj", "model.mtl"]
    for sub in sorted(set(geom.slot_textures) | {""}):
        textures = folder / "textures" / sub
        for key, channel in OBJ_CHANNELS.items():
            with open_read(textures / "metallic_roughness.png", IMAGE_LIMIT) as fh, Image.open(fh) as img:
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


def mtl_text(names: tuple[str, ...], folders: list[str], brdf: BrdfSpec | str) -> str:
    """One material per name reading its texture set (in ``textures/<folder>``): base colour,
    roughness, normal map, and the BRDF's specular parameter (``brdf.mtl_lines``: TANGO's specular
    colour or glTF's metallic)."""
    brdf = brdf_spec(brdf)
    blocks = []
    for name, sub in zip(names, folders, strict=True):
        t = "/".join(p for p in ("textures", sub) if p)
        lines = [f"newmtl {name}", "Kd 1 1 1", "Pr 1", f"map_Kd {t}/basecolor.png", f"map_Pr {t}/roughness.png"]
        lines += brdf.mtl_lines(t)
        lines += [f"map_Bump -bm 1 {t}/normal.png", f"norm {t}/normal.png"]
        blocks.append("\n".join(lines))
    return "# tango-stylize: the baked texture sets, one material per input material\n" + "\n\n".join(blocks) + "\n"


# ----------------------------------------------------------------------------------------- glTF
#: the file a glTF input's own document is written as, and the export format whose writer it
#: stands in for (:func:`own_document`)
DOCUMENT_FILE = EXPORT_FILES["glb"]
DOCUMENT_FORMAT = export_format_of("glb").name


def own_document(
    source: SourceMesh,
    origin: dict,
    brdf: BrdfSpec | str,
    occlusion: bool,
    folders: tuple[str, ...],
    changed: list[str],
    lights: tuple[DistantLight, ...] = (),
    second: SecondSet | None = None,
) -> dict[str, Callable[[Path], None]]:
    """The writer of a glTF input's own document (:func:`write_document_glb` into a folder's
    :data:`DOCUMENT_FILE`, reading the folder's ``textures/``; with the ``second`` UV set where
    the bake made one) in place of its format's writer, as
    :func:`stages.assets.formats.write_asset_files` takes it (``instead``); each change to the
    document is appended to ``changed``."""

    def write(folder: Path) -> None:
        folder = Path(folder)
        textures = folder / "textures"
        notes = write_document_glb(folder / DOCUMENT_FILE, source, textures, origin, brdf, occlusion, folders, lights, second)
        changed.extend(notes)

    return {DOCUMENT_FORMAT: write}


def write_document_glb(
    path: Path,
    source: SourceMesh,
    textures_dir: Path,
    origin: dict,
    brdf: BrdfSpec | str,
    occlusion: bool,
    folders: tuple[str, ...] = (),
    lights: tuple[DistantLight, ...] = (),
    second: SecondSet | None = None,
) -> list[str]:
    """``model.glb``: the input glTF document with its textured primitives' materials replaced by
    ones reading the baked texture sets (module docstring; ``folders``: each slot's set below
    ``textures_dir``), the learned suns (``lights``) added as lights. Where the bake made a
    ``second`` UV set, the primitives get it (:func:`~stages.assets.gltfuvset.add_uv_set`; what
    was done is left in ``second.written``) and the materials read it. The file needs
    nothing beside it and names nothing of this machine: images are embedded or dropped
    (:func:`own_images`), local paths in ``extras`` removed (:func:`drop_local_paths`); each
    change is logged and returned, one line each."""
    import pygltflib as g

    brdf = brdf_spec(brdf)
    doc, blobs = load_gltf_document(source.path)
    for acc in doc.accessors or []:  # pygltflib reads an absent offset as 0; without a view it must stay absent
        if acc.bufferView is None:
            acc.byteOffset = None
    buffer = GlbBuffer(g)
    _merge_buffers(doc, blobs, buffer)
    texcoord, set_notes = 0, []
    if second is not None:
        doc.accessors = list(doc.accessors or [])
        written = second.written = add_uv_set(doc, buffer, b"".join(buffer.blobs), source, second.corner_uv)
        texcoord = written.texcoord
        set_notes = [uv_set_note(written), *dict.fromkeys(written.notes)]
    buffer.images, buffer.textures = list(doc.images or []), list(doc.textures or [])
    doc.samplers = [*(doc.samplers or []), glb_sampler(g, True)]
    firsts: dict[str, int] = {}
    doc.materials = list(doc.materials or [])
    replaced: dict[int | None, int] = {}
    shared = _materials_elsewhere(doc, source) if texcoord else set()
    for k, part in enumerate(source.parts):
        old = part["material"]
        if old not in replaced:
            name = source.slot_names[source.slot[source.part == k][0]]
            sub = folders[source.slot_names.index(name)] if folders else ""
            if sub not in firsts:
                firsts[sub] = buffer.texture_set(Path(textures_dir) / sub, brdf, sampler=len(doc.samplers) - 1)
            new = glb_material(g, name, firsts[sub], brdf, occlusion, texcoord)
            if old is None or old in shared:  # also the material of primitives without the new set: a new one
                doc.materials.append(new)
                replaced[old] = len(doc.materials) - 1
            else:
                new.extras = doc.materials[old].extras
                doc.materials[old] = new
                replaced[old] = old
        doc.meshes[part["mesh"]].primitives[part["primitive"]].material = replaced[old]
    doc.images, doc.textures = buffer.images, buffer.textures
    notes = own_images(doc, buffer, Path(source.path).parent)
    _drop_unread_textures(doc)
    notes += drop_local_paths(doc)
    for note in notes:
        log.warning("%s: %s", Path(source.path).name, note)
    for note in set_notes:
        log.info("%s: %s", Path(source.path).name, note)
    notes += set_notes + _add_lights(g, doc, lights)
    doc.extensionsUsed = sorted(set(doc.extensionsUsed or []) | set(brdf.gltf_extensions))
    extras = doc.asset.extras if isinstance(doc.asset.extras, dict) else {}
    doc.asset.extras = {**extras, ORIGIN_METADATA_KEY: origin}
    blob = b"".join(buffer.blobs)
    doc.buffers = [g.Buffer(byteLength=len(blob))]
    doc.bufferViews = buffer.views
    doc.set_binary_blob(blob)
    with atomic_path(path) as tmp:
        doc.save_binary(str(tmp))
    return notes


def _materials_elsewhere(doc, source: SourceMesh) -> set[int]:
    """The materials that a primitive other than the textured triangle primitives of ``source``
    uses (lines, points, a mesh outside the default scene): replaced in place, they would read a
    UV set those primitives lack."""
    ours = {(part["mesh"], part["primitive"]) for part in source.parts}
    return {
        prim.material
        for m, mesh in enumerate(doc.meshes or [])
        for p, prim in enumerate(mesh.primitives)
        if (m, p) not in ours and prim.material is not None
    }


def input_faults(source: SourceMesh) -> tuple[dict[str, set[str]], dict]:
    """What the Khronos glTF-Validator finds wrong with a glTF input itself (its buffers and images
    read from its folder): per file the export writes from it (:data:`DOCUMENT_FILE`), the faults
    (:func:`~stages.assets.formats.message_key`) of its errors, which the document hands on and
    which are therefore not the export's; and the input's counts for the record (``ran`` False
    where the validator is not installed)."""
    report = validate_glb(source.path)
    if not report.get("ran"):
        return {}, {"ran": False}
    errors = report["messages"][: report["errors"]]
    summary = {"errors": report["errors"], "warnings": report["warnings"], "first": errors[0] if errors else None}
    return {DOCUMENT_FILE: {message_key(m) for m in errors}}, summary


def uv_set_note(written: UvSetWritten) -> str:
    """The line the export's record and log give a second UV set (:func:`add_uv_set`)."""
    return (
        f"the bake's UV set added as TEXCOORD_{written.texcoord} to {written.primitives} primitive(s), the input's own "
        f"UVs kept: {written.appended:,} seam vertices appended after the input's {written.vertices:,}, "
        f"{written.rewritten:,} corners re-indexed to them"
    )


def _add_lights(g, doc, lights: tuple[DistantLight, ...]) -> list[str]:
    """The learned suns into the document: ``KHR_lights_punctual`` directional lights after its
    own lights, one node each in its default scene; the change, one line (none without suns)."""
    if not lights:
        return []
    ext = dict(doc.extensions or {})
    own = list(ext.get(LIGHTS_EXTENSION, {}).get("lights", []))
    ext[LIGHTS_EXTENSION] = {**ext.get(LIGHTS_EXTENSION, {}), "lights": [*own, *punctual_lights(lights)]}
    doc.extensions = ext
    doc.nodes = list(doc.nodes or [])
    used = list(doc.extensionsUsed or [])
    added = add_distant_lights(g, doc.nodes, lights, used, len(own))
    doc.extensionsUsed = used
    if not doc.scenes:
        doc.scenes = [g.Scene(nodes=[])]
    scene = doc.scenes[doc.scene or 0]
    scene.nodes = [*(scene.nodes or []), *added]
    return [f"added the {len(lights)} learned sun(s) as {LIGHTS_EXTENSION} directional lights (nodes {added})"]


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


# ------------------------------------------------------------- what the input's document hands on
#: a local file system path within a text: POSIX (``/a/b``), Windows (``C:\``, ``\\server``), home, ``file:``
LOCAL_PATH = re.compile(r"""(?:^|[\s"'(<\[=,;:])(?:file:|~[\\/]|[A-Za-z]:[\\/]|\\\\[^\\\s]|/[^/\s]+/)""", re.IGNORECASE)
#: the image types a GLB embeds, by their first bytes (WebP: ``RIFF....WEBP``)
IMAGE_MAGIC = ((b"\x89PNG\r\n\x1a\n", "image/png"), (b"\xff\xd8\xff", "image/jpeg"), (b"\xabKTX 20\xbb\r\n\x1a\n", "image/ktx2"))


def own_images(doc, buffer: GlbBuffer, folder: Path) -> list[str]:
    """Keep the document's images inside ``model.glb``: an image whose ``uri`` is a relative path
    to a plain file in the input's ``folder`` (no ``..``, no link on the way; a PNG, JPEG, WebP or
    KTX2 image) is embedded in ``buffer``; any other ``uri`` but a ``data:`` URI (a remote or
    absolute one, which a viewer would fetch) is dropped, with the material references to the
    textures that show it (:func:`_drop_unread_textures` then removes them). Returns what was
    done, one line per image, naming no path."""
    notes, dropped = [], set()
    for k, image in enumerate(doc.images or []):
        uri = image.uri
        if uri is None or (isinstance(uri, str) and uri.startswith("data:")):
            continue
        found = _local_image(uri, folder)
        if isinstance(found, str):
            dropped.add(k)
            image.uri = None
            notes.append(f"image {k} dropped: its uri is {found}")
        else:
            image.uri, image.mimeType = None, found[1]
            image.bufferView = buffer.view(found[0])
            notes.append(f"image {k} embedded from the input's folder")
    if dropped:
        gone = {t for t, texture in enumerate(doc.textures or []) if _image_refs(texture) & dropped}
        for material in doc.materials or []:
            _forget_textures(material, gone)
    return notes


def _local_image(uri, folder: Path) -> tuple[bytes, str] | str:
    """The bytes and media type of the image a relative ``uri`` names in ``folder``, or why not."""
    if not isinstance(uri, str):
        return "not text"
    try:
        parts = urlsplit(uri)
    except ValueError:
        return "not a URI"
    if len(parts.scheme) == 1 or uri.startswith(("/", "\\")):
        return "an absolute path"
    if parts.scheme:
        return f"of the {parts.scheme.lower()[:20]}: scheme (a viewer would fetch it)"
    if parts.netloc or parts.query or parts.fragment:
        return "a URI with a host, query or fragment"
    rel = unquote(parts.path).replace("\\", "/")
    if any(ord(c) < 32 for c in rel):
        return "not a file name (it holds a control character)"
    if ".." in rel.split("/"):
        return "a path that leaves the input's folder"
    path = Path(folder) / rel
    if not rel or not plain_file(path, folder):
        return "not a plain file in the input's folder"
    data = read_bytes(path, IMAGE_LIMIT, folder)
    mime = next((m for magic, m in IMAGE_MAGIC if data.startswith(magic)), None)
    if mime is None and data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        mime = "image/webp"
    return (data, mime) if mime is not None else "not a PNG, JPEG, WebP or KTX2 image"


def _image_refs(texture) -> set:
    """The images a texture shows: its ``source`` and its extensions' (``EXT_texture_webp``, ...)."""
    refs = {texture.source}
    for ext in (texture.extensions or {}).values():
        if isinstance(ext, dict):
            refs.add(ext.get("source"))
    return refs - {None}


def _forget_textures(node, gone: set) -> None:
    """Remove from a material every texture reference (under a key ending in ``Texture``) to a
    texture in ``gone``."""
    items = node.items() if isinstance(node, dict) else vars(node).items() if hasattr(node, "__dict__") else ()
    for key, value in list(items):
        if value is None:
            continue
        if str(key).endswith("Texture"):
            index = value.get("index") if isinstance(value, dict) else getattr(value, "index", None)
            if index in gone:
                if isinstance(node, dict):
                    del node[key]
                else:
                    setattr(node, key, None)
            continue
        if isinstance(value, dict) or hasattr(value, "__dict__"):
            _forget_textures(value, gone)


def drop_local_paths(doc) -> list[str]:
    """Remove what would tell a reader of ``model.glb`` about the machine it was made on: every
    text in an ``extras`` (at any depth, and every key) that holds a local file system path
    (:data:`LOCAL_PATH`: ``/home/...``, ``C:\\...``, ``\\\\server``, ``~/``, ``file:``), and every
    ``uri`` in an extension but a ``data:`` URI (a viewer would fetch it). Names stay as they are.
    Returns one line per removal, a JSON pointer to where it was (naming no path)."""
    notes = []
    stack = [("", doc)]
    while stack:
        where, node = stack.pop()
        for key, value in _fields(node):
            here = f"{where}/{_pointer(key)}"
            if key == "extras":
                kept, removed = _without_local_paths(value, here)
                notes += removed
                if isinstance(node, dict) and kept is None:
                    del node[key]
                elif isinstance(node, dict):
                    node[key] = kept
                else:
                    setattr(node, key, kept if kept is not None else {})
            elif key == "uri" and isinstance(node, dict) and isinstance(value, str) and not value.startswith("data:"):
                del node[key]
                notes.append(f"{here}: a URI in an extension, removed")
            elif isinstance(value, (dict, list)) or dataclasses.is_dataclass(value):
                stack.append((here, value))
    return notes


def _fields(node) -> list:
    """The (key, value) pairs of a JSON object, array (index, value) or pygltflib object."""
    if isinstance(node, dict):
        return list(node.items())
    if isinstance(node, list):
        return list(enumerate(node))
    if dataclasses.is_dataclass(node) and not isinstance(node, type):
        return [(k, v) for k, v in vars(node).items() if not k.startswith("_")]
    return []


def _pointer(key) -> str:
    """A JSON pointer's step for ``key``, on one line."""
    return json.dumps(str(key))[1:-1].replace("~", "~0").replace("/", "~1")


def _without_local_paths(value, where: str):
    """``value`` (an ``extras``) without the texts and keys that hold a local path, and a line for
    each removed; a text that is one is removed whole (None)."""
    if isinstance(value, str):
        return (None, [f"{where}: a local file path, removed"]) if LOCAL_PATH.search(value) else (value, [])
    removed = []
    stack = [(value, where)]
    while stack:
        node, at = stack.pop()
        if not isinstance(node, (dict, list)):
            continue
        drop = []
        for key, item in _fields(node):
            if isinstance(key, str) and LOCAL_PATH.search(key):
                drop.append(key)
                removed.append(f"{at}: a key that is a local file path, removed")
            elif isinstance(item, str) and LOCAL_PATH.search(item):
                drop.append(key)
                removed.append(f"{at}/{_pointer(key)}: a local file path, removed")
            else:
                stack.append((item, f"{at}/{_pointer(key)}"))
        for key in reversed(drop):
            del node[key]
    return value, removed
