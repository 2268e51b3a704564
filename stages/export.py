"""export: turn a bake into an asset pack: USD (``model.usda`` + packaged ``model.usdz``), glTF 2.0
(``model.glb``), textures, the learned light and a preview image.

Geometry is faceted (each face has its own three vertices and its flat normal), which is how
TANGO shades the mesh and makes the per-face tangent frame of the bake exact for viewers. It is
returned to the input's units and position through the normalisation's inverse transform (the
rotation that made the input's up axis +Y is kept, so ``upAxis`` is Y), or left in the
normalised frame (``units: normalized``).

Material mapping:

* **USD** ``UsdPreviewSurface`` with ``useSpecularWorkflow = 1``: ``diffuseColor`` = the baked
  albedo, ``specularColor`` = TANGO's specular colour (F0), ``roughness`` = TANGO's roughness
  (both use ``alpha = roughness^2``), ``normal`` = the tangent-space normal map (scale 2, bias -1).
  A ``DomeLight`` carries the learned SG light as an equirectangular EXR (latlong).
* **glTF** metallic-roughness with ``metallic = 0``: ``baseColor`` = albedo, roughness in the green
  channel of ``metallicRoughnessTexture``, ``normalTexture`` with explicit ``TANGENT`` vectors (the
  bake's frame), and ``KHR_materials_specular`` for the coloured F0: glTF's dielectric F0 is
  ``0.04 * specularColorFactor * specularColorTexture`` (IOR 1.5), so the factor is 25 and the
  texture holds TANGO's F0 (clamped to 1 by glTF). What is lost: glTF makes the diffuse lobe
  give way to the specular one (energy conservation, ``(1 - F)`` weighting) where TANGO simply adds
  them, so a glTF viewer renders slightly darker diffuse at grazing angles; glTF's Fresnel uses
  the half vector per light sample where TANGO evaluates it once at the mirror direction; and the
  environment light is not part of glTF core (it ships beside the model as ``light.exr``/``.hdr``).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ConfigError, StageInputError, stage_errors
from .meshio import TriMesh, load_ply
from .normalize import Similarity
from .provenance import (
    ORIGIN_KEY,
    Timer,
    atomic_path,
    metadata,
    read_origin,
    setup_logging,
    staged_outputs,
    write_json_atomic,
)
from .settings import Settings

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]
#: key of the origin record in the USD layer's customLayerData and the glTF asset's extras
ORIGIN_METADATA_KEY = "tango_stylize"
TEXTURE_FILES = {k: f"textures/{k}.png" for k in ("basecolor", "metallic_roughness", "specular", "normal")}


@dataclass(frozen=True, kw_only=True)
class ExportSettings(Settings):
    """Settings of the export stage (config section ``export``)."""

    section = "export"
    #: "original": the input's units and position (inverse transform); "normalized": unit sphere
    units: str = "original"
    #: metres per unit of the exported geometry (USD metersPerUnit; glTF positions are scaled
    #: to metres by it)
    meters_per_unit: float = 1.0

    def __post_init__(self) -> None:
        if self.units not in ("original", "normalized"):
            raise ConfigError(f"export.units must be 'original' or 'normalized', got {self.units!r}")
        if not self.meters_per_unit > 0:
            raise ConfigError("export.meters_per_unit must be > 0")


@dataclass
class Faceted:
    """Per-corner arrays of a faceted mesh: ``positions, normals (3F, 3)``, ``uv (3F, 2)`` (glTF
    convention), ``tangents (3F, 4)``."""

    positions: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    tangents: np.ndarray


def faceted(mesh: TriMesh, atlas: dict, transform: Similarity | None) -> Faceted:
    """Corners of every face in export space (see the module docstring for the frame)."""
    pos = mesh.vertices[mesh.faces].reshape(-1, 3)
    n = np.repeat(mesh.face_normals, 3, axis=0)
    t = np.repeat(atlas["tangent"], 3, axis=0)
    w = np.repeat(atlas["handedness"], 3)
    if transform is not None:
        # x' = R x_original = x_normalized / scale + R c: original units and position, +Y up
        pos = pos / transform.scale + transform.rotation @ transform.centroid
    return Faceted(
        pos.astype(np.float32),
        n.astype(np.float32),
        atlas["uv"].reshape(-1, 2).astype(np.float32),
        np.concatenate([t, w[:, None]], axis=1).astype(np.float32),
    )


# ------------------------------------------------------------------------------------------ USD
def write_usd(path: Path, geom: Faceted, meters_per_unit: float, light_file: str | None, origin: dict) -> None:
    """Write ``model.usda``: a Mesh with ``st`` and normals, a UsdPreviewSurface bound to it, and
    a DomeLight with the learned light. Texture paths are relative to the file. ``origin`` (the
    guidance and weights that made the material) goes into the root layer's ``customLayerData``
    under ``tango_stylize`` and its label into the layer's documentation."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade, Vt

    stage = Usd.Stage.CreateNew(str(path))
    layer = stage.GetRootLayer()
    layer.documentation = f"tango-stylize asset. {origin['label']}"
    layer.customLayerData = {ORIGIN_METADATA_KEY: {k: v for k, v in origin.items() if v is not None}}
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    root = UsdGeom.Xform.Define(stage, "/Asset")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind("component")
    mesh = UsdGeom.Mesh.Define(stage, "/Asset/Geometry/Mesh")
    count = len(geom.positions)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(geom.positions))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(count // 3, 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.arange(count, dtype=np.int32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(geom.normals))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateDoubleSidedAttr(True)
    lo, hi = geom.positions.min(0), geom.positions.max(0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    st = np.stack([geom.uv[:, 0], 1.0 - geom.uv[:, 1]], axis=1).astype(np.float32)
    pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    pv.Set(Vt.Vec2fArray.FromNumpy(st))

    mat = UsdShade.Material.Define(stage, "/Asset/Looks/TangoMaterial")
    surf = UsdShade.Shader.Define(stage, "/Asset/Looks/TangoMaterial/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, "/Asset/Looks/TangoMaterial/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    varname = mat.CreateInput("frame:stPrimvarName", Sdf.ValueTypeNames.String)
    varname.Set("st")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).ConnectToSource(varname)

    def texture(name: str, file: str, color_space: str, scale=None, bias=None):
        tex = UsdShade.Shader.Define(stage, f"/Asset/Looks/TangoMaterial/{name}")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        if scale is not None:
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
            tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
        return tex

    base = texture("BaseColorTexture", TEXTURE_FILES["basecolor"], "sRGB")
    base.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(base.ConnectableAPI(), "rgb")
    spec = texture("SpecularTexture", TEXTURE_FILES["specular"], "sRGB")
    spec.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(spec.ConnectableAPI(), "rgb")
    rough = texture("RoughnessTexture", TEXTURE_FILES["metallic_roughness"], "raw")
    rough.CreateOutput("g", Sdf.ValueTypeNames.Float)
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(rough.ConnectableAPI(), "g")
    nrm = texture("NormalTexture", TEXTURE_FILES["normal"], "raw", (2.0, 2.0, 2.0, 1.0), (-1.0, -1.0, -1.0, 0.0))
    nrm.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(nrm.ConnectableAPI(), "rgb")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)

    if light_file:
        dome = UsdLux.DomeLight.Define(stage, "/Asset/Lights/LearnedLight")
        dome.CreateTextureFileAttr().Set(light_file)
        dome.CreateTextureFormatAttr().Set(UsdLux.Tokens.latlong)
        dome.CreateIntensityAttr().Set(1.0)
    stage.GetRootLayer().Save()


def package_usdz(usda: Path, usdz: Path, files: list[str]) -> None:
    """Package ``usda`` (first, as the root layer) and ``files`` (paths relative to it, stored
    under the same relative paths) into ``usdz``, atomically, with usd-core's zip writer (which
    aligns entries as the usdz format requires)."""
    from pxr import Sdf

    with atomic_path(usdz) as tmp:
        tmp.unlink()
        writer = Sdf.ZipFileWriter.CreateNew(str(tmp))
        writer.AddFile(str(usda), usda.name)
        for rel in files:
            writer.AddFile(str(usda.parent / rel), rel)
        writer.Save()


def validate_usd(path: Path) -> dict:
    """Run every validator usd-core registers on ``path`` and count what they report.

    Returns ``{"file", "validators" (how many ran), "validator_names" (sorted), "validator_digest"
    (SHA-256 of the names, one per line), "errors", "warnings", "infos" (counts), "messages"
    (``"name: message"`` of every error and warning)}``. Nothing here is a constant: a stage whose
    validators report errors fails, and the counts say what ran.
    """
    import hashlib

    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(path))
    registry = UsdValidation.ValidationRegistry()
    validators = registry.GetOrLoadAllValidators()
    names = sorted(v.GetMetadata().name for v in validators)
    context = UsdValidation.ValidationContext(validators)
    issues = context.Validate(stage)
    kinds = UsdValidation.ValidationErrorType
    count = {kind: sum(1 for e in issues if e.GetType() == kind) for kind in (kinds.Error, kinds.Warn, kinds.Info)}
    return {
        "file": Path(path).name,
        "validators": len(validators),
        "validator_names": names,
        "validator_digest": hashlib.sha256("\n".join(names).encode()).hexdigest(),
        "errors": count[kinds.Error],
        "warnings": count[kinds.Warn],
        "infos": count[kinds.Info],
        "messages": [f"{e.GetName()}: {e.GetMessage()}" for e in issues if e.GetType() in (kinds.Error, kinds.Warn)],
    }


