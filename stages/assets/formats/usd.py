"""USD: ``model.usda`` and ``model.usdz`` (the layer packaged with its textures and light), and
usd-core's validators.

``UsdPreviewSurface`` in the workflow of the asset's BRDF (its row's ``usd_specular_workflow``,
:mod:`stages.config.brdfs`). TANGO's BRDF: ``useSpecularWorkflow = 1``, ``diffuseColor`` = the
baked albedo, ``specularColor`` = TANGO's specular colour (F0), ``roughness`` = TANGO's roughness
(both use ``alpha = roughness^2``), ``normal`` = the tangent-space normal map (scale 2, bias -1).
glTF's BRDF: the metallic workflow (``useSpecularWorkflow = 0``, ``diffuseColor`` = base colour,
``metallic``, ``roughness``), as trained, nothing lost; the bake's ``specular.png`` (its F0, a
preview) is then not referenced. Where the bake wrote an ambient occlusion map, ``occlusion``
reads the metallic-roughness texture's red channel. A ``DomeLight`` carries the learned light's
environment (its SG lobes) as an equirectangular EXR (latlong), and a ``DistantLight`` each learned
sun (its angle the disc's diameter, normalised: its intensity is the illuminance). The levels of
detail go into one layer as the variants of a variant set ``LOD`` (:meth:`UsdFormat.write_levels`).
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np

from ...config.brdfs import BrdfSpec, brdf_spec
from ...config.layout import EXPORT_FORMATS, LEVELS_STEM, TEXTURE_FILES
from ...core.provenance import ORIGIN_METADATA_KEY, atomic_path
from ...core.safefiles import remove
from ...render.distant import DistantLight
from .base import AssetInfo, Exporter, facing_rotation
from .mesh import ExportMesh, Level

#: rotation of the USD DomeLight about +Y that shows our equirectangular light as our renderer sees it
DOME_ROTATE_Y_DEG = -90.0


class UsdFormat(Exporter):
    """USD: the layer as text (``model.usda``) and packaged with its textures and light
    (``model.usdz``, its root layer as ``export.usdz_root`` says), both judged by every validator
    usd-core registers."""

    def write(self, folder: Path, geom: ExportMesh, asset: AssetInfo) -> None:
        usda, usdz = (Path(folder) / name for name in self.files().values())
        with atomic_path(usda) as tmp:
            remove(tmp)
            write_usd(
                tmp,
                geom,
                asset.meters_per_unit,
                asset.light,
                asset.origin,
                brdf=asset.brdf,
                occlusion=asset.occlusion,
                lights=asset.lights,
            )
        package_usdz(usda, usdz, [*geom.texture_files(), asset.light], asset.settings.usdz_root)

    def write_levels(self, folder: Path, levels: list[Level], asset: AssetInfo, coverage: list[float]) -> None:
        """Every level as a variant of the variant set ``LOD`` (the first selected), the levels and
        their screen coverage in the layer's ``customLayerData``."""
        usda, usdz = (Path(folder) / name for name in self.files(LEVELS_STEM).values())
        switch = {"tango_stylize_lod": {"levels": [lv.name for lv in levels], "msft_screencoverage": coverage}}
        with atomic_path(usda) as tmp:
            remove(tmp)
            write_usd(
                tmp,
                levels,
                asset.meters_per_unit,
                asset.light,
                asset.origin,
                switch,
                brdf=asset.brdf,
                occlusion=asset.occlusion,
                lights=asset.lights,
            )
        files = [f"{lv.textures}/{key}.png" for lv in levels for key in TEXTURE_FILES] + [asset.light]
        package_usdz(usda, usdz, files, asset.settings.usdz_root)

    def validate(self, folder: Path, stem: str = "model") -> dict[str, dict]:
        return {name: validate_usd(Path(folder) / name) for name in self.files(stem).values()}

    def record(self, reports: dict[str, dict]) -> dict:
        """The validators that ran (on the first file) and the errors and warnings of both files."""
        own = [reports[name] for name in self.files().values()]
        return {
            "usd_validators": own[0]["validators"],
            "usd_validation_errors": sum(r["errors"] for r in own),
            "usd_validation_warnings": sum(r["warnings"] for r in own),
        }


