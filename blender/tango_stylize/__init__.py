"""TANGO Stylize for Blender: select objects, type a prompt (or pick a material to recover from
images), and the workflow gives them PBR materials, in Blender.

"Stylise selected" exports the selected mesh objects (:mod:`.exchange`; with their modifiers
applied into a stylised copy beside each, or as they are), runs ``python -m stages.quick`` in the
project's environment (the Python named in the add-on's preferences) as a background job
(:mod:`.job`) with its progress in the status bar and a cancel button (or Esc), and when it is done
puts the new materials into the objects' own slots, reading a bake UV map by name: the object's own
render UV map where the workflow can keep it, else a new map the add-on unwraps (``TANGO``). The
vertices, UV maps, vertex groups, rig and animation of each object are untouched. The textures are
packed into the .blend or written beside it; the learned light can be added as a world (and its
suns as lights). A failure reaches the user as one line, the workflow's own.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import bpy

from . import exchange, job

#: the one stylisation running (the add-on runs one at a time)
_RUNNING: dict[str, Run] = {}
#: the project's choices (presets, materials), asked once per session
_CHOICES: dict = {}


def preferences(context):
    return context.preferences.addons[__package__].preferences


class TangoPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    python: bpy.props.StringProperty(
        name="Project Python",
        description="The Python of the tango-stylize environment (the project's .venv/bin/python)",
        subtype="FILE_PATH",
    )
    workdir: bpy.props.StringProperty(
        name="Work folder",
        description="Where runs keep their configs and results (empty: a 'tango' folder beside the .blend file)",
        subtype="DIR_PATH",
    )
    test_clip: bpy.props.BoolProperty(
        name="Test CLIP",
        description="The tiny random test CLIP instead of the real one (results marked TEST ONLY; for checks only)",
    )
    overlays: bpy.props.StringProperty(
        name="Config overlays",
        description="Config files laid over the written one, separated by ';' (e.g. smaller sizes)",
    )

    def draw(self, context):
        for name in ("python", "workdir", "overlays", "test_clip"):
            self.layout.prop(self, name)


def _choice_search(key: str):
    def search(self, context, edit_text):
        found = _choices(context)
        names = list(found.get(key, {}))
        return [n for n in names if edit_text.lower() in n.lower()] or names

    return search


def _choices(context) -> dict:
    if not _CHOICES:
        try:
            _CHOICES.update(job.choices(preferences(context).python))
        except RuntimeError:
            return {}
    return _CHOICES


class TangoSettings(bpy.types.PropertyGroup):
    prompt: bpy.props.StringProperty(name="Prompt", description="What the objects should look like, e.g. 'a vase made of wood'")
    guidance: bpy.props.EnumProperty(
        name="Guidance",
        items=[
            ("CLIP", "Prompt", "CLIP guides the material towards the prompt"),
            ("IMAGE", "Material", "No CLIP: recover a procedural material from its renders"),
        ],
    )
    material: bpy.props.StringProperty(name="Material", default="wood", search=_choice_search("materials"))
    preset: bpy.props.StringProperty(name="Preset", default="fast", search=_choice_search("presets"))
    layout: bpy.props.EnumProperty(
        name="Bake into",
        items=[
            ("AUTO", "Auto", "The object's render UV map where the workflow can keep it, else a new map"),
            ("OWN", "Own UV map", "The object's render UV map (stops where the workflow cannot keep it)"),
            ("NEW", "New UV map", "A new UV map, 'TANGO', unwrapped by Smart UV Project"),
        ],
    )
    apply_modifiers: bpy.props.BoolProperty(
        name="Apply modifiers", description="Stylise the objects as their modifiers make them (into a copy beside each)"
    )
    pack: bpy.props.BoolProperty(name="Pack textures", default=True, description="Pack the textures into the .blend")
    add_light: bpy.props.BoolProperty(name="Add the learned light", description="As the scene's world (and its suns)")
    plan: bpy.props.StringProperty(name="Plan", description="What the last estimate said")


@dataclass
class Run:
    """A stylisation under way: the ``request``, the objects it paints (``targets``), what was
    exported of them and the background ``job``."""

    request: job.Request
    targets: list[str]
    exported: exchange.Exported
    job: job.Job | None = None
    #: the stylised copies made for this run (modifiers applied): removed again if it fails
    copies: list[str] = field(default_factory=list)

    @property
    def prefix(self) -> str:
        """The prefix of the names the run's exported materials and nodes carry."""
        return f"tango_{self.request.name.rsplit('-', 1)[-1]}_"

    def discard(self) -> None:
        """Remove the copies a failed or cancelled run made."""
        for name in self.copies:
            ob = bpy.data.objects.get(name)
            if ob is not None:
                mesh = ob.data
                bpy.data.objects.remove(ob)
                if mesh.users == 0:
                    bpy.data.meshes.remove(mesh)