#: the Khronos glTF-Validator as the repository installs it (``npm ci``; see package.json)
GLTF_VALIDATOR = REPO_ROOT / "node_modules" / "gltf-validator"


def validate_glb(path: Path) -> dict:
    """The Khronos glTF-Validator's counts for ``path`` when Node.js and the validator are installed
    (``scripts/setup.sh`` runs ``npm ci``), else ``{"ran": False, "reason": ...}``.

    Returns ``{"ran": True, "validator" (name and version), "errors", "warnings", "infos",
    "hints", "messages"}``.
    """
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None or not GLTF_VALIDATOR.is_dir():
        missing = "Node.js (node) is not on PATH" if node is None else f"{GLTF_VALIDATOR} is missing (run npm ci)"
        return {"ran": False, "reason": missing}
    proc = subprocess.run(
        [node, str(REPO_ROOT / "scripts" / "validate_gltf.mjs"), str(path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"the Khronos glTF-Validator could not run on {path}: {proc.stderr.strip()[-2000:]}")
    report = json.loads(proc.stdout)
    issues = report["issues"]
    return {
        "ran": True,
        "validator": f"Khronos glTF-Validator {report.get('validatorVersion')}",
        "errors": int(issues["numErrors"]),
        "warnings": int(issues["numWarnings"]),
        "infos": int(issues["numInfos"]),
        "hints": int(issues["numHints"]),
        "messages": [f"{m['code']} at {m.get('pointer', '')}: {m['message']}" for m in issues["messages"] if m["severity"] <= 1],
    }


# ----------------------------------------------------------------------------------------- glTF
def write_glb(path: Path, geom: Faceted, textures_dir: Path, meters_per_unit: float, name: str, origin: dict) -> None:
    """Write a self-contained binary glTF 2.0 file (see the module docstring for the mapping);
    ``origin`` goes into ``asset.extras.tango_stylize``."""
    import pygltflib as g

    pos = geom.positions * np.float32(meters_per_unit)
    blobs: list[bytes] = []
    views: list[g.BufferView] = []
    accessors: list[g.Accessor] = []

    def add_view(data: bytes, target=None) -> int:
        offset = sum(len(b) for b in blobs)
        pad = (-len(data)) % 4
        blobs.append(data + b"\x00" * pad)
        views.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
        return len(views) - 1

    def add_accessor(arr: np.ndarray, kind: str, target=g.ARRAY_BUFFER, minmax=False) -> int:
        view = add_view(np.ascontiguousarray(arr).tobytes(), target)
        ctype = g.FLOAT if arr.dtype == np.float32 else g.UNSIGNED_INT
        acc = g.Accessor(bufferView=view, componentType=ctype, count=len(arr), type=kind)
        if minmax:
            acc.min = arr.min(0).astype(float).tolist()
            acc.max = arr.max(0).astype(float).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    attrs = g.Attributes(
        POSITION=add_accessor(pos, g.VEC3, minmax=True),
        NORMAL=add_accessor(geom.normals, g.VEC3),
        TANGENT=add_accessor(geom.tangents, g.VEC4),
        TEXCOORD_0=add_accessor(geom.uv, g.VEC2),
    )
    indices = add_accessor(np.arange(len(pos), dtype=np.uint32), g.SCALAR, target=g.ELEMENT_ARRAY_BUFFER)
    images, textures = [], []
    for key in ("basecolor", "metallic_roughness", "normal", "specular"):
        view = add_view((textures_dir / f"{key}.png").read_bytes())
        images.append(g.Image(bufferView=view, mimeType="image/png", name=key))
        textures.append(g.Texture(source=len(images) - 1, sampler=0))
    material = g.Material(
        name="TangoMaterial",
        pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorTexture=g.TextureInfo(index=0),
            metallicRoughnessTexture=g.TextureInfo(index=1),
            metallicFactor=1.0,  # the texture's blue channel (0) is the metalness
            roughnessFactor=1.0,
        ),
        normalTexture=g.NormalMaterialTexture(index=2),
        doubleSided=True,
        extensions={
            "KHR_materials_specular": {
                "specularFactor": 1.0,
                "specularColorFactor": [25.0, 25.0, 25.0],
                "specularColorTexture": {"index": 3},
            }
        },
    )
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="tango-stylize", extras={ORIGIN_METADATA_KEY: origin}),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[g.Node(mesh=0, name=name)],
        meshes=[g.Mesh(name=name, primitives=[g.Primitive(attributes=attrs, indices=indices, material=0)])],
        materials=[material],
        textures=textures,
        images=images,
        samplers=[
            g.Sampler(
                magFilter=g.LINEAR,
                minFilter=g.LINEAR_MIPMAP_LINEAR,
                wrapS=g.CLAMP_TO_EDGE,
                wrapT=g.CLAMP_TO_EDGE,
            )
        ],
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=sum(len(b) for b in blobs))],
        extensionsUsed=["KHR_materials_specular"],
    )
    gltf.set_binary_blob(b"".join(blobs))
    with atomic_path(path) as tmp:
        gltf.save_binary(str(tmp))