def write_usd(
    path: Path,
    geom: ExportMesh | list[Level],
    meters_per_unit: float,
    light_file: str | None,
    origin: dict,
    extra_data: dict | None = None,
    brdf: BrdfSpec | str = "tango",
    occlusion: bool = False,
    lights: tuple[DistantLight, ...] = (),
) -> None:
    """Write ``model.usda``: a Mesh with ``st`` and normals, a UsdPreviewSurface bound to it, a
    DomeLight with the learned light's environment and a DistantLight per learned sun
    (``lights``: :func:`_usd_distant_lights`). Texture paths are relative to the file. ``origin`` (the
    guidance and weights that made the material) goes into the root layer's ``customLayerData``
    under ``tango_stylize`` (beside ``extra_data``) and its label into the layer's documentation.

    With a list of :class:`Level` (levels of detail, finest first) the mesh and its material live
    in the variants of a variant set ``LOD`` on ``/Asset`` (one variant per level, named after it,
    the first selected), so a user or a renderer switches levels by the variant selection."""
    from pxr import Usd, UsdGeom

    brdf = brdf_spec(brdf)
    stage = Usd.Stage.CreateNew(str(path))
    layer = stage.GetRootLayer()
    layer.documentation = f"tango-stylize asset. {origin['label']}"
    data = {ORIGIN_METADATA_KEY: {k: v for k, v in origin.items() if v is not None}}
    layer.customLayerData = {**data, **_usd_dictionary(extra_data or {})}
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    root = UsdGeom.Xform.Define(stage, "/Asset")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind("component")
    if isinstance(geom, ExportMesh):
        _usd_model(stage, geom, "textures", brdf, occlusion)
    else:
        variants = root.GetPrim().GetVariantSets().AddVariantSet("LOD")
        for level in geom:
            variants.AddVariant(level.name)
            variants.SetVariantSelection(level.name)
            with variants.GetVariantEditContext():
                _usd_model(stage, level.geom, level.textures, brdf, occlusion)
        variants.SetVariantSelection(geom[0].name)
    if light_file:
        _usd_dome_light(stage, light_file)
    _usd_distant_lights(stage, lights)
    stage.GetRootLayer().Save()


def _usd_dictionary(d: dict) -> dict:
    """``d`` with its lists as the typed arrays a USD dictionary holds (strings or doubles)."""
    from pxr import Vt

    def value(v):
        if isinstance(v, dict):
            return _usd_dictionary(v)
        if isinstance(v, list | tuple):
            return Vt.StringArray([str(x) for x in v]) if any(isinstance(x, str) for x in v) else Vt.DoubleArray(list(v))
        return v

    return {k: value(v) for k, v in d.items()}


