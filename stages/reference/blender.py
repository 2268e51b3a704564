"""Blender (``bpy``) as the judge of our assets: find it, run a job in it, map our frames to its.

Blender is run as a separate process (:mod:`stages.reference.blender_job` is the script it runs),
found in this order: ``TANGO_BLENDER`` (a Python that imports ``bpy``, or a ``blender``
executable), the project's ``.venv-blender`` (``bash scripts/setup.sh`` makes it: ``bpy`` 5.0
pins ``numpy < 2``, so it cannot share the main environment), the current interpreter when it
imports ``bpy``, and ``blender`` on the PATH.

Frames. Our assets are Y-up (glTF always; our USD declares ``upAxis = "Y"``); Blender's importers
turn them Z-up by ``(x, y, z) -> (x, -z, y)`` (:data:`Y_UP_TO_Z_UP`) and into metres (glTF is in
metres; Blender's USD importer applies ``metersPerUnit``). Blender's camera looks along its local
-z with +y up, like ours, so a camera-to-world matrix maps by the same rotation. Its
equirectangular world lookup and ours agree column for column once directions are mapped
(checked in ``tests/reference/test_blender_assets.py`` by rendering the world straight through
our cameras).
"""

from __future__ import annotations

import importlib.util
import logging
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..core.provenance import write_json_atomic
from ..core.safefiles import DATA_LIMIT, open_read, read_json
from ..imaging.quality import psnr
from ..imaging.targets import FULL_COVERAGE
from ..render import brdf as brdfs
from ..render.brdf import Brdf
from ..render.color import srgb_encode

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
JOB_SCRIPT = Path(__file__).with_name("blender_job.py")
#: our Y-up frame (glTF, USD with upAxis Y) to Blender's Z-up world, applied to column vectors
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: what to do when Blender is missing
INSTALL_HINT = (
    "install it with 'bash scripts/setup.sh test,reference,blender' (makes .venv-blender with bpy 5.0), "
    "or set TANGO_BLENDER to a Python that imports bpy or to a blender executable"
)


class BlenderUnavailable(RuntimeError):
    """No Blender could be found; the message says how to install one."""


def find_blender() -> list[str]:
    """The command that runs a Python script in Blender: ``[python]`` (a Python with ``bpy``)
    or ``[blender, -b, --factory-startup, --python-exit-code, 1, --python]``."""
    given = os.environ.get("TANGO_BLENDER")
    venv = REPO_ROOT / ".venv-blender" / "bin" / "python"
    if given:
        exe = shutil.which(given) or (given if Path(given).is_file() else None)
        if exe is None:
            raise BlenderUnavailable(f"TANGO_BLENDER={given!r} does not exist; {INSTALL_HINT}")
    elif venv.is_file():
        exe = str(venv)
    elif importlib.util.find_spec("bpy") is not None:
        exe = sys.executable
    else:
        exe = shutil.which("blender")
    if exe is None:
        raise BlenderUnavailable(f"Blender was not found; {INSTALL_HINT}")
    if Path(exe).name.startswith("blender"):
        return [exe, "-b", "--factory-startup", "--python-exit-code", "1", "--python"]
    return [exe]


def blender_version() -> str | None:
    """Blender's version string, or None when Blender is missing."""
    try:
        cmd = find_blender()
    except BlenderUnavailable:
        return None
    if len(cmd) > 1:
        out = subprocess.run([cmd[0], "--version"], capture_output=True, text=True, timeout=120)
        return out.stdout.splitlines()[0].strip() if out.returncode == 0 and out.stdout else None
    out = subprocess.run([*cmd, "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True, text=True, timeout=300)
    lines = [s for s in out.stdout.splitlines() if s.strip()]
    return lines[-1].strip() if out.returncode == 0 and lines else None


@dataclass
class JobResult:
    """What a Blender job answered: the report (JSON), the mesh's per-corner arrays (or {}), the
    renders ``(V, S, W, W, 4)`` linear RGBA per camera and seed (or None), and its wall time."""

    report: dict
    corners: dict
    renders: np.ndarray | None
    seconds: float


def run_job(job: dict, workdir: Path, timeout_s: float = 1800.0) -> JobResult:
    """Run one job (see :mod:`stages.reference.blender_job`) in Blender, in ``workdir``."""
    cmd = find_blender()
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    job = {**job, "out": str(workdir)}
    job_file = workdir / "job.json"
    write_json_atomic(job_file, job)
    args = [*cmd, str(JOB_SCRIPT)] + (["--", str(job_file)] if len(cmd) > 1 else [str(job_file)])
    t0 = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, cwd=workdir)
    seconds = time.perf_counter() - t0
    for line in proc.stdout.splitlines() + proc.stderr.splitlines():
        if line.strip():
            log.debug("blender: %s", line)
    if proc.returncode != 0 or not (workdir / "report.json").is_file():
        tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-15:])
        raise RuntimeError(f"Blender job on {job['asset']} failed (exit {proc.returncode}):\n{tail}")
    report = read_json(workdir / "report.json", "Blender wrote no valid report: run the judge again.")
    corners, renders = {}, None
    if (workdir / "mesh.npz").is_file():
        with open_read(workdir / "mesh.npz", DATA_LIMIT) as fh, np.load(fh) as z:
            corners = {k: z[k] for k in z.files}
    if (workdir / "render.npy").is_file():
        with open_read(workdir / "render.npy", DATA_LIMIT) as fh:
            renders = np.load(fh)
    return JobResult(report, corners, renders, seconds)


