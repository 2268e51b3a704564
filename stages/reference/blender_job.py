"""One Blender job: import an exported asset, describe what arrived, and render it with Cycles.

This file runs *inside Blender's Python* (``bpy``: the ``blender`` environment that
``scripts/setup.sh`` makes in ``.venv-blender``, or a Blender install as ``blender -b --python
blender_job.py -- job.json``), never in the project's environment: it imports only ``bpy``,
``numpy`` and the standard library, and nothing from ``stages``. The project side
(:mod:`stages.reference.blender`) writes the job, runs this file in a subprocess and reads the
answer, so Blender's own pins (``bpy`` 5.0 needs ``numpy < 2``) never touch the main environment.

Job (JSON): ``asset`` (a ``.glb``/``.gltf``, ``.usd``/``.usda``/``.usdz``), ``out`` (a folder), and
optionally ``inspect: true`` and ``render: {...}`` (see :func:`render`). Answer: ``out/report.json``
(objects, meshes, the material's node graph from the Principled BSDF's inputs back to the image
textures, the world) plus ``out/mesh.npz`` (per face corner: world position, UV, normal, Blender's
own MikkTSpace tangent and bitangent sign) and ``out/render.npz`` (linear RGBA per camera and seed).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

#: Principled BSDF inputs whose wiring the report describes
PRINCIPLED_INPUTS = ("Base Color", "Roughness", "Metallic", "Normal", "Specular Tint", "Specular IOR Level", "IOR")


def reset_scene() -> None:
    """An empty scene with an empty world (the USD importer turns a DomeLight into the scene's
    world only when the scene has one)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.world = bpy.data.worlds.new("World")
    scene.world.use_nodes = True


def import_asset(path: Path) -> None:
    """Import an asset by its suffix; armatures are set to their rest pose, so that a skinned mesh
    is drawn as the file stores it (what our renders show), not in an animation's first frame."""
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        result = bpy.ops.import_scene.gltf(filepath=str(path))
    elif suffix in (".usd", ".usda", ".usdc", ".usdz"):
        result = bpy.ops.wm.usd_import(filepath=str(path))
    elif suffix == ".obj":
        result = bpy.ops.wm.obj_import(filepath=str(path))
    else:
        raise SystemExit(f"{path}: not an asset Blender imports here (.glb, .gltf, .usd, .usda, .usdc, .usdz, .obj)")
    if "FINISHED" not in result:
        raise SystemExit(f"{path}: Blender's importer returned {result}")
    for ob in bpy.context.scene.objects:  # a rig drawn in its rest pose: the surface as the file stores it
        if ob.type == "ARMATURE":
            ob.data.pose_position = "REST"
    bpy.context.view_layer.update()


def _default(value):
    try:
        return [float(x) for x in value]
    except TypeError:
        return float(value)


def upstream(socket, depth: int = 0) -> list[dict]:
    """The chain of nodes feeding ``socket`` (depth first, first link of each input)."""
    chain = []
    for link in socket.links:
        node = link.from_node
        entry = {"node": node.type, "name": node.name, "output": link.from_socket.name, "inputs": {}}
        if node.type == "TEX_IMAGE" and node.image is not None:
            entry["image"] = Path(bpy.path.abspath(node.image.filepath)).name or node.image.name
            entry["colorspace"] = node.image.colorspace_settings.name
            entry["interpolation"] = node.interpolation
        if node.type == "NORMAL_MAP":
            entry["space"] = node.space
            entry["uv_map"] = node.uv_map
            entry["strength"] = float(node.inputs["Strength"].default_value)
        if node.type == "MIX":
            entry["blend_type"] = node.blend_type
        for inp in node.inputs:
            if not inp.enabled:
                continue
            if inp.is_linked and depth < 6:
                entry["inputs"][inp.identifier] = upstream(inp, depth + 1)
            elif hasattr(inp, "default_value"):
                entry["inputs"][inp.identifier] = _default(inp.default_value)
        chain.append(entry)
    return chain


