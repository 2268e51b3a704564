"""The Blender round trip's work: the cell's exported files imported into Blender, checked and
rendered with Cycles from evaluation views (:mod:`.blender`), against our render of the trained field
at the same hits; the lobes alone of the format whose row says ``lobe_split`` (the GLB's), which
split the gap between the BRDF models; and the comparison sheet. What the round trip knows of each
imported file (its light, its occlusion, its faces' order) is its export format's row,
:data:`stages.config.layout.EXPORT_FORMATS`; ``fmt`` below is the file's suffix
(``roundtrip.formats``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..config.layout import EXPORT_FILES, export_format_of
from ..config.sections import RoundtripSettings
from ..core.errors import StageInputError
from ..core.provenance import Timer
from ..geometry.raycache import RayCache
from ..imaging.views import ViewStore
from ..render.color import srgb_encode
from .blender import Y_UP_TO_Z_UP, BlenderUnavailable, check_import, compare_renders, render_job, run_job

log = logging.getLogger(__name__)


#: Cycles passes of the file whose format splits its lobes (the GLB): the material as imported,
#: its diffuse lobe alone (no specular reflection) and its specular lobe alone (black base colour)
PASSES = {
    "full": {},
    "diffuse": {"Specular IOR Level": 0.0},
    "specular": {"Base Color": (0.0, 0.0, 0.0, 1.0)},
}


@dataclass
class Lobes:
    """Our render at the hits of one view, linear ``(N, 3)`` each."""

    diffuse: np.ndarray
    specular: np.ndarray

    @property
    def rgb(self) -> np.ndarray:
        return self.diffuse + self.specular


def field_renders(field, cache: RayCache, views: list[int], device: str, shadows: bool = False) -> list[Lobes]:
    """Our render of the trained field at every hit of the given views, with the field's shadows
    when ``shadows`` (for Cycles' ``full`` transport; its ``direct_unshadowed`` casts none, so the
    comparison of like with like is unshadowed)."""
    store = ViewStore(cache, torch.device(device), field.normals, shadows=shadows and field.shadows)
    out = []
    for i in views:
        v = store[i]
        with torch.no_grad():
            sh = v.shade(field).shading
        out.append(Lobes(sh.diffuse.cpu().numpy().astype(np.float64), sh.specular.cpu().numpy().astype(np.float64)))
    return out


def comparison_sheet(ours: np.ndarray, theirs: dict[str, np.ndarray]) -> np.ndarray:
    """One row: ours | each format's Cycles render | 4 x |difference| of the first; sRGB, white
    where no pixel counted."""

    def show(x):
        return np.where(np.isnan(x), 1.0, np.clip(srgb_encode(np.clip(np.nan_to_num(x), 0, None)), 0, 1))

    first = next(iter(theirs.values()))
    diff = np.where(np.isnan(ours), np.nan, np.abs(show(first) - show(ours)) * 4.0)
    return np.concatenate([show(ours), *(show(t) for t in theirs.values()), np.where(np.isnan(diff), 1.0, diff)], axis=1)


@dataclass
class RoundtripScene:
    """What every Blender job of a cell renders and is compared with: the evaluation ``cache``, the
    chosen ``views`` and their ``hits``, Blender's cameras for them, our render at those hits (``reference``), the
    exported geometry with its metres per unit, the export stage's metadata, the settings and the
    folders of the exported files and of the jobs' work."""

    cache: RayCache
    views: list[int]
    hits: list
    cameras: np.ndarray
    reference: list[Lobes]
    geom: object
    meters_per_unit: float
    export_meta: dict
    settings: RoundtripSettings
    export_dir: Path
    work: Path
    #: the baked frame's tangents per corner where ``geom`` holds none per vertex (a kept layout)
    tangents: np.ndarray | None = None
    #: the input file where the asset is its own topology (a kept layout), for :func:`own_format_check`
    source: Path | None = None
    #: whether the GLB is the input's own document (faces in the input's order)
    document: bool = False


