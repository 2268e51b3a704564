"""What passes between Blender and the workflow: the selected objects out as a GLB, and the
stylised materials back onto the same objects.

Out: one glTF node and mesh per object, in world space (the object's transform applied, in
glTF's +Y up), one primitive per material slot it uses (one material per object and slot, named
``tango_<run>_m<k>``, so that they come back under names nothing else has), its corner normals, and its bake UV map as
``TEXCOORD_0``: one glTF vertex per distinct (vertex, normal, UV) corner. Nothing of the object
changes; the rig, shape keys and animation are not needed to paint the surface and stay in Blender.

Back: the finished run's ``model.glb`` is imported into a scratch collection, its materials (which
Blender's own glTF importer wires: base colour, metallic-roughness, normal map, occlusion, the
specular colour) are renamed after the object's, made to read the bake UV map by name, and put
in the object's slots; the scratch objects are removed. The object's vertices, UV maps, vertex
groups, modifiers, rig and animation are untouched.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

#: the UV map the add-on makes where an object has none it can bake into
BAKE_UV_MAP = "TANGO"
#: Blender +Z up to glTF +Y up: (x, y, z) -> (x, z, -y)
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: Blender's equirectangular lookup puts the light image's column ``u`` at its ``u + 1/2``: the world
#: is turned half a turn about +Z (stages/reference/blender.py's WORLD_ROTATION_Z, measured there)
WORLD_ROTATION_Z = math.pi


@dataclass
class Exported:
    """What :func:`write_glb` wrote: per object, the glTF material index of each of its slots
    (None: a slot with no faces), and the UV map each object's ``TEXCOORD_0`` holds."""

    slots: dict[str, list[int | None]]
    uv_maps: dict[str, str | None]


def own_uv_map(ob) -> str | None:
    """The UV map Blender renders an object with (None: it has none)."""
    active = next((uv for uv in ob.data.uv_layers if uv.active_render), None)
    return active.name if active is not None else None


def make_bake_uv_map(ob, margin: float = 0.003) -> str:
    """A new UV map for the bake (:data:`BAKE_UV_MAP`), unwrapped by Blender's Smart UV Project;
    the object's own maps and its active and render choices stay as they are."""
    me = ob.data
    active = me.uv_layers.active.name if me.uv_layers.active else None
    render = own_uv_map(ob)
    layer = me.uv_layers.get(BAKE_UV_MAP) or me.uv_layers.new(name=BAKE_UV_MAP, do_init=False)
    me.uv_layers.active = layer
    picked = np.empty(len(me.polygons), bool)  # the mesh's own face selection, put back after
    me.polygons.foreach_get("select", picked)
    with kept_selection():
        for o in bpy.context.view_layer.objects:  # edit mode takes every selected object: unwrap this one alone
            o.select_set(o == ob)
        bpy.context.view_layer.objects.active = ob
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.select_all(action="SELECT")
        bpy.ops.uv.smart_project(angle_limit=math.radians(66.0), island_margin=margin)
        bpy.ops.object.mode_set(mode="OBJECT")
    me.polygons.foreach_set("select", picked)
    if active is not None:
        me.uv_layers.active = me.uv_layers[active]
    if render is not None:
        me.uv_layers[render].active_render = True
    return BAKE_UV_MAP


class kept_selection:
    """The view layer's selected and active objects, put back as they were on leaving."""

    def __enter__(self):
        layer = bpy.context.view_layer
        self.active, self.selected = layer.objects.active, {o.name for o in layer.objects if o.select_get()}
        return self

    def __exit__(self, *exc):
        layer = bpy.context.view_layer
        for o in layer.objects:
            o.select_set(o.name in self.selected)
        if self.active is not None and self.active.name in layer.objects:
            layer.objects.active = self.active
        return False