def describe_material(mat) -> dict:
    out = {"name": mat.name, "principled": None}
    if not mat.use_nodes:
        return out
    nodes = mat.node_tree.nodes
    output = next((n for n in nodes if n.type == "OUTPUT_MATERIAL" and n.is_active_output), None)
    surface = upstream(output.inputs["Surface"]) if output else []
    out["surface"] = [s["node"] for s in surface]
    # node groups' linked inputs by the group's name: glTF's importer keeps what Blender's shading
    # has no socket for (the occlusion texture) in a "glTF Material Output" group
    out["groups"] = {
        n.node_tree.name: {i.name: upstream(i) for i in n.inputs if i.is_linked}
        for n in nodes
        if n.type == "GROUP" and n.node_tree is not None
    }
    principled = next((n for n in nodes if n.type == "BSDF_PRINCIPLED"), None)
    if principled is None:
        return out
    out["principled"] = {
        name: {"linked": principled.inputs[name].is_linked, "from": upstream(principled.inputs[name])}
        if principled.inputs[name].is_linked
        else {"linked": False, "value": _default(principled.inputs[name].default_value)}
        for name in PRINCIPLED_INPUTS
    }
    return out


def describe_world(world) -> dict:
    if world is None or not world.use_nodes:
        return {"nodes": []}
    nodes = []
    for n in world.node_tree.nodes:
        entry = {"node": n.type, "name": n.name}
        if n.type == "TEX_ENVIRONMENT" and n.image is not None:
            entry["image"] = Path(bpy.path.abspath(n.image.filepath)).name
            entry["projection"] = n.projection
        if n.type == "MAPPING":
            entry["rotation"] = [float(x) for x in n.inputs["Rotation"].default_value]
        nodes.append(entry)
    return {"nodes": nodes}