def _workdir(context) -> Path:
    given = preferences(context).workdir
    if given:
        return Path(bpy.path.abspath(given))
    if bpy.data.filepath:
        return Path(bpy.path.abspath("//tango"))
    return Path(tempfile.gettempdir()) / "tango-blender"


def _targets(context, apply_modifiers: bool) -> list:
    """The selected mesh objects, or with ``apply_modifiers`` a stylised copy of each holding its
    evaluated mesh (its armature modifiers off while it is made, so in rest pose), linked beside it."""
    objects = [ob for ob in context.selected_objects if ob.type == "MESH"]
    if not objects:
        raise RuntimeError("select one or more mesh objects")
    if not apply_modifiers:
        return objects
    copies = []
    for ob in objects:
        armatures = [m for m in ob.modifiers if m.type == "ARMATURE" and m.show_viewport]
        for m in armatures:
            m.show_viewport = False
        depsgraph = context.evaluated_depsgraph_get()
        mesh = bpy.data.meshes.new_from_object(ob.evaluated_get(depsgraph), preserve_all_data_layers=True, depsgraph=depsgraph)
        for m in armatures:
            m.show_viewport = True
        copy = ob.copy()
        copy.data, copy.name = mesh, f"{ob.name} stylised"
        for m in [m for m in copy.modifiers if m.type != "ARMATURE"]:
            copy.modifiers.remove(m)
        for collection in ob.users_collection:
            collection.objects.link(copy)
        copies.append(copy)
    return copies


def _request(context, settings, name: str, uv: str) -> job.Request:
    """The run for the scene's ``settings``: the exported objects at ``<work folder>/blender/<name>/input.glb``."""
    prefs = preferences(context)
    if not prefs.python or not Path(bpy.path.abspath(prefs.python)).is_file():
        raise RuntimeError("set the project's Python in the add-on's preferences (the project's .venv/bin/python)")
    if settings.guidance == "CLIP" and not settings.prompt.strip():
        raise RuntimeError("type a prompt")
    material = settings.material if settings.guidance == "IMAGE" else ""
    prompt = settings.prompt.strip() or f"an object made of {material}"
    overlays = tuple(bpy.path.abspath(o.strip()) for o in prefs.overlays.split(";") if o.strip())
    python, workdir = bpy.path.abspath(prefs.python), _workdir(context)
    mesh = workdir / "blender" / name / "input.glb"
    return job.Request(python, workdir, mesh, prompt, settings.preset, name, material, prefs.test_clip, uv, overlays)


def _name(targets, settings) -> str:
    """The run's experiment name: the file's and the objects' names, and a digest of the settings
    that make another result (prompt, material, guidance, preset, modifiers)."""
    material = settings.material if settings.guidance == "IMAGE" else ""
    said = (settings.prompt.strip(), material, settings.preset, str(settings.apply_modifiers), settings.layout)
    return job.run_name(Path(bpy.data.filepath).stem or "untitled", *(ob.name for ob in targets), settings=said)


def prepare(context, settings) -> Run:
    """Everything before the run: the objects to paint, their bake UV maps (:func:`_bake_maps`),
    the exported GLB and the request. A stylised copy made here is removed again if this fails."""
    if context.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    targets = _targets(context, settings.apply_modifiers)
    copies = [ob.name for ob in targets] if settings.apply_modifiers else []
    run = Run(_request(context, settings, _name(targets, settings), "keep"), [ob.name for ob in targets], None, copies=copies)
    try:
        run.exported = _bake_maps(targets, settings.layout, run)
    except Exception:
        run.discard()
        raise
    return run


