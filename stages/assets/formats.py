"""Asset file formats: indexed geometry, USD (``model.usda`` + packaged ``model.usdz``) and binary
glTF 2.0 (``model.glb``) writers, and their validators (usd-core's, the Khronos glTF-Validator).

Geometry (:class:`ExportMesh`) carries the bake's frame (:class:`~stages.geometry.tangents.CornerFrames`):
the shading normals the field was trained with (flat, as TANGO shades, or smooth) and MikkTSpace
tangents, so viewers rebuild the frame the normal map was baked in. Vertices are shared wherever
position, normal, UV and tangent agree and split only at UV seams, creases (every edge, for flat
normals) and handedness changes; a viewer or Blender computing its own MikkTSpace on them welds
the same corners and gets the same frame. It is
returned to the input's units and position through the normalisation's inverse transform (the
rotation that made the input's up axis +Y is kept, so ``upAxis`` is Y), or left in the
normalised frame (``units: normalized``).

Material mapping:

* **USD** ``UsdPreviewSurface`` with ``useSpecularWorkflow = 1``: ``diffuseColor`` = the baked
  albedo, ``specularColor`` = TANGO's specular colour (F0), ``roughness`` = TANGO's roughness
  (both use ``alpha = roughness^2``), ``normal`` = the tangent-space normal map (scale 2, bias -1).
  A ``DomeLight`` carries the learned SG light as an equirectangular EXR (latlong).
* **glTF** metallic-roughness with ``metallic = 0``: ``baseColor`` = albedo, roughness in the green
  channel of ``metallicRoughnessTexture`` (and, where the bake wrote one, the ambient occlusion in
  its red channel as the ``occlusionTexture``; USD's ``occlusion`` reads the same channel),
  ``normalTexture`` with explicit ``TANGENT`` vectors (the bake's frame), and
  ``KHR_materials_specular`` for the coloured F0: glTF's dielectric F0 is
  ``0.04 * specularColorFactor * specularColorTexture`` (IOR 1.5), so the factor is 25 and the
  texture holds TANGO's F0 (clamped to 1 by glTF). What is lost: glTF makes the diffuse lobe
  give way to the specular one (energy conservation, ``(1 - F)`` weighting) where TANGO simply adds
  them, so a glTF viewer renders slightly darker diffuse at grazing angles; glTF's Fresnel uses
  the half vector per light sample where TANGO evaluates it once at the mirror direction; and the
  environment light is not part of glTF core (it ships beside the model as ``light.exr``/``.hdr``).

A field trained with glTF's own BRDF (``optimize.brdf: gltf``) is written as it was trained, with
nothing lost: glTF metallic-roughness with the baked base colour, roughness (green) and metallic
(blue), no extension; USD's ``UsdPreviewSurface`` in its metallic workflow
(``useSpecularWorkflow = 0``, ``diffuseColor`` = base colour, ``metallic``, ``roughness``). The
bake's ``specular.png`` (its F0, a preview) is then not referenced by either.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config.layout import TEXTURE_FILES
from ..core.errors import StageInputError
from ..core.provenance import ORIGIN_METADATA_KEY, atomic_path
from ..core.safefiles import DATA_LIMIT, IMAGE_LIMIT, open_read, read_bytes, remove
from ..geometry.meshio import TriMesh
from ..geometry.normalization import Similarity

log = logging.getLogger(__name__)
REPO_ROOT = Path(__file__).resolve().parents[2]
#: rotation of the USD DomeLight about +Y that shows our equirectangular light as our renderer sees it
DOME_ROTATE_Y_DEG = -90.0


@dataclass
class ExportMesh:
    """Indexed geometry in export space: per vertex ``positions, normals (V, 3)``, ``uv (V, 2)``
    (glTF convention), ``tangents (V, 4)`` (xyz and the handedness ``w``), and ``indices (F, 3)``.
    A vertex is a distinct combination of all four, so vertices are shared inside UV charts and
    smooth regions and split only at UV seams, creases and handedness changes.

    The input's own topology (a kept UV layout, :mod:`stages.assets.layouts`) comes with
    ``tangents`` None (viewers compute MikkTSpace, the frame the bake used), its material
    ``slots (F,)`` (index into ``slot_names``; each slot its own material, reading the texture set
    in its ``slot_textures`` folder) and ``repeat`` (textures repeat past the unit square, glTF's default sampler,
    rather than clamp at its edges)."""

    positions: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    tangents: np.ndarray | None
    indices: np.ndarray
    slots: np.ndarray | None = None
    slot_names: tuple[str, ...] = ()
    repeat: bool = False
    #: per slot, the folder of its texture set below the textures' folder ("": that folder itself)
    slot_textures: tuple[str, ...] = ()

    def corners(self) -> ExportMesh:
        """The same mesh with every face corner its own vertex (what importers report per loop)."""
        i = self.indices.reshape(-1)
        t = None if self.tangents is None else self.tangents[i]
        return ExportMesh(
            self.positions[i],
            self.normals[i],
            self.uv[i],
            t,
            np.arange(len(i)).reshape(-1, 3),
            self.slots,
            self.slot_names,
            self.repeat,
        )

    def reordered(self, order: np.ndarray) -> ExportMesh:
        """The same mesh with its faces in ``order`` (the order a file with one primitive per slot
        holds them: :meth:`glb_face_order`)."""
        slots = None if self.slots is None else self.slots[order]
        return dataclasses.replace(self, indices=self.indices[order], slots=slots)

    def glb_face_order(self) -> np.ndarray:
        """The faces in the order :func:`write_glb` writes them: slot after slot."""
        return np.concatenate([faces for _, faces in self.slot_faces()])

    def slot_faces(self) -> list[tuple[str, np.ndarray]]:
        """``(material name, face indices)`` per slot in slot order; one unnamed slot without slots."""
        if self.slots is None or len(self.slot_names) <= 1:
            return [(self.slot_names[0] if self.slot_names else "", np.arange(len(self.indices)))]
        return [(name, np.flatnonzero(self.slots == k)) for k, name in enumerate(self.slot_names) if (self.slots == k).any()]

    def texture_folder(self, name: str) -> str:
        """The folder (below the textures' folder) of the texture set of slot ``name``."""
        if name in self.slot_names and self.slot_textures:
            return self.slot_textures[self.slot_names.index(name)]
        return ""

    def texture_files(self) -> list[str]:
        """Every texture set's files, relative to the asset's folder (``textures/...``)."""
        folders = sorted(set(self.slot_textures) | {""})
        return [str(Path("textures", f, Path(rel).name)) for f in folders for rel in TEXTURE_FILES.values()]


#: arrays of the bake's ``atlas.npz``: ``uv (F, 3, 2)`` and the frame (:meth:`CornerFrames.arrays`)
ATLAS_KEYS = ("uv", "normal", "tangent", "handedness", "face_normal")


def read_atlas(path: Path) -> dict[str, np.ndarray]:
    """The bake's ``atlas.npz`` (:data:`ATLAS_KEYS`); an older bake's file (per-face tangents only)
    is refused with what to do."""
    with open_read(path, DATA_LIMIT, remedy="Run the bake stage again.") as fh, np.load(fh) as z:
        atlas = {k: z[k] for k in z.files}
    missing = [k for k in ATLAS_KEYS if k not in atlas]
    if missing or atlas["tangent"].ndim != 3:
        raise StageInputError(
            path,
            f"has no per-corner frame (missing {', '.join(missing) or 'corner tangents'}): written by an older bake",
            "Rerun the bake stage (snakemake --forcerun bake).",
        )
    return atlas


def export_mesh(mesh: TriMesh, atlas: dict, transform: Similarity | None, weld: bool = True) -> ExportMesh:
    """The traced mesh with the bake's UVs and frame (corner normals, MikkTSpace tangents and
    handedness from ``atlas.npz``) in export space (see the module docstring), its corners welded
    where all their attributes are equal (as float32, exactly: what a viewer would share too), or
    with ``weld=False`` every corner its own vertex."""
    kept = "source_face" in atlas  # the input's own layout (bake.uv): its textures repeat
    pos = mesh.vertices[mesh.faces].reshape(-1, 3)
    n = atlas["normal"].reshape(-1, 3)
    t = atlas["tangent"].reshape(-1, 3)
    w = np.repeat(atlas["handedness"], 3)
    if transform is not None:
        # x' = R x_original = x_normalized / scale + R c: original units and position, +Y up
        pos = pos / transform.scale + transform.rotation @ transform.centroid
    corner = np.concatenate([pos, n, atlas["uv"].reshape(-1, 2), t, w[:, None]], axis=1).astype(np.float32)
    if not weld:
        c = corner
        return ExportMesh(
            c[:, 0:3].copy(), c[:, 3:6].copy(), c[:, 6:8].copy(), c[:, 8:12].copy(), np.arange(len(c)).reshape(-1, 3), repeat=kept
        )
    _, first, inverse = np.unique(corner, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # vertices in the order faces first use them
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    v = corner[first[order]]
    return ExportMesh(
        np.ascontiguousarray(v[:, 0:3]),
        np.ascontiguousarray(v[:, 3:6]),
        np.ascontiguousarray(v[:, 6:8]),
        np.ascontiguousarray(v[:, 8:12]),
        rank[inverse.reshape(-1)].reshape(-1, 3).astype(np.int64),
        repeat=kept,
    )


# ------------------------------------------------------------------------------------------ USD
@dataclass
class Level:
    """One level of detail of an asset: its ``geom``, the folder of its four textures (relative to
    the written file for USD, any path for glTF) and its variant/node ``name``."""

    name: str
    geom: ExportMesh
    textures: str


def write_usd(
    path: Path,
    geom: ExportMesh | list[Level],
    meters_per_unit: float,
    light_file: str | None,
    origin: dict,
    extra_data: dict | None = None,
    brdf: str = "tango",
    occlusion: bool = False,
) -> None:
    """Write ``model.usda``: a Mesh with ``st`` and normals, a UsdPreviewSurface bound to it, and
    a DomeLight with the learned light. Texture paths are relative to the file. ``origin`` (the
    guidance and weights that made the material) goes into the root layer's ``customLayerData``
    under ``tango_stylize`` (beside ``extra_data``) and its label into the layer's documentation.

    With a list of :class:`Level` (levels of detail, finest first) the mesh and its material live
    in the variants of a variant set ``LOD`` on ``/Asset`` (one variant per level, named after it,
    the first selected), so a user or a renderer switches levels by the variant selection."""
    from pxr import Usd, UsdGeom

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


def _usd_model(stage, geom: ExportMesh, textures: str, brdf: str = "tango", occlusion: bool = False) -> None:
    """``/Asset/Geometry/Mesh`` and its material ``/Asset/Looks/TangoMaterial`` reading the
    textures from the folder ``textures`` (relative to the layer): TANGO's specular workflow, or
    for glTF's BRDF the metallic workflow (base colour, metallic, roughness); with ``occlusion``
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


def _usd_material(stage, path: str, textures: str, brdf: str, occlusion: bool, repeat: bool):
    """A UsdPreviewSurface material at ``path`` reading the texture set in ``textures`` (module
    docstring), its textures repeating (``repeat``) or clamped at the edges."""
    from pxr import Gf, Sdf, UsdShade

    wrap = "repeat" if repeat else "clamp"
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0 if brdf == "gltf" else 1)
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
    if brdf == "gltf":
        rough.CreateOutput("b", Sdf.ValueTypeNames.Float)
        surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).ConnectToSource(rough.ConnectableAPI(), "b")
    else:
        spec = texture("SpecularTexture", "specular", "sRGB")
        spec.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        surf.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(spec.ConnectableAPI(), "rgb")
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
    (``"name: message"`` of every error and warning)}``. Nothing here is a constant: a stage whose
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
        "messages": [f"{e.GetName()}: {e.GetMessage()}" for e in issues if e.GetType() in (kinds.Error, kinds.Warn)],
    }


def write_model_files(
    folder: Path,
    geom: ExportMesh,
    meters_per_unit: float,
    usdz_root: str,
    name: str,
    origin: dict,
    timer=None,
    brdf: str = "tango",
    occlusion: bool = False,
    glb_writer=None,
) -> dict:
    """Write one asset's ``model.usda``, ``model.usdz`` and ``model.glb`` into ``folder`` (which
    already holds ``textures/*.png`` and ``light.exr``), each atomically, and validate all three
    (``glb_writer(path)``, where given, writes the GLB instead of :func:`write_glb`):
    returns ``{"usd": [usd-core's report on model.usda, on model.usdz], "gltf": the Khronos
    report}``. Warnings are logged; any validator error raises (the folder is the caller's staging
    folder, so nothing half-checked is committed). ``timer`` (a :class:`~stages.core.provenance.Timer`)
    times the ``usd``, ``gltf`` and ``validate`` parts."""
    from contextlib import nullcontext

    def part(key):
        return timer(key) if timer is not None else nullcontext()

    folder = Path(folder)
    with part("usd"):
        with atomic_path(folder / "model.usda") as tmp:
            remove(tmp)
            write_usd(tmp, geom, meters_per_unit, "light.exr", origin, brdf=brdf, occlusion=occlusion)
        package_usdz(folder / "model.usda", folder / "model.usdz", [*geom.texture_files(), "light.exr"], usdz_root)
    with part("gltf"):
        if glb_writer is not None:
            glb_writer(folder / "model.glb")
        else:
            write_glb(
                folder / "model.glb", geom, folder / "textures", meters_per_unit, name, origin, brdf=brdf, occlusion=occlusion
            )
    with part("validate"):
        usd = [validate_usd(folder / "model.usda"), validate_usd(folder / "model.usdz")]
        gltf = validate_glb(folder / "model.glb")
    check_reports({r["file"]: r for r in usd} | {"model.glb": gltf}, folder)
    return {"usd": usd, "gltf": gltf}


def check_reports(reports: dict[str, dict], where: Path) -> None:
    """Log every validator message of ``reports`` (file -> :func:`validate_usd` or
    :func:`validate_glb` report), one line each, and a warning for a glTF-Validator that did not
    run.

    Raises:
        StageInputError: any report has an error (one line: the file, the count, the first message).
    """
    lines = [f"{where.name}/{name}: {one_line(m)}" for name, r in reports.items() for m in r.get("messages", [])]
    for line in lines:
        log.warning("validation: %s", line)
    for name, r in reports.items():
        if r.get("ran") is False:
            log.warning("the Khronos glTF-Validator did not run: %s; %s is unchecked", r["reason"], name)
    failed = [(name, r) for name, r in reports.items() if r.get("errors")]
    if failed:
        name, r = failed[0]
        first = f", the first: {one_line(r['messages'][0]).rstrip('.')}" if r.get("messages") else ""
        raise StageInputError(
            Path(where) / name,
            f"failed validation with {r['errors']} error(s){first}",
            f"Every message is in the log above ({sum(x['errors'] for _, x in failed)} error(s) in all).",
        )


def one_line(text, limit: int = 300) -> str:
    """``text`` on one line (line breaks and other control characters as spaces), at most ``limit``
    characters: a validator's message quotes the file it read, whatever that holds."""
    flat = " ".join("".join(" " if ord(c) < 32 or 127 <= ord(c) < 160 else c for c in str(text)).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


#: the Khronos glTF-Validator as the repository installs it (``npm ci``; see package.json)
GLTF_VALIDATOR = REPO_ROOT / "node_modules" / "gltf-validator"
#: the report's 3D viewer (model-viewer) as ``npm ci`` installs it
MODEL_VIEWER = REPO_ROOT / "node_modules" / "@google" / "model-viewer" / "dist" / "model-viewer-umd.min.js"


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
            "messages": [one_line(f"{m['code']} at {m.get('pointer', '')}: {m['message']}") for m in found],
        }
    except (ValueError, KeyError, TypeError) as exc:
        raise StageInputError(
            path, f"the Khronos glTF-Validator's report cannot be read ({type(exc).__name__})", remedy
        ) from None


# ----------------------------------------------------------------------------------------- glTF
def write_glb(
    path: Path,
    geom: ExportMesh,
    textures_dir: Path,
    meters_per_unit: float,
    name: str,
    origin: dict,
    lods: list[tuple[ExportMesh, Path]] = (),
    screen_coverage: list[float] | None = None,
    brdf: str = "tango",
    occlusion: bool = False,
) -> None:
    """Write a self-contained binary glTF 2.0 file (see the module docstring for the mapping);
    ``origin`` goes into ``asset.extras.tango_stylize``. With ``occlusion`` the material's
    ``occlusionTexture`` is the metallic-roughness texture (its red channel, glTF's packing).

    ``lods`` (coarser levels, each geometry with its textures' folder) makes the file an
    ``MSFT_lod`` asset: the scene's node holds the finest level and lists one node per coarser
    level (outside the scene) in ``extensions.MSFT_lod.ids``, each with its own mesh and material,
    and ``extras.MSFT_screencoverage`` (one threshold per level, finest first) says when to switch.
    A viewer without the extension shows the finest level."""
    import pygltflib as g

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
    used = [] if brdf == "gltf" else ["KHR_materials_specular"]
    if lods:
        if screen_coverage is None or len(screen_coverage) != len(lods) + 1:
            raise ValueError(f"MSFT_lod needs one screen coverage per level ({len(lods) + 1}), got {screen_coverage}")
        nodes[0].extensions = {"MSFT_lod": {"ids": list(range(1, len(nodes)))}}
        nodes[0].extras = {"MSFT_screencoverage": [float(c) for c in screen_coverage]}
        used.append("MSFT_lod")
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="tango-stylize", extras={ORIGIN_METADATA_KEY: origin}),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
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
    gltf.set_binary_blob(b"".join(buffer.blobs))
    with atomic_path(path) as tmp:
        gltf.save_binary(str(tmp))


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

    def texture_set(self, folder: Path, brdf: str, tag: str = "", sampler: int = 0) -> int:
        """Add the bake's textures in ``folder`` (base colour, metallic-roughness, normal, and for
        TANGO's BRDF the specular colour) as images and textures; returns the first's index."""
        g = self.g
        first = len(self.textures)
        keys = ("basecolor", "metallic_roughness", "normal") + (() if brdf == "gltf" else ("specular",))
        for key in keys:
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


def glb_material(g, name: str, first: int, brdf: str, occlusion: bool):
    """A level's material: its textures from index ``first`` (base colour, metallic-roughness,
    normal, and TANGO's specular colour through ``KHR_materials_specular``), the occlusion in the
    metallic-roughness texture's red channel when baked."""
    specular = {
        "KHR_materials_specular": {
            "specularFactor": 1.0,
            "specularColorFactor": [25.0, 25.0, 25.0],
            "specularColorTexture": {"index": first + 3},
        }
    }
    return g.Material(
        name=name,
        pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorTexture=g.TextureInfo(index=first),
            metallicRoughnessTexture=g.TextureInfo(index=first + 1),
            metallicFactor=1.0,  # the texture's blue channel is the metalness (0 for TANGO's BRDF)
            roughnessFactor=1.0,
        ),
        normalTexture=g.NormalMaterialTexture(index=first + 2),
        occlusionTexture=g.OcclusionTextureInfo(index=first + 1) if occlusion else None,
        doubleSided=True,
        extensions={} if brdf == "gltf" else specular,
    )