def _corners(ob, uv_map: str | None) -> dict[str, np.ndarray]:
    """An object's triangle corners: world positions and normals (glTF's frame), the bake UV map's
    coordinates (glTF's v down; NaN where it has none), per triangle its slot, and each corner's
    vertex."""
    me = ob.data
    me.calc_loop_triangles()
    tris = len(me.loop_triangles)
    if not tris:
        raise RuntimeError(f"{ob.name} has no faces to stylise")
    loops = np.empty(tris * 3, np.int64)
    me.loop_triangles.foreach_get("loops", loops)
    slot = np.empty(tris, np.int64)
    me.loop_triangles.foreach_get("material_index", slot)
    vert = np.empty(len(me.loops), np.int64)
    me.loops.foreach_get("vertex_index", vert)
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    normals = np.empty(len(me.loops) * 3)
    me.corner_normals.foreach_get("vector", normals)
    m = np.array(ob.matrix_world)
    lin = Z_UP_TO_Y_UP @ m[:3, :3]
    pos = co.reshape(-1, 3) @ lin.T + Z_UP_TO_Y_UP @ m[:3, 3]
    n = normals.reshape(-1, 3) @ np.linalg.inv(m[:3, :3]) @ Z_UP_TO_Y_UP.T
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    uv = np.full((len(me.loops), 2), np.nan)
    if uv_map is not None:
        raw = np.empty(len(me.loops) * 2)
        me.uv_layers[uv_map].data.foreach_get("uv", raw)
        uv = raw.reshape(-1, 2) * [1.0, -1.0] + [0.0, 1.0]
    tri = loops.reshape(-1, 3)
    if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform: the winding turned, as exporters do
        tri = tri[:, [0, 2, 1]]
    return {"position": pos[vert], "normal": n, "uv": uv, "triangles": tri, "slot": slot}


def write_glb(objects, path: Path, uv_maps: dict[str, str | None], prefix: str) -> Exported:
    """``objects`` (mesh objects) as one GLB at ``path`` (module docstring), each with the UV map
    ``uv_maps[name]`` as ``TEXCOORD_0``, one material per object and slot named
    ``<prefix>m<k>``."""
    blob, views, accessors, meshes, nodes, materials = bytearray(), [], [], [], [], []
    exported = Exported({}, {})

    def add(arr: np.ndarray, kind: str, component: int, target: int, bounds: bool = False) -> int:
        data = np.ascontiguousarray(arr).tobytes()
        blob.extend(b"\0" * ((-len(blob)) % 4))
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), "target": target})
        blob.extend(data)
        acc = {"bufferView": len(views) - 1, "componentType": component, "count": len(arr), "type": kind}
        if bounds:
            acc.update(min=arr.min(0).tolist(), max=arr.max(0).tolist())
        accessors.append(acc)
        return len(accessors) - 1

    for k, ob in enumerate(objects):
        c = _corners(ob, uv_maps[ob.name])
        uv = np.nan_to_num(c["uv"], nan=-1.0)
        key = np.concatenate([c["position"], c["normal"], uv], axis=1).astype(np.float32)
        _, first, corner = np.unique(key.view(np.uint32), axis=0, return_index=True, return_inverse=True)
        corner = corner.reshape(-1)
        attrs = {
            "POSITION": add(c["position"][first].astype(np.float32), "VEC3", 5126, 34962, True),
            "NORMAL": add(c["normal"][first].astype(np.float32), "VEC3", 5126, 34962),
        }
        if np.isfinite(c["uv"]).all():
            attrs["TEXCOORD_0"] = add(c["uv"][first].astype(np.float32), "VEC2", 5126, 34962)
        prims, slots = [], []
        for s in range(max(len(ob.material_slots), 1)):  # each object's slot its own material: its own UVs
            faces = c["triangles"][c["slot"] == s]
            if not len(faces):
                slots.append(None)
                continue
            materials.append({"name": f"{prefix}m{len(materials)}"})
            idx = corner[faces].reshape(-1).astype(np.uint32)
            prims.append({"attributes": attrs, "indices": add(idx, "SCALAR", 5125, 34963), "material": len(materials) - 1})
            slots.append(len(materials) - 1)
        meshes.append({"name": ob.data.name, "primitives": prims})
        nodes.append({"name": f"{prefix}o{k}", "mesh": k})
        exported.slots[ob.name] = slots
        exported.uv_maps[ob.name] = uv_maps[ob.name]
    doc = {
        "asset": {"version": "2.0", "generator": "tango-stylize Blender add-on"},
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }
    _save_glb(path, doc, bytes(blob))
    return exported