def _bake_maps(targets, layout: str, run: Run) -> exchange.Exported:
    """Each object's bake UV map (module docstring): its render map, checked by the workflow
    (``--uv keep``, planned only); a new one where it has none, where ``layout`` asks for one, or
    (``AUTO``) where the workflow refuses to keep the objects' own; the objects exported with them."""
    request = run.request
    own = {ob.name: exchange.own_uv_map(ob) for ob in targets}
    missing = [name for name, uv_map in own.items() if uv_map is None]
    if layout == "OWN" and missing:
        raise RuntimeError(f"{', '.join(missing)} has no UV map: choose Auto or New UV map")
    maps = {ob.name: exchange.make_bake_uv_map(ob) if layout == "NEW" or own[ob.name] is None else own[ob.name] for ob in targets}
    exported = exchange.write_glb(targets, request.mesh, maps, run.prefix)
    if layout == "NEW":
        return exported
    proc = job.plan(request)
    said = proc.stdout + proc.stderr
    if proc.returncode == 0:
        return exported
    if layout == "OWN" or job.REFUSED_LAYOUT not in said:  # not the layout: the run would fail the same way
        raise RuntimeError(job.last_line(said))
    maps = {ob.name: exchange.make_bake_uv_map(ob) for ob in targets}
    return exchange.write_glb(targets, request.mesh, maps, run.prefix)


def finish(context, run: Run, settings) -> list[str]:
    """The finished run's materials into the objects' slots (module docstring); returns what was
    done, one line each."""
    result = job.result_of(run.request)
    count = 1 + max((k for slots in run.exported.slots.values() for k in slots if k is not None), default=-1)
    materials, lights = exchange.import_materials(result.glb, count, run.prefix)
    provenance = {
        "prompt": run.request.prompt,
        "preset": run.request.preset,
        "guidance": f"image-guided ({run.request.material})" if run.request.material else "CLIP",
        "test_only": run.request.test_clip,
        "results": str(result.export),
        "bake_uv": result.uv.get("layout", ""),
    }
    done = []
    for name in run.targets:
        ob = bpy.data.objects[name]
        uv_map = run.exported.uv_maps[name]
        for s, k in enumerate(run.exported.slots[name]):
            if k is None:
                continue
            mat = materials[k]
            old = ob.material_slots[s].material if s < len(ob.material_slots) else None
            base = (old.name if old else ob.name).split(" (TANGO")[0]  # a material stylised before: its own name
            mat.name = f"{base} (TANGO{' TEST ONLY' if run.request.test_clip else ''})"
            exchange.read_uv_map(mat, uv_map)
            mat["tango_stylize"] = json.dumps(provenance)
            if s < len(ob.material_slots):
                ob.material_slots[s].material = mat
            else:
                ob.data.materials.append(mat)
        ob["tango_stylize"] = json.dumps({**provenance, "uv_map": uv_map})
        done.append(f"{name}: {len([k for k in run.exported.slots[name] if k is not None])} material(s) on UV map {uv_map}")
    beside = Path(bpy.path.abspath("//")) if bpy.data.filepath else run.request.workdir  # the .blend's folder, once saved
    folder = beside / "textures" / run.request.name
    exchange.keep_images([m for m in materials if m is not None], settings.pack, folder)
    _lights(context, settings, run, result, lights)
    return done


def _lights(context, settings, run: Run, result, lights) -> None:
    if settings.add_light:
        context.scene.world = exchange.add_world(result.export / "light.hdr", f"TANGO light ({run.request.name})")
        for ob in lights:
            context.scene.collection.objects.link(ob)
        return
    for ob in lights:
        data = ob.data
        bpy.data.objects.remove(ob)
        if data.users == 0:
            bpy.data.lights.remove(data)