def file_suns(export_meta: dict) -> list[dict]:
    """The learned suns the exported files carry (the export's ``distant_lights``, in the files'
    frame) as Blender suns: the direction each comes from in Blender's world, its strength (the
    irradiance's largest channel), colour and angular diameter (radians)."""
    out = []
    for record in export_meta.get("stats", {}).get("distant_lights", []):
        e = np.asarray(record["irradiance"], np.float64)
        peak = float(e.max()) if e.max() > 0 else 0.0
        d = Y_UP_TO_Z_UP @ np.asarray(record["direction"], np.float64)
        out.append(
            {
                "direction": (d / np.linalg.norm(d)).tolist(),
                "strength": peak,
                "color": (e / peak).tolist() if peak > 0 else [1.0, 1.0, 1.0],
                "angle": 2.0 * np.radians(float(record["radius_deg"])),
            }
        )
    return out


def check_suns(imported: list[dict], meant: list[dict]) -> tuple[dict, list[str]]:
    """The suns Blender's importer made (``imported``: the job's ``lights``) against the ones the
    file means (:func:`file_suns`), each meant sun paired with the imported one nearest its
    direction (a kept document's own suns may be there too): the problems (fewer suns than the
    file's, a direction more than 0.1 degrees or a colour more than 1e-3 away) and, per sun, what
    the importer read of the strength and the angular diameter as a share of the file's (an
    importer's own convention, recorded; the render uses the file's)."""
    suns = [light for light in imported if light["type"] == "SUN"]
    problems = [] if len(suns) >= len(meant) else [f"{len(suns)} sun(s) imported where the file has {len(meant)}"]
    figures = []
    for want in meant if suns else ():
        apart_all = [float(np.degrees(np.arccos(np.clip(np.dot(s["direction"], want["direction"]), -1.0, 1.0)))) for s in suns]
        k = int(np.argmin(apart_all))
        got, apart = suns[k], apart_all[k]
        colour = float(np.abs(np.asarray(got["color"]) - np.asarray(want["color"])).max())
        if apart > 0.1:
            problems.append(f"the sun {got['name']} comes from {apart:.2f} degrees away from the file's direction")
        if colour > 1e-3:
            problems.append(f"the sun {got['name']}'s colour is {colour:.3g} away from the file's")
        figures.append(
            {
                "direction_error_deg": apart,
                "strength_read": got["energy"] / want["strength"] if want["strength"] > 0 else None,
                "angle_read": got["angle"] / want["angle"] if want["angle"] > 0 else None,
            }
        )
    return {"suns": figures}, problems


def blender_pass(scene: RoundtripScene, fmt: str, name: str, overrides: dict, timer: Timer):
    """One Blender job: import the exported file of suffix ``fmt`` and render it (the ``name``
    pass: the material as imported, or with its ``overrides``), lit by ``light.hdr`` as the world
    unless the file carries its light (the USD's DomeLight) and by the suns the file carries, as it
    means them (:func:`file_suns`); the inspection and the renders."""
    s = scene.settings
    env = None if export_format_of(fmt).carries_light else (scene.export_dir / "light.hdr").resolve()
    render = render_job(
        scene.cameras, scene.cache.fov_deg, scene.cache.width, spp=s.spp, seed=s.seed, transport=s.transport, environment=env
    )
    suns = file_suns(scene.export_meta)
    job = {
        "asset": str((scene.export_dir / EXPORT_FILES[fmt]).resolve()),
        "inspect": name == "full",
        "uv_map": baked_uv_map(scene, fmt),
        "render": {**render, "principled_overrides": overrides, **({"suns": suns} if suns else {})},
    }
    with timer(f"blender_{fmt}_{name}"):
        try:
            return run_job(job, scene.work / f"{fmt}_{name}", s.timeout_s)
        except BlenderUnavailable as exc:
            raise StageInputError(Path("blender"), str(exc), "Or set roundtrip.enabled: false.") from None