def mesh_corners(ob, uv_map: int = 0) -> dict[str, np.ndarray]:
    """Per face corner (loop) arrays of a mesh object, in world space; the UVs of its ``uv_map``-th
    UV map (the set a material reads: a glTF ``TEXCOORD_<n>`` arrives as the n-th map) and
    tangents Blender's own from it (MikkTSpace, what its normal-map node uses)."""
    me = ob.data
    n = len(me.loops)
    uv_name = me.uv_layers[uv_map].name if len(me.uv_layers) > uv_map else None
    vert = np.zeros(n, np.int64)
    me.loops.foreach_get("vertex_index", vert)
    co = np.zeros(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    m = np.array(ob.matrix_world, np.float64)
    pos = co.reshape(-1, 3)[vert] @ m[:3, :3].T + m[:3, 3]
    sizes = np.zeros(len(me.polygons), np.int64)
    me.polygons.foreach_get("loop_total", sizes)
    out = {"position": pos.astype(np.float32), "face_sizes": sizes}
    normals = np.zeros(n * 3, np.float32)
    me.corner_normals.foreach_get("vector", normals)
    rot = m[:3, :3]
    out["normal"] = (normals.reshape(-1, 3) @ np.linalg.inv(rot)).astype(np.float32)  # inverse transpose
    if uv_name is not None:
        uv = np.zeros(n * 2, np.float32)
        me.uv_layers[uv_name].data.foreach_get("uv", uv)
        out["uv"] = uv.reshape(-1, 2)
        me.calc_tangents(uvmap=uv_name)
        tan = np.zeros(n * 3, np.float32)
        sign = np.zeros(n, np.float32)
        me.loops.foreach_get("tangent", tan)
        me.loops.foreach_get("bitangent_sign", sign)
        out["tangent"] = (tan.reshape(-1, 3) @ rot.T).astype(np.float32)
        out["bitangent_sign"] = sign
    return out


def describe_light(ob) -> dict:
    """A light object as imported: its type, strength (``energy``), colour, angular diameter
    (a sun's ``angle``) and the unit direction it comes from in Blender's world (its local ``+z``:
    a Blender light shines along its ``-z``)."""
    d = ob.matrix_world.to_3x3() @ Vector((0.0, 0.0, 1.0))
    d.normalize()
    return {
        "name": ob.name,
        "type": ob.data.type,
        "energy": float(ob.data.energy),
        "color": [float(c) for c in ob.data.color],
        "angle": float(getattr(ob.data, "angle", 0.0)),
        "direction": [float(c) for c in d],
    }


def use_suns(suns: list[dict]) -> None:
    """Replace the scene's lights by ``suns`` (each ``direction`` it comes from in Blender's world,
    ``strength`` (irradiance), ``color`` and ``angle``, its angular diameter in radians): the lights
    the asset file means, whatever an importer made of them."""
    scene = bpy.context.scene
    for ob in [o for o in scene.objects if o.type == "LIGHT"]:
        bpy.data.objects.remove(ob, do_unlink=True)
    for k, sun in enumerate(suns):
        data = bpy.data.lights.new(f"JudgeSun{k}", type="SUN")
        data.energy = float(sun["strength"])
        data.color = [float(c) for c in sun["color"]]
        data.angle = float(sun["angle"])
        ob = bpy.data.objects.new(f"JudgeSun{k}", data)
        ob.matrix_world = Vector((0.0, 0.0, 1.0)).rotation_difference(Vector(sun["direction"])).to_matrix().to_4x4()
        scene.collection.objects.link(ob)


def inspect(out: Path, uv_map: int = 0) -> dict:
    scene = bpy.context.scene
    report = {"objects": [], "materials": [], "world": describe_world(scene.world)}
    arrays = {}
    # meshes an importer made to draw bones (glTF's armatures: an icosphere) are not the asset
    bone_shapes = {
        pb.custom_shape.name for ob in scene.objects if ob.type == "ARMATURE" for pb in ob.pose.bones if pb.custom_shape
    }
    for ob in scene.objects:
        entry = {
            "name": ob.name,
            "type": ob.type,
            "parent": ob.parent.name if ob.parent else None,
            "matrix_world": [list(r) for r in ob.matrix_world],
            "bone_shape": ob.name in bone_shapes,
        }
        if ob.type == "MESH":
            me = ob.data
            corners = [ob.matrix_world @ Vector(c) for c in ob.bound_box]
            entry.update(
                vertices=len(me.vertices),
                corners=len(me.loops),
                faces=len(me.polygons),
                uv_maps=[u.name for u in me.uv_layers],
                bbox_min=[min(c[i] for c in corners) for i in range(3)],
                bbox_max=[max(c[i] for c in corners) for i in range(3)],
                materials=[m.name for m in me.materials if m is not None],
                shape_keys=len(me.shape_keys.key_blocks) if me.shape_keys else 0,
                data=me.name,  # objects that draw one glTF mesh share it
            )
            if not arrays and ob.name not in bone_shapes:  # the first mesh (our assets have one)
                arrays = mesh_corners(ob, uv_map)
        if ob.type == "ARMATURE":
            entry["bones"] = len(ob.data.bones)
        report["objects"].append(entry)
    report["actions"] = len(bpy.data.actions)
    report["materials"] = [describe_material(m) for m in bpy.data.materials if m.users]
    report["lights"] = [describe_light(ob) for ob in scene.objects if ob.type == "LIGHT"]
    report["unit_scale_length"] = float(scene.unit_settings.scale_length)
    if arrays:
        np.savez(out / "mesh.npz", **arrays)
    return report


def use_environment(path: str, rotation_z: float = 0.0) -> None:
    """The world: an equirectangular environment texture (linear radiance, strength 1), looked up
    in directions rotated by ``rotation_z`` radians about Blender's +z."""
    world = bpy.context.scene.world
    nt = world.node_tree
    nt.nodes.clear()
    tex = nt.nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(path)
    tex.image.colorspace_settings.name = "Linear Rec.709"
    tex.projection = "EQUIRECTANGULAR"
    tex.interpolation = "Linear"
    coords = nt.nodes.new("ShaderNodeTexCoord")
    mapping = nt.nodes.new("ShaderNodeMapping")
    mapping.vector_type = "POINT"
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, float(rotation_z))
    nt.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = 1.0
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])


