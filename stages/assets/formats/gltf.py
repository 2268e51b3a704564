"""glTF: ``model.glb``, a self-contained binary glTF 2.0 file, and the Khronos glTF-Validator.

Metallic-roughness in the mapping of the asset's BRDF (its row's ``exported_textures``,
``gltf_extensions`` and ``gltf_material_extensions``, :mod:`stages.config.brdfs`). TANGO's BRDF:
``metallic = 0``, ``baseColor`` = albedo, roughness in the green channel of
``metallicRoughnessTexture`` (and, where the bake wrote one, the ambient occlusion in its red
channel as the ``occlusionTexture``), ``normalTexture`` with explicit ``TANGENT`` vectors (the
bake's frame), and ``KHR_materials_specular`` for the coloured F0: glTF's dielectric F0 is
``0.04 * specularColorFactor * specularColorTexture`` (IOR 1.5), so the factor is 25 and the
texture holds TANGO's F0 (clamped to 1 by glTF). What is lost: glTF makes the diffuse lobe give
way to the specular one (energy conservation, ``(1 - F)`` weighting) where TANGO simply adds them,
so a glTF viewer renders slightly darker diffuse at grazing angles; glTF's Fresnel uses the half
vector per light sample where TANGO evaluates it once at the mirror direction; and the
environment light is not part of glTF core (it ships beside the model as ``light.exr``/``.hdr``).
The learned suns are in the file as ``KHR_lights_punctual`` directional lights (their angular
size, which glTF lacks, in each light's ``extras``).
A field trained with glTF's own BRDF (``optimize.brdf: gltf``) is written as it was trained, with
nothing lost: the baked base colour, roughness (green) and metallic (blue), no extension. The
levels of detail go into one file with ``MSFT_lod`` (:meth:`GltfFormat.write_levels`).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np

from ...config.brdfs import BrdfSpec, brdf_spec
from ...config.layout import EXPORT_FORMATS, LEVELS_STEM
from ...core.errors import StageInputError
from ...core.provenance import ORIGIN_METADATA_KEY, atomic_path
from ...core.safefiles import IMAGE_LIMIT, read_bytes
from ...core.tools import GLTF_VALIDATOR, REPO_ROOT
from ...render.distant import DistantLight
from .base import AssetInfo, Exporter, facing_rotation, one_line
from .mesh import ExportMesh, Level


class GltfFormat(Exporter):
    """glTF: ``model.glb`` with its textures inside, judged by the Khronos glTF-Validator (where
    Node.js and the validator are installed)."""

    def write(self, folder: Path, geom: ExportMesh, asset: AssetInfo) -> None:
        (glb,) = (Path(folder) / name for name in self.files().values())
        write_glb(glb, geom, Path(folder) / "textures", asset)

    def write_levels(self, folder: Path, levels: list[Level], asset: AssetInfo, coverage: list[float]) -> None:
        """The finest level in the scene, the coarser ones as its ``MSFT_lod`` alternatives."""
        (glb,) = (Path(folder) / name for name in self.files(LEVELS_STEM).values())
        lods = [(lv.geom, Path(folder) / lv.textures) for lv in levels[1:]]
        write_glb(glb, levels[0].geom, Path(folder) / levels[0].textures, asset, lods, coverage)

    def validate(self, folder: Path, stem: str = "model") -> dict[str, dict]:
        return {name: validate_glb(Path(folder) / name) for name in self.files(stem).values()}

    def record(self, reports: dict[str, dict]) -> dict:
        """The validator's errors and warnings (None where it did not run)."""
        (report,) = (reports[name] for name in self.files().values())
        return {"gltf_validation_errors": report.get("errors"), "gltf_validation_warnings": report.get("warnings")}