def export_to_blender(points: np.ndarray, meters_per_unit: float) -> np.ndarray:
    """Points ``(..., 3)`` in our export space (Y-up, the file's units) to Blender's world."""
    return (np.asarray(points, np.float64) * meters_per_unit) @ Y_UP_TO_Z_UP.T


def blender_cameras(c2w: np.ndarray, transform, meters_per_unit: float, own_frame: bool = False) -> np.ndarray:
    """Our camera-to-world matrices ``(V, 4, 4)`` (normalised frame) as Blender camera matrices
    for an asset exported with ``transform`` (a :class:`~stages.geometry.normalization.Similarity`
    back to the input's units, or None when exported normalised) and ``meters_per_unit``; with
    ``own_frame`` the asset's positions are the input's own (``x_original``, a kept layout's
    topology) rather than the export space ``R x_original``."""
    c2w = np.asarray(c2w, np.float64)
    eye = c2w[:, :3, 3]
    rot = c2w[:, :3, :3]
    if transform is not None and own_frame:
        eye = transform.inverse(eye)
        rot = transform.rotation.T @ rot
    elif transform is not None:
        eye = eye / transform.scale + transform.rotation @ transform.centroid
    out = np.zeros_like(c2w)
    out[:, :3, :3] = Y_UP_TO_Z_UP @ rot
    out[:, :3, 3] = export_to_blender(eye, meters_per_unit)
    out[:, 3, 3] = 1.0
    return out


#: Blender's equirectangular lookup puts our column ``u`` at its ``u + 1/2``: the world texture of
#: a GLB round trip is turned half a turn about +z (measured by rendering the world straight)
WORLD_ROTATION_Z = float(np.pi)
#: how far Blender's imported shading normals may lie from the exported ones: Blender keeps custom
#: normals in a compressed per-corner encoding, measured up to 0.12 degrees off (the duck's new atlas,
#: a two-material glTF) and 0.02 on most meshes
NORMAL_TOLERANCE_DEG = 0.25
#: Principled BSDF's dielectric F0 at ``Specular IOR Level`` 0.5 and IOR 1.5, per unit tint
PRINCIPLED_F0 = 0.04


def _chain(entries: list[dict]) -> list[dict]:
    """The nodes of an upstream chain, depth first."""
    out = []
    for e in entries:
        out.append(e)
        for value in e.get("inputs", {}).values():
            if isinstance(value, list) and value and isinstance(value[0], dict):
                out.extend(_chain(value))
    return out