# -------------------------------------------------------------------------------------- the run
def run(
    mesh_path: Path,
    transform_path: Path,
    bake_dir: Path,
    preview: Path,
    out_dir: Path,
    settings: ExportSettings,
    name: str = "model",
) -> dict:
    """Write the asset pack of one grid cell into ``out_dir``."""
    timer = Timer()
    bake_dir, out_dir = Path(bake_dir), Path(out_dir)
    needed = [mesh_path, transform_path, bake_dir / "atlas.npz", bake_dir / "light.exr", preview]
    needed += [bake_dir / f for f in TEXTURE_FILES.values()]
    for p in needed:
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the bake stage first.")
    origin = read_origin(bake_dir / "meta.json")
    mesh = load_ply(mesh_path)
    with np.load(bake_dir / "atlas.npz") as z:
        atlas = {k: z[k] for k in z.files}
    tf = Similarity.from_json(json.loads(Path(transform_path).read_text()))
    geom = faceted(mesh, atlas, tf if settings.units == "original" else None)
    with staged_outputs(out_dir) as staging:
        with timer("copy"):
            for rel in TEXTURE_FILES.values():
                (staging / "textures").mkdir(exist_ok=True)
                with atomic_path(staging / rel) as tmp:
                    shutil.copyfile(bake_dir / rel, tmp)
            for fname in ("light.exr", "light.hdr"):
                with atomic_path(staging / fname) as tmp:
                    shutil.copyfile(bake_dir / fname, tmp)
            with atomic_path(staging / "preview.png") as tmp:
                shutil.copyfile(preview, tmp)
        with timer("usd"):
            with atomic_path(staging / "model.usda") as tmp:
                tmp.unlink()
                write_usd(tmp, geom, settings.meters_per_unit, "light.exr", origin)
            package_usdz(staging / "model.usda", staging / "model.usdz", [*TEXTURE_FILES.values(), "light.exr"])
        with timer("gltf"):
            write_glb(staging / "model.glb", geom, staging / "textures", settings.meters_per_unit, name, origin)
        with timer("validate"):
            usd = [validate_usd(staging / "model.usda"), validate_usd(staging / "model.usdz")]
            gltf = validate_glb(staging / "model.glb")
        messages = [f"{r['file']}: {m}" for r in usd for m in r["messages"]]
        for line in messages:
            log.warning("usd-core validation: %s", line)
        if not gltf["ran"]:
            log.warning("the Khronos glTF-Validator did not run: %s; model.glb is unchecked", gltf["reason"])
        else:
            for line in gltf["messages"]:
                log.warning("glTF validation: %s", line)
        if any(r["errors"] for r in usd) or gltf.get("errors"):
            raise RuntimeError("asset validation failed:\n" + "\n".join(messages + gltf.get("messages", [])))
        from PIL import Image

        with Image.open(staging / TEXTURE_FILES["basecolor"]) as img:
            texture_size = int(img.size[0])
        stats = {
            "faces": len(mesh.faces),
            "vertices_exported": len(geom.positions),
            "texture_size": texture_size,
            "usd_validation": usd,
            "usd_validators": usd[0]["validators"],
            "usd_validation_errors": sum(r["errors"] for r in usd),
            "usd_validation_warnings": sum(r["warnings"] for r in usd),
            "gltf_validation": gltf,
            "gltf_validation_errors": gltf.get("errors"),
            "gltf_validation_warnings": gltf.get("warnings"),
            "bounds": [geom.positions.min(0).tolist(), geom.positions.max(0).tolist()],
        }
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="export",
                settings=settings.to_dict(),
                inputs={"mesh": mesh_path, "transform": transform_path, "bake": bake_dir},
                outputs={k: out_dir / k for k in ("model.usda", "model.usdz", "model.glb")},
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, ORIGIN_KEY: origin},
            ),
        )
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.export", description=__doc__.split("\n")[0])
    parser.add_argument("--mesh", required=True, type=Path)
    parser.add_argument("--transform", required=True, type=Path)
    parser.add_argument("--bake-dir", required=True, type=Path)
    parser.add_argument("--preview", required=True, type=Path, help="preview image to ship (PNG)")
    parser.add_argument("--out-dir", required=True, type=Path)
    parser.add_argument("--name", default="model")
    parser.add_argument("--settings", default="{}")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    with stage_errors("export") as status:
        run(
            args.mesh,
            args.transform,
            args.bake_dir,
            args.preview,
            args.out_dir,
            ExportSettings.from_json(args.settings),
            args.name,
        )
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