def validate_glb(path: Path) -> dict:
    """The Khronos glTF-Validator's counts for ``path`` when Node.js and the validator are installed
    (``scripts/setup.sh`` runs ``npm ci``), else ``{"ran": False, "reason": ...}``.

    Returns ``{"ran": True, "validator" (name and version), "errors", "warnings", "infos",
    "hints", "messages"}`` (the errors' and warnings' messages, errors first, each on one line).

    Raises:
        StageInputError: the validator failed on the file, or wrote no report (one line: why).
    """
    node = shutil.which("node")
    if node is None or not GLTF_VALIDATOR.is_dir():
        # the folder relative to the checkout: a record that travels in a pack names no local path
        where = GLTF_VALIDATOR.relative_to(REPO_ROOT).as_posix()
        missing = "Node.js (node) is not on PATH" if node is None else f"the validator ({where}) is missing: run npm ci"
        return {"ran": False, "reason": missing}
    remedy = "Check the validator with python -m stages.doctor (npm ci reinstalls it)."
    try:
        proc = subprocess.run(
            [node, str(REPO_ROOT / "scripts" / "validate_gltf.mjs"), str(path)],
            capture_output=True,
            text=True,
            errors="replace",
            timeout=300,
        )
    except subprocess.TimeoutExpired:
        raise StageInputError(path, "the Khronos glTF-Validator did not finish within 300 s", remedy) from None
    if proc.returncode != 0:
        said = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        why = next((ln for ln in said if "Error" in ln), said[-1] if said else f"exit status {proc.returncode}")
        raise StageInputError(path, f"the Khronos glTF-Validator could not check it ({one_line(why, 200)})", remedy)
    try:
        report = json.loads(proc.stdout)
        issues = report["issues"]
        found = sorted((m for m in issues["messages"] if m["severity"] <= 1), key=lambda m: m["severity"])  # errors first
        return {
            "ran": True,
            "validator": f"Khronos glTF-Validator {one_line(report.get('validatorVersion'), 40)}",
            "errors": int(issues["numErrors"]),
            "warnings": int(issues["numWarnings"]),
            "infos": int(issues["numInfos"]),
            "hints": int(issues["numHints"]),
            # the validator stops listing (and counting) after its first 100 messages
            "truncated": bool(issues.get("truncated", False)),
            "messages": [one_line(f"{m['code']} at {m.get('pointer', '')}: {m['message']}") for m in found],
        }
    except (ValueError, KeyError, TypeError) as exc:
        raise StageInputError(
            path, f"the Khronos glTF-Validator's report cannot be read ({type(exc).__name__})", remedy
        ) from None


def write_glb(
    path: Path,
    geom: ExportMesh,
    textures_dir: Path,
    asset: AssetInfo,
    lods: list[tuple[ExportMesh, Path]] = (),
    screen_coverage: list[float] | None = None,
) -> None:
    """Write a self-contained binary glTF 2.0 file of ``geom`` and the textures in ``textures_dir``
    (see the module docstring for the mapping) with what ``asset`` says of it: its metres per
    unit and name, its ``origin`` (into ``asset.extras.tango_stylize``), its BRDF, whether the
    material's ``occlusionTexture`` is the metallic-roughness texture (its red channel, glTF's
    packing: ``asset.occlusion``), and its distant ``lights`` (the learned suns), which become
    ``KHR_lights_punctual`` directional lights, one node each in the scene (:func:`add_distant_lights`).

    ``lods`` (coarser levels, each geometry with its textures' folder) makes the file an
    ``MSFT_lod`` asset: the scene's node holds the finest level and lists one node per coarser
    level (outside the scene) in ``extensions.MSFT_lod.ids``, each with its own mesh and material,
    and ``extras.MSFT_screencoverage`` (one threshold per level, finest first) says when to switch.
    A viewer without the extension shows the finest level."""
    import pygltflib as g

    brdf, occlusion, meters_per_unit, name = brdf_spec(asset.brdf), asset.occlusion, asset.meters_per_unit, asset.name
    buffer = GlbBuffer(g)
    materials, meshes, nodes = [], [], []
    for k, (level, tex_dir) in enumerate([(geom, textures_dir), *lods]):
        tag = "" if not lods else f"lod{k}"
        attrs, parts = buffer.geometry(level, meters_per_unit)
        firsts: dict[str, int] = {}
        primitives = []
        for slot, indices in parts:
            folder = level.texture_folder(slot)
            if folder not in firsts:  # one texture set per folder, shared by the slots that read it
                firsts[folder] = buffer.texture_set(Path(tex_dir) / folder, brdf, tag)
            primitives.append(g.Primitive(attributes=attrs, indices=indices, material=len(materials)))
            material = slot or (f"TangoMaterial_{tag}" if tag else "TangoMaterial")
            materials.append(glb_material(g, material, firsts[folder], brdf, occlusion))
        label = f"{name}_{tag}" if tag else name
        meshes.append(g.Mesh(name=label, primitives=primitives))
        nodes.append(g.Node(mesh=k, name=label))
    used = list(brdf.gltf_extensions)
    if lods:
        if screen_coverage is None or len(screen_coverage) != len(lods) + 1:
            raise ValueError(f"MSFT_lod needs one screen coverage per level ({len(lods) + 1}), got {screen_coverage}")
        nodes[0].extensions = {"MSFT_lod": {"ids": list(range(1, len(nodes)))}}
        nodes[0].extras = {"MSFT_screencoverage": [float(c) for c in screen_coverage]}
        used.append("MSFT_lod")
    scene_nodes = [0, *add_distant_lights(g, nodes, asset.lights, used)]
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="tango-stylize", extras={ORIGIN_METADATA_KEY: asset.origin}),
        scene=0,
        scenes=[g.Scene(nodes=scene_nodes)],
        nodes=nodes,
        meshes=meshes,
        materials=materials,
        textures=buffer.textures,
        images=buffer.images,
        samplers=[glb_sampler(g, geom.repeat)],
        accessors=buffer.accessors,
        bufferViews=buffer.views,
        buffers=[g.Buffer(byteLength=sum(len(b) for b in buffer.blobs))],
        extensionsUsed=used,
    )
    if asset.lights:
        gltf.extensions = {LIGHTS_EXTENSION: {"lights": punctual_lights(asset.lights)}}
    gltf.set_binary_blob(b"".join(buffer.blobs))
    with atomic_path(path) as tmp:
        gltf.save_binary(str(tmp))