def material_wiring(report: dict) -> dict:
    """What feeds each Principled input of the first material: ``{input: {"image", "colorspace",
    "output" (the socket the chain leaves its image by, e.g. Green of a Separate Color), "nodes"
    (node types from the BSDF back to the image), "normal_space", "factor"}}``, plus
    ``specular_f0_scale``: the F0 Blender renders per unit of our specular texture (glTF: the
    ``KHR_materials_specular`` factor through a multiply node)."""
    mats = [m for m in report.get("materials", []) if m.get("principled")]
    if not mats:
        return {}
    wiring = {}
    linked = {name: inp for name, inp in mats[0]["principled"].items()}
    # the glTF importer's "glTF Material Output" group holds the occlusion (Blender shades without it)
    for group in mats[0].get("groups", {}).values():
        linked.update({f"group:{name}": {"linked": True, "from": chain} for name, chain in group.items()})
    for name, inp in linked.items():
        if not inp["linked"]:
            wiring[name] = {"value": inp["value"]}
            continue
        nodes = _chain(inp["from"])
        image = next((n for n in nodes if n["node"] == "TEX_IMAGE"), None)
        entry = {"nodes": [n["node"] for n in nodes], "output": inp["from"][0]["output"]}
        if image is not None:
            entry.update(image=image.get("image"), colorspace=image.get("colorspace"))
        normal_map = next((n for n in nodes if n["node"] == "NORMAL_MAP"), None)
        if normal_map is not None:
            entry.update(normal_space=normal_map["space"], normal_strength=normal_map["strength"])
        factor = 1.0
        for n in nodes:
            if n["node"] == "MIX" and n.get("blend_type") == "MULTIPLY":
                constants = [v for v in n["inputs"].values() if isinstance(v, list) and len(v) in (3, 4)]
                if constants:
                    factor *= float(np.mean(constants[-1][:3]))
        entry["factor"] = factor
        wiring[name] = entry
    level = wiring.get("Specular IOR Level", {}).get("value", 0.5)
    ior = wiring.get("IOR", {}).get("value", 1.5)
    f0_ior = ((ior - 1.0) / (ior + 1.0)) ** 2 if isinstance(ior, float) else PRINCIPLED_F0
    tint = wiring.get("Specular Tint", {})
    wiring["specular_f0_scale"] = f0_ior * 2.0 * float(level) * tint.get("factor", 1.0) if "image" in tint else 0.0
    return wiring


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def check_import(
    result: JobResult, geom, meters_per_unit: float, brdf: Brdf | str = "tango", occlusion: bool = False, tangents=None
) -> dict:
    """Compare what Blender imported with what we exported (``geom``: the
    :class:`~stages.assets.formats.ExportMesh` in export space, compared per face corner). Returns the measured
    figures and ``problems`` (empty when the asset arrived intact): one mesh with every face and
    corner, positions where they belong in metres and Z-up (units, up axis), UVs (Blender's
    ``v`` is ``1 - v`` of glTF), the shading normals, Blender's own MikkTSpace tangents and bitangents
    against the frame the normal map was baked in (handedness), and the Principled BSDF's wiring
    (the BRDF's ``blender_wiring``: for TANGO's, the specular texture as the specular tint; for
    glTF's, metallic from the blue channel of the metallic-roughness texture; with ``occlusion``, the occlusion from its red
    channel, which Blender's glTF importer keeps in its "glTF Material Output" group: pass it for
    a glTF asset only, as Blender's USD importer does not read UsdPreviewSurface's ``occlusion``).
    ``tangents (3F, 4)``: the baked frame's tangents per corner, where the geometry holds none
    per vertex (a kept layout's topology).

    An asset of several mesh objects (a kept glTF document with several mesh nodes) is checked for
    its total faces and corners and its wiring; its corners, which Blender orders object by object,
    are compared by the round trip's own-format check instead (the input's import against the
    output's: :func:`~stages.reference.roundtrip_job.own_format_check`)."""
    report, c = result.report, result.corners
    geom = geom.corners()
    meshes = [o for o in report.get("objects", []) if o["type"] == "MESH" and not o.get("bone_shape")]
    out: dict = {"blender": report.get("blender"), "mesh_objects": len(meshes)}
    n = len(geom.positions)
    faces, corners = sum(m["faces"] for m in meshes), sum(m["corners"] for m in meshes)
    out.update(faces=faces, corners=corners, uv_maps=sorted({u for m in meshes for u in m["uv_maps"]}))
    if not meshes or not c:
        return {**out, "problems": [f"expected one mesh object, found {len(meshes)}"]}
    if corners != n or faces != n // 3:
        return {**out, "problems": [f"{faces} faces / {corners} corners arrived, {n // 3} / {n} exported"]}
    if len(meshes) == 1:
        out["bbox_min"], out["bbox_max"] = meshes[0]["bbox_min"], meshes[0]["bbox_max"]
        problems = _corner_checks(out, c, geom, meters_per_unit, tangents)
    else:
        out["corners_compared"] = f"by the own-format check ({len(meshes)} mesh objects)"
        problems = []
    problems += _wiring_checks(out, report, brdfs.get(brdf), occlusion)
    return {**out, "problems": problems}