class TANGO_OT_stylise_selected(bpy.types.Operator):
    """Give the selected objects PBR materials from the prompt (a background job; Esc cancels)"""

    bl_idname = "tango.stylise_selected"
    bl_label = "Stylise selected"
    bl_options = {"REGISTER"}

    _timer = None

    def execute(self, context):  # in the background (no event loop): run to the end here
        started = self._start(context)
        if started != {"RUNNING_MODAL"}:
            return started
        run = _RUNNING["run"]
        code = run.job.wait()
        return self._end(context, code)

    def invoke(self, context, event):
        started = self._start(context)
        if started != {"RUNNING_MODAL"}:
            return started
        wm = context.window_manager
        self._timer = wm.event_timer_add(1.0, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _start(self, context):
        if "run" in _RUNNING:
            self.report({"ERROR"}, "a stylisation is already running: wait for it or cancel it")
            return {"CANCELLED"}
        settings = context.scene.tango_stylize
        try:
            run = prepare(context, settings)
        except (RuntimeError, OSError) as exc:
            self.report({"ERROR"}, str(exc).splitlines()[0])
            return {"CANCELLED"}
        try:
            env = job.environment(run.request.python)
            log = run.request.mesh.parent / "run.log"
            run.job = job.Job(run.request.command(), run.request.workdir, log, env).start()
        except OSError as exc:
            run.discard()
            self.report({"ERROR"}, str(exc).splitlines()[0])
            return {"CANCELLED"}
        _RUNNING["run"] = run
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        run = _RUNNING.get("run")
        if run is None:
            return self._end(context, None)
        if event.type == "ESC" and event.value == "PRESS":
            run.job.cancel()
            run.discard()
            return self._end(context, None)
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        code = run.job.poll()
        if code is None:
            share, line = run.job.progress()
            context.window_manager.progress_update(int(100 * share))
            context.workspace.status_text_set(f"TANGO {int(100 * share)}%: {line}")
            return {"RUNNING_MODAL"}
        return self._end(context, code)

    def _end(self, context, code):
        run = _RUNNING.pop("run", None)
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            context.window_manager.progress_end()
            context.workspace.status_text_set(None)
        if run is None or code is None:
            self.report({"WARNING"}, "stylisation cancelled")
            return {"CANCELLED"}
        if code != 0:
            run.discard()
            self.report({"ERROR"}, f"the workflow stopped: {job.last_line(run.job.output())}")
            return {"CANCELLED"}
        try:
            done = finish(context, run, context.scene.tango_stylize)
        except (RuntimeError, OSError, KeyError) as exc:
            run.discard()
            self.report({"ERROR"}, str(exc).splitlines()[0])
            return {"CANCELLED"}
        self.report({"INFO"}, "; ".join(done))
        return {"FINISHED"}


class TANGO_OT_cancel(bpy.types.Operator):
    """Stop the running stylisation"""

    bl_idname = "tango.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        run = _RUNNING.get("run")
        if run is not None and run.job is not None:
            run.job.cancel()
            run.discard()
            _RUNNING.pop("run", None)
        return {"FINISHED"}


class TANGO_OT_estimate(bpy.types.Operator):
    """The workflow's plan for the selected objects: the UV layout, the steps and the time it expects"""

    bl_idname = "tango.estimate"
    bl_label = "Estimate"

    def execute(self, context):
        settings = context.scene.tango_stylize
        try:
            targets = [ob for ob in context.selected_objects if ob.type == "MESH"]
            if not targets:
                raise RuntimeError("select one or more mesh objects")
            request = _request(context, settings, _name(targets, settings), "auto")
            exchange.write_glb(targets, request.mesh, {ob.name: exchange.own_uv_map(ob) for ob in targets}, "tango_plan_")
            proc = job.plan(request)
        except (RuntimeError, OSError) as exc:
            self.report({"ERROR"}, str(exc).splitlines()[0])
            return {"CANCELLED"}
        if proc.returncode != 0:
            self.report({"ERROR"}, job.last_line(proc.stdout + proc.stderr))
            return {"CANCELLED"}
        keep = ("UV layout:", "  ", "Estimated wall time")
        settings.plan = "\n".join(ln for ln in proc.stdout.splitlines() if ln.startswith(keep))
        return {"FINISHED"}


class TANGO_PT_panel(bpy.types.Panel):
    bl_label = "TANGO Stylize"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "TANGO"

    def draw(self, context):
        s, col = context.scene.tango_stylize, self.layout.column()
        col.prop(s, "guidance", expand=True)
        col.prop(s, "prompt" if s.guidance == "CLIP" else "material")
        for name in ("preset", "layout", "apply_modifiers", "pack", "add_light"):
            col.prop(s, name)
        if "run" in _RUNNING:
            share, line = _RUNNING["run"].job.progress()
            col.label(text=f"{int(100 * share)}%: {line[:60]}")
            col.operator("tango.cancel", icon="CANCEL")
            return
        row = col.row()
        row.operator("tango.estimate")
        row.operator("tango.stylise_selected")
        for line in s.plan.splitlines():
            for k in range(0, len(line), 70):
                col.label(text=line[k : k + 70])


CLASSES = (
    TangoPreferences,
    TangoSettings,
    TANGO_OT_stylise_selected,
    TANGO_OT_cancel,
    TANGO_OT_estimate,
    TANGO_PT_panel,
)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.tango_stylize = bpy.props.PointerProperty(type=TangoSettings)


def unregister():
    run = _RUNNING.pop("run", None)
    if run is not None and run.job is not None:
        run.job.cancel()
    del bpy.types.Scene.tango_stylize
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