#: the extension that carries the learned suns
LIGHTS_EXTENSION = "KHR_lights_punctual"
#: lumens per watt (at 555 nm): a glTF directional light's intensity is in lux, which an importer
#: reads as irradiance through this factor (Blender's, in its default lighting mode)
LUMENS_PER_WATT = 683.0


def punctual_lights(lights: tuple[DistantLight, ...]) -> list[dict]:
    """The document-level ``KHR_lights_punctual`` lights of distant ``lights``: directional, the
    colour the irradiance over its largest channel, the intensity that channel in lux
    (:data:`LUMENS_PER_WATT` times the irradiance, in W/m^2 where the environment image's
    radiance is read as W/(m^2 sr)); glTF has no angular size, so the radius and the irradiance
    also go into the light's ``extras``."""
    out = []
    for k, light in enumerate(lights):
        e = np.asarray(light.irradiance, np.float64)
        peak = float(e.max()) if e.size and e.max() > 0 else 0.0
        colour = (e / peak).tolist() if peak > 0 else [1.0, 1.0, 1.0]
        out.append(
            {
                "type": "directional",
                "name": f"Sun{k}",
                "color": [float(c) for c in colour],
                "intensity": LUMENS_PER_WATT * peak,
                "extras": light.record(),
            }
        )
    return out


def add_distant_lights(g, nodes: list, lights: tuple[DistantLight, ...], used: list[str], first: int = 0) -> list[int]:
    """Append one node per distant light to ``nodes`` (turned so that it shines along the light's
    ``-direction``: :func:`~stages.assets.formats.base.facing_rotation`), each naming its light
    of :func:`punctual_lights` in the ``KHR_lights_punctual`` extension (numbered from ``first``:
    after a document's own lights), and the extension to ``used`` where there is any; returns the
    new nodes' indices."""
    added = []
    for k, light in enumerate(lights):
        rotation = list(facing_rotation(light.direction))
        nodes.append(g.Node(name=f"Sun{k}", rotation=rotation, extensions={LIGHTS_EXTENSION: {"light": first + k}}))
        added.append(len(nodes) - 1)
    if lights and LIGHTS_EXTENSION not in used:
        used.append(LIGHTS_EXTENSION)
    return added