def render(job: dict, out: Path) -> dict:
    """Render ``job["cameras"]`` (camera-to-world 4x4 in Blender's world, OpenGL-style: looking
    along local -z, +y up) at ``width`` x ``width`` with the full field of view ``fov_deg``, with
    Cycles on the CPU: ``spp`` samples per pixel per seed in ``seeds``, a one-pixel box filter (each
    pixel the mean over its footprint), no denoising, no adaptive sampling, a transparent film
    (alpha = covered fraction) unless ``background``; ``principled_overrides`` sets Principled BSDF
    inputs to constants (``{"Specular IOR Level": 0}``: no specular lobe, the diffuse alone).
    ``transport``: ``direct_unshadowed`` (light
    arrives straight from the world and the object casts no shadow on itself: the transport our
    closed-form renderer models) or ``full`` (path tracing, ``max_bounces`` 8)."""
    scene = bpy.context.scene
    for name, value in job.get("principled_overrides", {}).items():
        for mat in bpy.data.materials:
            for node in mat.node_tree.nodes if mat.use_nodes else ():
                if node.type == "BSDF_PRINCIPLED":
                    for link in list(node.inputs[name].links):
                        mat.node_tree.links.remove(link)
                    node.inputs[name].default_value = value
    scene.render.engine = "CYCLES"
    scene.render.use_persistent_data = True
    cy = scene.cycles
    cy.device = "CPU"
    cy.use_denoising = False
    cy.use_adaptive_sampling = False
    cy.samples = int(job["spp"])
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 1.0
    cy.use_light_tree = True
    if job.get("transport", "direct_unshadowed") == "direct_unshadowed":
        cy.max_bounces = 0
        for ob in scene.objects:
            ob.visible_shadow = False
    else:
        cy.max_bounces = 8
        cy.diffuse_bounces = cy.glossy_bounces = 8
    if job.get("threads"):
        scene.render.threads_mode = "FIXED"
        scene.render.threads = int(job["threads"])
    scene.render.film_transparent = not job.get("background", False)
    for ob in scene.objects:
        ob.hide_render = ob.type == "MESH" and bool(job.get("hide_meshes", False))
    scene.render.resolution_x = scene.render.resolution_y = int(job["width"])
    scene.render.resolution_percentage = 100
    scene.render.use_compositing = False
    scene.render.use_sequencer = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGBA"
    settings.exr_codec = "ZIP"

    cam_data = bpy.data.cameras.new("JudgeCamera")
    cam_data.type = "PERSP"
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle = math.radians(float(job["fov_deg"]))
    cam = bpy.data.objects.new("JudgeCamera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    mesh_obs = [ob for ob in scene.objects if ob.type == "MESH"]
    pts = [ob.matrix_world @ Vector(c) for ob in mesh_obs for c in ob.bound_box]
    centre = sum(pts, Vector()) / max(len(pts), 1)
    w = int(job["width"])
    seeds = [int(s) for s in job.get("seeds", [0])]
    images = np.zeros((len(job["cameras"]), len(seeds), w, w, 4), np.float32)
    t0 = time.perf_counter()
    for i, c2w in enumerate(job["cameras"]):
        cam.matrix_world = Matrix(c2w)
        dist = (Vector([c2w[0][3], c2w[1][3], c2w[2][3]]) - centre).length
        cam_data.clip_start = max(dist * 1e-4, 1e-6)
        cam_data.clip_end = dist * 1e3 + 1.0
        for k, seed in enumerate(seeds):
            cy.seed = seed
            path = out / f"view{i:03d}_{k}.exr"
            scene.render.filepath = str(path)
            bpy.ops.render.render(write_still=True)
            img = bpy.data.images.load(str(path))
            px = np.zeros(w * w * 4, np.float32)
            img.pixels.foreach_get(px)
            bpy.data.images.remove(img)
            path.unlink()
            images[i, k] = px.reshape(w, w, 4)[::-1]  # Blender's rows start at the bottom
    seconds = time.perf_counter() - t0
    np.save(out / "render.npy", images)
    return {"views": len(job["cameras"]), "seeds": seeds, "spp": cy.samples, "seconds": seconds}


def main(argv: list[str]) -> int:
    # under `blender -b --python this.py -- job.json` the job follows "--"
    args = argv[argv.index("--") + 1 :] if "--" in argv else argv[1:]
    if len(args) != 1:
        raise SystemExit("usage: python blender_job.py JOB.json")
    job = json.loads(Path(args[0]).read_text())
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    reset_scene()
    if job.get("asset"):
        import_asset(Path(job["asset"]))
    report = {"blender": bpy.app.version_string, "asset": job.get("asset"), "import_seconds": time.perf_counter() - t0}
    render_job = job.get("render") or {}
    if render_job.get("environment"):
        use_environment(render_job["environment"], render_job.get("environment_rotation_z", 0.0))
    if job.get("asset") and job.get("inspect", True):
        report.update(inspect(out, int(job.get("uv_map", 0))))
    if "suns" in render_job:
        use_suns(render_job["suns"])
    if render_job:
        report["render"] = render(render_job, out)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