def _usd_model(stage, geom: ExportMesh, textures: str, brdf: BrdfSpec, occlusion: bool = False) -> None:
    """``/Asset/Geometry/Mesh`` and its material ``/Asset/Looks/TangoMaterial`` reading the
    textures from the folder ``textures`` (relative to the layer) in the workflow of ``brdf``
    (``usd_specular_workflow``): TANGO's specular workflow, or for glTF's BRDF the metallic
    workflow (base colour, metallic, roughness); with ``occlusion``
    the preview surface's ``occlusion`` reads the metallic-roughness texture's red channel."""
    from pxr import Gf, Sdf, Tf, UsdGeom, UsdShade, Vt

    # typed parents: importers (Blender's among them) drop an untyped prim from the transform
    # hierarchy, and the up-axis correction applied at /Asset with it
    UsdGeom.Xform.Define(stage, "/Asset/Geometry")
    UsdGeom.Scope.Define(stage, "/Asset/Looks")
    mesh = UsdGeom.Mesh.Define(stage, "/Asset/Geometry/Mesh")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(geom.positions))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(geom.indices), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(geom.indices.reshape(-1).astype(np.int32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(geom.normals))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateDoubleSidedAttr(True)
    lo, hi = geom.positions.min(0), geom.positions.max(0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    st = np.stack([geom.uv[:, 0], 1.0 - geom.uv[:, 1]], axis=1).astype(np.float32)
    pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    pv.Set(Vt.Vec2fArray.FromNumpy(st))

    slots = geom.slot_faces()
    taken: set[str] = set()
    for name, faces in slots:
        prim_name = Tf.MakeValidIdentifier(name) if name else "TangoMaterial"
        while prim_name in taken:  # two names that make the same identifier
            prim_name += "_"
        taken.add(prim_name)
        folder = geom.texture_folder(name)
        looks = f"{textures}/{folder}" if folder else textures
        mat = _usd_material(stage, f"/Asset/Looks/{prim_name}", looks, brdf, occlusion, geom.repeat)
        if name and prim_name != name:
            mat.GetPrim().SetDisplayName(name)
        if len(slots) == 1:
            UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
            continue
        subset = UsdGeom.Subset.Define(stage, f"/Asset/Geometry/Mesh/{prim_name}")
        subset.CreateElementTypeAttr(UsdGeom.Tokens.face)
        subset.CreateFamilyNameAttr(UsdShade.Tokens.materialBind)
        subset.CreateIndicesAttr(Vt.IntArray.FromNumpy(faces.astype(np.int32)))
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(mat)
    if len(slots) > 1:
        UsdGeom.Subset.SetFamilyType(mesh, UsdShade.Tokens.materialBind, UsdGeom.Tokens.partition)


def _usd_material(stage, path: str, textures: str, brdf: BrdfSpec, occlusion: bool, repeat: bool):
    """A UsdPreviewSurface material at ``path`` reading the texture set in ``textures`` (module
    docstring), its textures repeating (``repeat``) or clamped at the edges."""
    from pxr import Gf, Sdf, UsdShade

    wrap = "repeat" if repeat else "clamp"
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(brdf.usd_specular_workflow)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, f"{path}/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    varname = mat.CreateInput("frame:stPrimvarName", Sdf.ValueTypeNames.String)
    varname.Set("st")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).ConnectToSource(varname)

    def texture(name: str, key: str, color_space: str, scale=None, bias=None):
        tex = UsdShade.Shader.Define(stage, f"{path}/{name}")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(f"{textures}/{key}.png")
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(wrap)
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(wrap)
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        if scale is not None:
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
            tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
        return tex

    base = texture("BaseColorTexture", "basecolor", "sRGB")
    base.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(base.ConnectableAPI(), "rgb")
    rough = texture("RoughnessTexture", "metallic_roughness", "raw")
    rough.CreateOutput("g", Sdf.ValueTypeNames.Float)
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(rough.ConnectableAPI(), "g")
    if occlusion:
        rough.CreateOutput("r", Sdf.ValueTypeNames.Float)
        surf.CreateInput("occlusion", Sdf.ValueTypeNames.Float).ConnectToSource(rough.ConnectableAPI(), "r")
    if brdf.usd_specular_workflow:
        spec = texture("SpecularTexture", "specular", "sRGB")
        spec.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        surf.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(spec.ConnectableAPI(), "rgb")
    else:
        rough.CreateOutput("b", Sdf.ValueTypeNames.Float)
        surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).ConnectToSource(rough.ConnectableAPI(), "b")
    nrm = texture("NormalTexture", "normal", "raw", (2.0, 2.0, 2.0, 1.0), (-1.0, -1.0, -1.0, 0.0))
    nrm.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(nrm.ConnectableAPI(), "rgb")
    return mat


def _usd_dome_light(stage, light_file: str) -> None:
    from pxr import UsdGeom, UsdLux

    UsdGeom.Xform.Define(stage, "/Asset/Lights")
    dome = UsdLux.DomeLight.Define(stage, "/Asset/Lights/LearnedLight")
    # OpenEXR's latlong (USD's dome convention) puts longitude 0 at +z and pi/2 at +x, with
    # u = (pi - longitude) / 2 pi; our maps put u = azimuth / 2 pi at (cos a, 0, sin a): a
    # quarter turn apart (DOME_ROTATE_Y_DEG; Blender's importer checks it in the tests)
    UsdGeom.Xformable(dome.GetPrim()).AddRotateYOp().Set(DOME_ROTATE_Y_DEG)
    dome.CreateTextureFileAttr().Set(light_file)
    dome.CreateTextureFormatAttr().Set(UsdLux.Tokens.latlong)
    dome.CreateIntensityAttr().Set(1.0)