def _save_glb(path: Path, doc: dict, blob: bytes) -> None:
    """A GLB file: the JSON chunk (space-padded) and the binary chunk (zero-padded), written whole
    or not at all."""
    text = json.dumps(doc).encode()
    text += b" " * ((-len(text)) % 4)
    blob += b"\0" * ((-len(blob)) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    tmp.replace(path)


def import_materials(glb: Path, count: int, prefix: str) -> tuple[list, list]:
    """The stylised materials ``<prefix>m0 .. <prefix>m<count-1>`` of a finished run's ``glb``,
    imported by Blender's glTF importer into a scratch collection, and the lights it carries (the
    learned suns). The imported meshes are removed; the lights are returned unlinked; the
    selection is left as it was."""
    scratch = bpy.data.collections.new("tango_import")
    bpy.context.scene.collection.children.link(scratch)
    layer = bpy.context.view_layer.layer_collection.children[scratch.name]
    previous = bpy.context.view_layer.active_layer_collection
    bpy.context.view_layer.active_layer_collection = layer
    before = set(bpy.data.materials)
    try:
        with kept_selection():
            result = bpy.ops.import_scene.gltf(filepath=str(glb))
    finally:
        bpy.context.view_layer.active_layer_collection = previous
    if "FINISHED" not in result:
        raise RuntimeError(f"Blender's glTF importer could not read {glb}")
    new = {m.name: m for m in set(bpy.data.materials) - before}
    materials = [new.get(f"{prefix}m{k}") for k in range(count)]
    lights = [ob for ob in scratch.all_objects if ob.type == "LIGHT"]
    for ob in list(scratch.all_objects):
        if ob.type == "LIGHT":
            scratch.objects.unlink(ob)
            continue
        data = ob.data
        bpy.data.objects.remove(ob)
        if isinstance(data, bpy.types.Mesh) and data.users == 0:
            bpy.data.meshes.remove(data)
    bpy.data.collections.remove(scratch)
    if any(m is None for m in materials):
        raise RuntimeError(f"{glb} does not hold the {count} materials it was sent with")
    return materials, lights


def read_uv_map(material, uv_map: str) -> None:
    """Make every image texture and normal map of ``material`` read the UV map ``uv_map`` by name
    (the importer lets a glTF ``TEXCOORD_0`` texture read the render UV map)."""
    tree = material.node_tree
    for node in list(tree.nodes):
        if node.type == "NORMAL_MAP":
            node.uv_map = uv_map
        if node.type != "TEX_IMAGE":
            continue
        vector = node.inputs["Vector"]
        source = vector.links[0].from_node if vector.links else None
        if source is not None and source.type == "UVMAP":
            source.uv_map = uv_map
            continue
        if source is None:
            uv = tree.nodes.new("ShaderNodeUVMap")
            uv.uv_map = uv_map
            uv.location = (node.location.x - 250, node.location.y)
            tree.links.new(uv.outputs["UV"], vector)
        else:  # a mapping node (KHR_texture_transform) between: feed its input
            inner = source.inputs.get("Vector")
            if inner is not None and inner.links and inner.links[0].from_node.type == "UVMAP":
                inner.links[0].from_node.uv_map = uv_map


def keep_images(materials, pack: bool, folder: Path | None) -> None:
    """The materials' images packed into the .blend (``pack``) or written as PNG files into
    ``folder`` (beside the .blend) and read from there."""
    images = {n.image for m in materials for n in m.node_tree.nodes if n.type == "TEX_IMAGE" and n.image is not None}
    for image in images:
        if pack:
            if image.packed_file is None:
                image.pack()
            continue
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{bpy.path.clean_name(image.name)}.png"
        image.filepath_raw = str(path)
        image.file_format = "PNG"
        image.save()
        if image.packed_file is not None:
            image.unpack(method="REMOVE")
        image.filepath = bpy.path.relpath(str(path)) if bpy.data.filepath else str(path)  # moves with the .blend


def add_world(light_hdr: Path, name: str):
    """A world lit by the learned light (``light.hdr``, linear radiance), turned as the judge turns
    it (:data:`WORLD_ROTATION_Z`); returns it (the caller sets it on the scene)."""
    world = bpy.data.worlds.new(name)
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    tex = nt.nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(str(light_hdr), check_existing=True)
    tex.image.colorspace_settings.name = "Linear Rec.709"
    coords, mapping = nt.nodes.new("ShaderNodeTexCoord"), nt.nodes.new("ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, WORLD_ROTATION_Z)
    bg, out = nt.nodes.new("ShaderNodeBackground"), nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return world
