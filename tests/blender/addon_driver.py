"""Run inside Blender (``python addon_driver.py JOB.json``, a Python with bpy): install the add-on's zip
with Blender's own extension installer, build a rigged, animated, UV-mapped scene, stylise the
selected objects with the add-on's operator and write what changed to ``JOB["out"]`` (JSON).

The scene: ``Body``, a UV sphere with its own UV map (and a second one, ``Detail``), weighted to a
two-bone armature whose upper bone is animated, with two material slots; ``Box``, a cube whose UV
map was removed (the add-on must make one) and whose one slot holds the body's first material.
What is recorded before and after, per object: the vertices, every UV map's coordinates, the
vertex groups' weights, the material slots and what their materials read; and the armature's
bones and the action's keyframes."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import bpy
import numpy as np


def build_scene() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, radius=1.0, location=(0, 0, 1))
    body = bpy.context.active_object
    body.name = "Body"
    body.data.uv_layers.new(name="Detail")
    for k, name in enumerate(("Skin", "Cap")):
        mat = bpy.data.materials.new(name)
        body.data.materials.append(mat)
        if k:
            for poly in body.data.polygons:
                poly.material_index = int(poly.center.z > 0.5)  # the top: the second slot
    bpy.ops.object.armature_add(location=(0, 0, 0))
    rig = bpy.context.active_object
    rig.name = "Rig"
    bpy.ops.object.mode_set(mode="EDIT")
    lower = rig.data.edit_bones[0]
    lower.name, lower.head, lower.tail = "Lower", (0, 0, 0), (0, 0, 1)
    upper = rig.data.edit_bones.new("Upper")
    upper.head, upper.tail, upper.parent = (0, 0, 1), (0, 0, 2), lower
    bpy.ops.object.mode_set(mode="OBJECT")
    for name in ("Lower", "Upper"):
        group = body.vertex_groups.new(name=name)
        for v in body.data.vertices:
            upper = 0.5 * (v.co.z + 1.0)  # the sphere's local height, 0 at its bottom, 1 at its top
            group.add([v.index], upper if name == "Upper" else 1.0 - upper, "REPLACE")
    body.parent = rig
    body.modifiers.new("Armature", "ARMATURE").object = rig
    pose = rig.pose.bones["Upper"]
    pose.rotation_mode = "XYZ"
    for frame, angle in ((1, 0.0), (24, 0.6)):
        pose.rotation_euler = (angle, 0.0, 0.0)
        pose.keyframe_insert("rotation_euler", frame=frame)
    bpy.ops.mesh.primitive_cube_add(size=0.8, location=(2.5, 0, 0.4))
    box = bpy.context.active_object
    box.name = "Box"
    box.data.uv_layers.remove(box.data.uv_layers[0])
    box.data.materials.append(bpy.data.materials["Skin"])  # one material on two objects, each with its own UVs
    bpy.ops.object.select_all(action="DESELECT")
    body.select_set(True)
    box.select_set(True)
    bpy.context.view_layer.objects.active = body


def _slot(slot) -> dict:
    """A material slot: its material's name, images (names, sizes, packed or files), the UV maps its
    nodes read by name and the Principled BSDF's linked inputs."""
    mat = slot.material
    nodes = [] if mat is None or mat.node_tree is None else mat.node_tree.nodes
    textures = [n for n in nodes if n.type == "TEX_IMAGE" and n.image is not None]
    principled = next((n for n in nodes if n.type == "BSDF_PRINCIPLED"), None)
    return {
        "material": mat.name if mat else None,
        "images": sorted(n.image.name for n in textures),
        "uv_maps": sorted({n.uv_map for n in nodes if n.type in ("UVMAP", "NORMAL_MAP")}),
        "packed": all(n.image.packed_file is not None for n in textures),
        "sizes": sorted({tuple(n.image.size) for n in textures}),
        "wired": sorted(i.name for i in principled.inputs if i.links) if principled is not None else [],
        "files": [n.image.filepath for n in textures],
    }


def _object(ob) -> dict:
    me = ob.data
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    uvs = {}
    for layer in me.uv_layers:
        raw = np.empty(len(me.loops) * 2)
        layer.data.foreach_get("uv", raw)
        uvs[layer.name] = raw.round(7).tolist()
    return {
        "vertices": co.round(7).tolist(),
        "polygons": len(me.polygons),
        "uv_maps": uvs,
        "weights": [[(g.group, round(g.weight, 7)) for g in v.groups] for v in me.vertices],
        "slots": [_slot(slot) for slot in ob.material_slots],
        "parent": ob.parent.name if ob.parent else None,
        "modifiers": [m.type for m in ob.modifiers],
        "provenance": json.loads(ob.get("tango_stylize", "{}")),
    }


def _curves(action) -> list:
    """An action's F-curves (Blender 5's layered actions: every channel bag's)."""
    if hasattr(action, "fcurves"):
        return list(action.fcurves)
    return [c for layer in action.layers for strip in layer.strips for bag in strip.channelbags for c in bag.fcurves]


def record() -> dict:
    out = {"objects": {ob.name: _object(ob) for ob in bpy.data.objects if ob.type == "MESH"}}
    rig = bpy.data.objects.get("Rig")
    if rig is not None:
        bones = rig.data.bones
        out["bones"] = [(b.name, [round(x, 7) for x in b.head_local], b.parent.name if b.parent else None) for b in bones]
        action = rig.animation_data.action if rig.animation_data else None
        curves = _curves(action) if action is not None else []
        keys = [(c.data_path, c.array_index, tuple(round(x, 7) for x in k.co)) for c in curves for k in c.keyframe_points]
        out["keys"] = sorted(keys)
    out["world"] = bpy.context.scene.world.name if bpy.context.scene.world else None
    out["lights"] = [ob.name for ob in bpy.data.objects if ob.type == "LIGHT"]
    return out


def main(argv: list[str]) -> int:
    job = json.loads(Path(argv[-1]).read_text())
    build_scene()
    result = bpy.ops.extensions.package_install_files(filepath=job["zip"], repo="user_default", enable_on_install=True)
    assert "FINISHED" in result, result
    addon = "bl_ext.user_default.tango_stylize"
    prefs = bpy.context.preferences.addons[addon].preferences
    prefs.python, prefs.workdir, prefs.test_clip, prefs.overlays = job["python"], job["workdir"], True, job["overlay"]
    settings = bpy.context.scene.tango_stylize
    settings.prompt, settings.preset, settings.add_light = "a ball made of wood", "fast", True
    before = record()
    result = bpy.ops.tango.stylise_selected()
    after = record()
    # the body again, as its modifiers make it (a subdivision), into a new UV map: a stylised copy beside it
    body = bpy.data.objects["Body"]
    body.modifiers.new("Subdivision", "SUBSURF").levels = 1
    bpy.ops.object.select_all(action="DESELECT")
    body.select_set(True)
    settings.apply_modifiers, settings.layout, settings.add_light, settings.pack = True, "NEW", False, False
    applied = bpy.ops.tango.stylise_selected()
    out = {"result": sorted(result), "applied": sorted(applied), "before": before, "after": after, "copy": record()}
    Path(job["out"]).write_text(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