def _corner_checks(out: dict, c: dict, geom, meters_per_unit: float, tangents) -> list[str]:
    """:func:`check_import`'s per-corner comparison of one imported mesh (its figures go into ``out``)."""
    problems = []
    if not np.all(c["face_sizes"] == 3):
        return ["the faces did not arrive as triangles"]
    want = export_to_blender(geom.positions, meters_per_unit)
    diag = float(np.linalg.norm(want.max(0) - want.min(0)))
    out["position_error_rel"] = float(np.abs(c["position"] - want).max() / diag)
    if out["position_error_rel"] > 1e-5:
        problems.append(f"positions differ by {out['position_error_rel']:.2g} of the diagonal (units or up axis)")
    if not out["uv_maps"] or "uv" not in c:
        return [*problems, "no UV map arrived"]
    uv_want = np.stack([geom.uv[:, 0], 1.0 - geom.uv[:, 1]], axis=1)
    out["uv_error"] = float(np.abs(c["uv"] - uv_want).max())
    if out["uv_error"] > 1e-5:
        problems.append(f"UVs differ by up to {out['uv_error']:.2g}")
    normals = geom.normals.astype(np.float64) @ Y_UP_TO_Z_UP.T
    out["normal_error_deg"] = float(_angle_deg(c["normal"], normals).max())
    if out["normal_error_deg"] > NORMAL_TOLERANCE_DEG:
        problems.append(f"shading normals differ by up to {out['normal_error_deg']:.2g} degrees")
    # tangents: Blender computes its own (MikkTSpace) and its normal-map node uses them
    frame = geom.tangents if tangents is None else tangents
    t_want = frame[:, :3].astype(np.float64) @ Y_UP_TO_Z_UP.T
    b_want = frame[:, 3:4] * np.cross(normals, t_want)
    b_blender = c["bitangent_sign"][:, None] * np.cross(c["normal"], c["tangent"])
    good = np.linalg.norm(t_want, axis=1) > 0.5  # faces with a degenerate UV triangle have no frame
    t_err, b_err = _angle_deg(c["tangent"], t_want)[good], _angle_deg(b_blender, b_want)[good]
    out["tangent_error_deg_p99"] = float(np.percentile(t_err, 99)) if len(t_err) else 0.0
    out["bitangent_error_deg_p99"] = float(np.percentile(b_err, 99)) if len(b_err) else 0.0
    out["handedness_agreement"] = float((b_err < 90.0).mean()) if len(b_err) else 1.0
    if out["tangent_error_deg_p99"] > 1.0 or out["handedness_agreement"] < 0.999:
        problems.append(
            f"Blender's tangent frame differs from the baked one (tangents p99 {out['tangent_error_deg_p99']:.2g} deg, "
            f"handedness agrees on {100 * out['handedness_agreement']:.2f}% of corners)"
        )
    return problems


def _wiring_checks(out: dict, report: dict, brdf: Brdf, occlusion: bool) -> list[str]:
    """:func:`check_import`'s check of the Principled BSDF's inputs (its figures go into ``out``)."""
    problems = []
    wiring = material_wiring(report)
    out["wiring"] = wiring
    expect = {
        "Base Color": ("basecolor", "sRGB", None),
        "Roughness": ("metallic_roughness", "Non-Color", "Green"),
        "Normal": ("normal", "Non-Color", None),
        **brdf.blender_wiring,
        **({"group:Occlusion": ("metallic_roughness", "Non-Color", "Red")} if occlusion else {}),
    }
    if not wiring:
        problems.append("no Principled BSDF arrived")
    for name, (image, space, channel) in expect.items():
        got = wiring.get(name, {})
        stem = Path(got["image"]).stem if got.get("image") else None  # glTF images arrive by name, USD by file
        if stem != image or got.get("colorspace") != space:
            problems.append(f"Principled {name} is fed by {got.get('image')} ({got.get('colorspace')}), not {image} ({space})")
        if channel and got.get("output") != channel:
            problems.append(f"Principled {name} reads {got.get('output')!r} of {image}, expected its {channel} channel")
    if wiring and wiring.get("Normal", {}).get("normal_space") != "TANGENT":
        problems.append("the normal map is not a tangent-space Normal Map node")
    out["specular_f0_scale"] = wiring.get("specular_f0_scale", 0.0) if wiring else 0.0
    return problems


def pick_views(count: int, wanted: int) -> list[int]:
    """``wanted`` view indices evenly spread over ``count`` (all of them when ``wanted`` is 0 or
    at least ``count``)."""
    if wanted <= 0 or wanted >= count:
        return list(range(count))
    return sorted({int(round(x)) for x in np.linspace(0, count, wanted, endpoint=False)})