def _usd_distant_lights(stage, lights: tuple[DistantLight, ...]) -> None:
    """One ``DistantLight`` per learned sun under ``/Asset/Lights``, as UsdLux defines it: oriented
    to shine along ``-direction`` (:func:`~stages.assets.formats.base.facing_rotation`),
    ``inputs:angle`` the disc's angular diameter in degrees, ``inputs:normalize`` on so that
    ``inputs:intensity`` (the irradiance's largest channel) is the illuminance of a surface facing
    it, and ``inputs:color`` the irradiance over that channel."""
    from pxr import Gf, UsdGeom, UsdLux

    if not lights:
        return
    UsdGeom.Xform.Define(stage, "/Asset/Lights")
    for k, light in enumerate(lights):
        sun = UsdLux.DistantLight.Define(stage, f"/Asset/Lights/Sun{k}")
        x, y, z, w = facing_rotation(light.direction)
        UsdGeom.Xformable(sun.GetPrim()).AddOrientOp().Set(Gf.Quatf(w, x, y, z))
        e = np.asarray(light.irradiance, np.float64)
        peak = float(e.max()) if e.size and e.max() > 0 else 0.0
        sun.CreateAngleAttr().Set(2.0 * math.degrees(light.radius))
        sun.CreateNormalizeAttr().Set(True)
        sun.CreateIntensityAttr().Set(peak)
        sun.CreateColorAttr().Set(Gf.Vec3f(*((e / peak).tolist() if peak > 0 else [1.0, 1.0, 1.0])))


def package_usdz(usda: Path, usdz: Path, files: list[str], root: str = "usdc") -> None:
    """Package ``usda`` (first, as the root layer: converted to USD's binary crate format,
    ``<stem>.usdc``, as usdz files usually carry it, or with ``root="usda"`` as the text itself)
    and ``files`` (paths relative to it, stored under the same relative paths) into ``usdz``,
    atomically, with usd-core's zip writer (which aligns entries as the usdz format requires)."""
    import tempfile

    from pxr import Sdf

    with atomic_path(usdz) as tmp, tempfile.TemporaryDirectory() as d:
        remove(tmp)
        crate = usda
        if root == "usdc":
            crate = Path(d) / f"{usda.stem}.usdc"
            if not Sdf.Layer.FindOrOpen(str(usda)).Export(str(crate)):
                raise RuntimeError(f"usd-core could not write {usda} as a binary crate layer")
        writer = Sdf.ZipFileWriter.CreateNew(str(tmp))
        writer.AddFile(str(crate), crate.name)
        for rel in files:
            writer.AddFile(str(usda.parent / rel), rel)
        writer.Save()


def validate_usd(path: Path) -> dict:
    """Run every validator usd-core registers on ``path`` and count what they report.

    Returns ``{"file", "validators" (how many ran), "validator_names" (sorted), "validator_digest"
    (SHA-256 of the names, one per line), "errors", "warnings", "infos" (counts), "messages"
    (``"name: message"`` of every error, then every warning, each sorted)}``. Nothing here is a constant: a stage whose
    validators report errors fails, and the counts say what ran.
    """
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
        # errors first, each kind sorted: usd-core's validators run in parallel, so the order they
        # report in varies from run to run
        "messages": [
            m
            for kind in (kinds.Error, kinds.Warn)
            for m in sorted(f"{e.GetName()}: {e.GetMessage()}" for e in issues if e.GetType() == kind)
        ],
    }


#: USD's format object (its row: ``EXPORT_FORMATS["usd"]``)
USD = UsdFormat(EXPORT_FORMATS["usd"])