def added_set(scene: RoundtripScene) -> dict:
    """The export's record of the second UV set it gave a glTF input's document (empty: none)."""
    return (scene.export_meta.get("stats", {}) or {}).get("second_uv_set") or {}


def baked_uv_map(scene: RoundtripScene, fmt: str) -> int:
    """Which UV map of the file of suffix ``fmt`` holds the bake: the second set the export added
    to a glTF input's own document (``TEXCOORD_<n>``, Blender's n-th map), else the first."""
    added = added_set(scene)
    if not scene.document or fmt != "glb" or not added:
        return 0
    return int(str(added["attribute"]).rsplit("_", 1)[1])


def graded_import(scene: RoundtripScene, fmt: str, res) -> tuple[dict, object]:
    """A format's imported asset checked and its render graded against ours: its result record
    and the comparison (images per view). The occlusion map is checked where Blender's importer
    keeps it (not the USD's), the faces in slot order where the format writes them so (our GLB:
    one primitive per material slot; a glTF input's own document keeps the input's order)."""
    exported, spec = scene.export_meta.get("stats", {}), export_format_of(fmt)
    occlusion = bool(exported.get("occlusion", False)) and spec.blender_keeps_occlusion
    geom, tangents = scene.geom, scene.tangents
    if spec.faces_by_slot and not scene.document:
        order = geom.glb_face_order()
        geom = geom.reordered(order)
        tangents = None if tangents is None else tangents.reshape(-1, 3, 4)[order].reshape(-1, 4)
    checks = check_import(res, geom, scene.meters_per_unit, exported.get("brdf", "tango"), occlusion, tangents)
    world = [n["node"] for n in res.report.get("world", {}).get("nodes", [])]
    if "TEX_ENVIRONMENT" not in world:
        checks["problems"].append("the world has no environment texture (the learned light did not arrive)")
    suns, problems = check_suns(res.report.get("lights", []), file_suns(scene.export_meta))
    checks.update(suns)
    checks["problems"] += problems
    for problem in checks["problems"]:
        log.warning("Blender import of %s: %s", EXPORT_FILES[fmt], problem)
    cmp = compare_renders(scene.hits, res.renders, [r.rgb for r in scene.reference])
    log.info(
        "%s in Blender %s: %.2f dB against our render over %d object pixels (Cycles noise %.1f dB), %d problem(s)",
        EXPORT_FILES[fmt],
        res.report.get("blender"),
        cmp.psnr_db,
        cmp.pixels,
        cmp.noise_psnr_db,
        len(checks["problems"]),
    )
    result = {
        "psnr_db": cmp.psnr_db,
        "noise_psnr_db": cmp.noise_psnr_db,
        "per_view_psnr_db": cmp.per_view_psnr_db,
        "pixels": cmp.pixels,
        "import": checks,
        "blender": res.report.get("blender"),
        "blender_seconds": res.seconds,
        "render_seconds": res.report["render"]["seconds"],
    }
    return result, cmp