def render_job(c2w: np.ndarray, fov_deg: float, width: int, *, spp: int, seed: int, transport: str, environment=None) -> dict:
    """The ``render`` part of a job: our cameras (already in Blender's world), ``spp`` samples per
    pixel split over two seeds, and ``environment`` (an equirectangular file set as the world,
    turned by :data:`WORLD_ROTATION_Z`; None keeps the world the importer made)."""
    job = {
        "cameras": np.asarray(c2w).tolist(),
        "fov_deg": float(fov_deg),
        "width": int(width),
        "spp": int(spp) // 2,
        "seeds": [int(seed), int(seed) + 1],
        "transport": transport,
    }
    if environment is not None:
        job.update(environment=str(environment), environment_rotation_z=WORLD_ROTATION_Z)
    return job


@dataclass
class Comparison:
    """Blender's renders against ours over fully covered object pixels, sRGB: ``psnr_db``,
    ``noise_psnr_db`` (the Cycles renders against their own noise, from the two seeds),
    ``per_view_psnr_db``, ``pixels``, and the images ``ours, theirs (V, W, W, 3)`` (linear, NaN
    off the object) for figures."""

    psnr_db: float
    noise_psnr_db: float
    per_view_psnr_db: list[float]
    pixels: int
    ours: np.ndarray
    theirs: np.ndarray


def compare_renders(hits: list, renders: np.ndarray, reference: list[np.ndarray]) -> Comparison:
    """``hits``: the :class:`~stages.geometry.raycache.ViewHits` of each rendered view;
    ``renders (V, 2, W, W, 4)`` from Blender (premultiplied RGBA, two seeds); ``reference``: our
    linear radiance per hit of each view ``(N_i, 3)``."""

    def srgb(x):
        return np.clip(srgb_encode(np.clip(x, 0.0, None)), 0.0, 1.0)

    ours_all, theirs_all, per_view, noise_sum = [], [], [], 0.0
    v, _, w = renders.shape[:3]
    ours_img = np.full((v, w, w, 3), np.nan, np.float32)
    theirs_img = np.full((v, w, w, 3), np.nan, np.float32)
    for i, (h, ref) in enumerate(zip(hits, reference, strict=True)):
        halves = renders[i].reshape(2, -1, 4)[:, h.pixel]
        mean = halves.mean(0)
        full = mean[:, 3] >= FULL_COVERAGE
        if not full.any():
            per_view.append(float("nan"))
            continue
        theirs = mean[full, :3] / mean[full, 3:4]
        a, b = srgb(theirs), srgb(ref[full])
        ours_all.append(b)
        theirs_all.append(a)
        per_view.append(psnr(torch.from_numpy(a), torch.from_numpy(b)))
        h0, h1 = (srgb(x[full, :3] / np.maximum(x[full, 3:4], 1e-8)) for x in halves)
        noise_sum += float(((h0 - h1) ** 2).sum() / 4.0)
        idx = h.pixel[full]
        ours_img[i].reshape(-1, 3)[idx] = ref[full]
        theirs_img[i].reshape(-1, 3)[idx] = theirs
    if not ours_all:
        raise RuntimeError("no evaluation view has a fully covered object pixel in Blender's renders")
    a, b = np.concatenate(theirs_all), np.concatenate(ours_all)
    noise_mse = noise_sum / a.size
    return Comparison(
        psnr(torch.from_numpy(a), torch.from_numpy(b)),
        float("inf") if noise_mse == 0 else float(10.0 * np.log10(1.0 / noise_mse)),
        per_view,
        len(a),
        ours_img,
        theirs_img,
    )


def probe(glb: Path, workdir: Path, expected_faces: int, timeout_s: float = 180.0) -> str:
    """The smallest real use of Blender, for the doctor: import the tiny GLB ``glb`` (written by
    :func:`stages.geometry.probes.write_probe_glb`) through the job script the roundtrip stage
    runs, and check that one mesh with ``expected_faces`` faces and a Principled BSDF arrived.
    Raises :class:`BlenderUnavailable` or what the job raised."""
    res = run_job({"asset": str(Path(glb).resolve()), "inspect": True}, workdir, timeout_s)
    meshes = [o for o in res.report.get("objects", []) if o.get("type") == "MESH"]
    if len(meshes) != 1 or meshes[0].get("faces") != expected_faces:
        raise RuntimeError(
            f"Blender imported {[m.get('faces') for m in meshes]} face(s) per mesh, not one mesh of {expected_faces}"
        )
    if not any(m.get("principled") for m in res.report.get("materials", [])):
        raise RuntimeError("Blender imported the GLB without a Principled BSDF material")
    return f"Blender {res.report.get('blender')} imported a {expected_faces}-face GLB in {res.seconds:.1f} s"