class GlbBuffer:
    """The binary buffer of a GLB: its byte blobs (each padded to 4 bytes), buffer views and
    accessors, as ``write_glb`` adds them (``g``: the pygltflib module)."""

    def __init__(self, g) -> None:
        self.g = g
        self.blobs: list[bytes] = []
        self.views: list = []
        self.accessors: list = []
        self.images: list = []
        self.textures: list = []

    def texture_set(self, folder: Path, brdf: BrdfSpec, tag: str = "", sampler: int = 0) -> int:
        """Add the bake's textures in ``folder`` that ``brdf``'s assets reference
        (``brdf.exported_textures``: base colour, metallic-roughness, normal, and for TANGO's BRDF
        the specular colour) as images and textures; returns the first's index."""
        g = self.g
        first = len(self.textures)
        for key in brdf.exported_textures:
            view = self.view(read_bytes(Path(folder) / f"{key}.png", IMAGE_LIMIT, remedy="Run the bake stage again."))
            self.images.append(g.Image(bufferView=view, mimeType="image/png", name=f"{tag}_{key}" if tag else key))
            self.textures.append(g.Texture(source=len(self.images) - 1, sampler=sampler))
        return first

    def view(self, data: bytes, target=None) -> int:
        offset = sum(len(b) for b in self.blobs)
        self.blobs.append(data + b"\x00" * ((-len(data)) % 4))
        self.views.append(self.g.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
        return len(self.views) - 1

    def accessor(self, arr: np.ndarray, kind: str, target=None, minmax: bool = False) -> int:
        g = self.g
        view = self.view(np.ascontiguousarray(arr).tobytes(), g.ARRAY_BUFFER if target is None else target)
        ctype = {np.dtype(np.float32): g.FLOAT, np.dtype(np.uint32): g.UNSIGNED_INT, np.dtype(np.uint16): g.UNSIGNED_SHORT}[
            arr.dtype
        ]
        acc = g.Accessor(bufferView=view, componentType=ctype, count=len(arr), type=kind)
        if minmax:
            acc.min = arr.min(0).astype(float).tolist()
            acc.max = arr.max(0).astype(float).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def geometry(self, level: ExportMesh, meters_per_unit: float):
        """A level's vertex attributes (positions in metres; tangents where it has them) and, per
        material slot (:meth:`ExportMesh.slot_faces`), its name and index accessor."""
        g = self.g
        pos = level.positions * np.float32(meters_per_unit)
        attrs = g.Attributes(
            POSITION=self.accessor(pos, g.VEC3, minmax=True),
            NORMAL=self.accessor(level.normals, g.VEC3),
            TANGENT=None if level.tangents is None else self.accessor(level.tangents, g.VEC4),
            TEXCOORD_0=self.accessor(level.uv, g.VEC2),
        )
        # 16-bit indices where they suffice (glTF allows both; the 65535th index is reserved for restarts)
        index_type = np.uint16 if len(pos) < 65535 else np.uint32
        parts = []
        for slot, faces in level.slot_faces():
            tri = level.indices[faces].reshape(-1).astype(index_type)
            parts.append((slot, self.accessor(tri, g.SCALAR, target=g.ELEMENT_ARRAY_BUFFER)))
        return attrs, parts


def glb_sampler(g, repeat: bool):
    """Trilinear filtering; textures repeat (a kept layout, glTF's default) or clamp (an atlas)."""
    wrap = g.REPEAT if repeat else g.CLAMP_TO_EDGE
    return g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=wrap, wrapT=wrap)


def glb_material(g, name: str, first: int, brdf: BrdfSpec, occlusion: bool, texcoord: int = 0):
    """A level's material: its textures from index ``first`` (base colour, metallic-roughness,
    normal, and TANGO's specular colour through ``KHR_materials_specular``: ``brdf``'s
    ``gltf_material_extensions``), the occlusion in the metallic-roughness texture's red channel
    when baked, each read through UV set ``texcoord`` (``TEXCOORD_<texcoord>``)."""
    uv = {"texCoord": texcoord} if texcoord else {}
    return g.Material(
        name=name,
        pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorTexture=g.TextureInfo(index=first, **uv),
            metallicRoughnessTexture=g.TextureInfo(index=first + 1, **uv),
            metallicFactor=1.0,  # the texture's blue channel is the metalness (0 for TANGO's BRDF)
            roughnessFactor=1.0,
        ),
        normalTexture=g.NormalMaterialTexture(index=first + 2, **uv),
        occlusionTexture=g.OcclusionTextureInfo(index=first + 1, **uv) if occlusion else None,
        doubleSided=True,
        extensions=brdf.gltf_material_extensions(first, texcoord),
    )


#: glTF's format object (its row: ``EXPORT_FORMATS["gltf"]``)
GLTF = GltfFormat(EXPORT_FORMATS["gltf"])