def own_format_check(scene: RoundtripScene, timer: Timer) -> dict:
    """The asset in the input's own format (the GLB of a glTF input, ``model.obj`` of an OBJ's)
    imported into Blender beside the input itself: the same objects (mesh objects among them),
    armature bones, actions and shape keys, the same face and corner counts, as many vertices (up to
    a second UV set's appended seam vertices more: Blender merges those that differ from their
    source only in their UVs, which it keeps per corner), and the same UVs per corner (the input's
    own first set, where it had one).
    Returns the counts of both, the largest UV difference and ``problems``."""
    own = scene.export_dir / (EXPORT_FILES["glb"] if scene.document else "model.obj")
    got = {}
    for key, path in (("input", scene.source), ("output", own)):
        with timer(f"blender_{key}_import"):
            try:
                job = {"asset": str(Path(path).resolve()), "inspect": True}
                res = run_job(job, scene.work / f"own_{key}", scene.settings.timeout_s)
            except BlenderUnavailable as exc:
                raise StageInputError(Path("blender"), str(exc), "Or set roundtrip.enabled: false.") from None
        objects = [o for o in res.report.get("objects", []) if not o.get("bone_shape")]
        meshes = [o for o in objects if o["type"] == "MESH"]
        data = list({m.get("data", k): m for k, m in enumerate(meshes)}.values())  # a mesh drawn twice counts once
        counts = {k: sum(int(m[k]) for m in data) for k in ("vertices", "faces", "corners", "shape_keys")}
        bones = sum(int(o.get("bones", 0)) for o in objects)
        rig = {"objects": len(objects), "bones": bones, "actions": res.report.get("actions", 0)}
        got[key] = {"file": Path(path).name, "mesh_objects": len(meshes), **counts, **rig, "uv": res.corners.get("uv")}
    a, b = got["input"], got["output"]
    # the seam vertices of a second UV set come after the input's own (stats.second_uv_set)
    appended = int(added_set(scene).get("appended_vertices", 0))
    b["appended_vertices"] = appended
    # Blender keeps UVs per corner and may merge vertices that differ only there: an appended one
    # arrives as its own vertex or as its source again
    problems = [
        f"{k}: {b[k]:,} in Blender's import of {b['file']}, {a[k]:,} in its import of the input {a['file']}"
        + (f" (and {appended:,} appended)" if k == "vertices" and appended else "")
        for k in ("mesh_objects", "objects", "bones", "actions", "shape_keys", "vertices", "faces", "corners")
        if not a[k] <= b[k] <= a[k] + (appended if k == "vertices" else 0)
    ]
    uv_error = None
    if a["uv"] is not None and b["uv"] is not None and len(a["uv"]) == len(b["uv"]):
        # primitives without UVs (Blender fills them with 0, 1) that the export gave the bake's set as their first
        filled = int(added_set(scene).get("primitives_given_lower_sets", 0))
        had = ~(a["uv"] == (0.0, 1.0)).all(axis=1) if filled else np.ones(len(a["uv"]), bool)
        uv_error = float(np.abs(a["uv"][had] - b["uv"][had]).max(initial=0.0))
        if uv_error > 1e-6:
            problems.append(f"UVs differ by up to {uv_error:.2g} from the input's in Blender")
    elif a["uv"] is not None:
        problems.append(f"the UVs of {b['file']} did not arrive as the input's")
    for problem in problems:
        log.warning("own format in Blender: %s", problem)
    strip = {k: {kk: vv for kk, vv in v.items() if kk != "uv"} for k, v in got.items()}
    return {**strip, "uv_error": uv_error, "problems": problems}


def lobe_split(scene: RoundtripScene, lobes: dict, fmt: str) -> dict:
    """Each lobe alone of the file of suffix ``fmt`` (the format that splits its lobes) against
    ours, Blender's two lobes simply added (TANGO's sum, no layering), and the specular lobe's
    share of our radiance."""
    hits, reference = scene.hits, scene.reference
    split = {
        "diffuse_psnr_db": compare_renders(hits, lobes["diffuse"], [r.diffuse for r in reference]).psnr_db,
        "specular_psnr_db": compare_renders(hits, lobes["specular"], [r.specular for r in reference]).psnr_db,
    }
    summed = lobes["diffuse"].copy()
    summed[..., :3] += lobes["specular"][..., :3]
    split["lobes_summed_psnr_db"] = compare_renders(hits, summed, [r.rgb for r in reference]).psnr_db
    ours_spec = float(np.concatenate([r.specular for r in reference]).mean())
    ours_all = float(np.concatenate([r.rgb for r in reference]).mean())
    split["specular_share"] = ours_spec / max(ours_all, 1e-12)
    log.info(
        "%s lobes: diffuse alone %.2f dB, specular alone %.2f dB, Blender's lobes added %.2f dB "
        "(specular is %.0f%% of our radiance)",
        EXPORT_FILES[fmt],
        split["diffuse_psnr_db"],
        split["specular_psnr_db"],
        split["lobes_summed_psnr_db"],
        100 * split["specular_share"],
    )
    return split
