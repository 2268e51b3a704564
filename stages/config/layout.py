"""File names the stages write and the rules declare: the contract between the two, importable
without torch (the workflow builds its outputs from it)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from ..core.registry import Registry

#: the images the optimize stage renders from every evaluation view (``renders/<kind>.png``)
RENDER_KINDS = ("rgb", "diffuse", "specular", "roughness", "normal", "normal_original")

#: the optimize stage's outputs (besides ``meta.json``), relative to its folder
OPTIMIZE_FILES = {
    "field": "field.pt",
    "loss_csv": "loss.csv",
    "loss_png": "loss.png",
    "light": "light.npz",
    **{f"render_{k}": f"renders/{k}.png" for k in (*RENDER_KINDS, "light")},
}

#: the baked texture maps (``textures/<name>.png`` in the bake and export folders)
TEXTURES = ("basecolor", "metallic_roughness", "specular", "normal")
TEXTURE_FILES = {k: f"textures/{k}.png" for k in TEXTURES}


@dataclass(frozen=True)
class ExportFormat:
    """One export format as the workflow and every reader of an asset folder know it: the files its
    writer makes and, as data, what the lod stage, the Blender round trip and the report need to
    know of it. Its writer and validator are its object in :mod:`stages.assets.formats`,
    registered under the same name; a new format is one row of :data:`EXPORT_FORMATS` and one
    module there (CONTRIBUTING.md, *To add an export format*)."""

    #: its name (the registry's key)
    name: str
    #: the files it writes, by suffix (``<stem>.<suffix>``: :meth:`files`), in the order it writes them
    suffixes: tuple[str, ...]
    #: what it holds, in a line (the asset pack's README)
    description: str
    #: it holds every level of detail in one file of each suffix (the lod stage's ``model_lods.*``)
    levels_in_one_file: bool = False
    #: the suffix of its file Blender imports in the round trip (a choice of ``roundtrip.formats``), or None
    blender_import: str | None = None
    #: that file brings its own light into Blender (USD's DomeLight); otherwise the round trip
    #: lights the import with ``light.hdr`` as the world
    carries_light: bool = False
    #: Blender's importer keeps its occlusion texture (the round trip checks the wiring where it does)
    blender_keeps_occlusion: bool = False
    #: its faces arrive in material-slot order (one primitive per slot), not the mesh's
    faces_by_slot: bool = False
    #: the round trip also renders its material's lobes apart (``roundtrip.split_lobes``), which
    #: splits the gap between our BRDF and Blender's
    lobe_split: bool = False
    #: the suffix of its file the report's 3D viewer (model-viewer, which reads glTF) shows, or None
    viewer: str | None = None

    def files(self, stem: str = "model") -> dict[str, str]:
        """Its files' names by suffix: ``{suffix: "<stem>.<suffix>"}``."""
        return {suffix: f"{stem}.{suffix}" for suffix in self.suffixes}


def check_format(new: ExportFormat, formats: Iterable[ExportFormat] = ()) -> ExportFormat:
    """``new``, refused (ValueError) where it names a round-trip or viewer file it does not write,
    or where one of ``formats`` (those registered) already writes a file of its suffixes, feeds
    the viewer or splits the lobes as it does."""
    if {new.blender_import, new.viewer} - {None, *new.suffixes}:
        raise ValueError(f"export format {new.name!r} names a file it does not write")
    for f in formats:
        if set(f.suffixes) & set(new.suffixes):
            raise ValueError(f"export formats {f.name!r} and {new.name!r} both write *.{' *.'.join(f.suffixes)}")
        for what in ("viewer", "lobe_split"):
            if getattr(f, what) and getattr(new, what):
                raise ValueError(f"export formats {f.name!r} and {new.name!r} both have {what}")
    return new


#: the export formats by name, in the order the export writes them (and the round trip's
#: ``formats`` lists its choices); :func:`stages.assets.formats.temporarily` adds one for a block
EXPORT_FORMATS: Registry[ExportFormat] = Registry("export format")
for _format in (
    ExportFormat(
        name="gltf",
        suffixes=("glb",),
        description="binary glTF 2.0, the light beside it as light.hdr; levels of detail by MSFT_lod",
        levels_in_one_file=True,  # MSFT_lod
        blender_import="glb",
        blender_keeps_occlusion=True,
        faces_by_slot=True,
        lobe_split=True,
        viewer="glb",
    ),
    ExportFormat(
        name="usd",
        suffixes=("usda", "usdz"),
        description="USD, as text and packaged with textures and light; levels of detail as the variant set LOD",
        levels_in_one_file=True,  # a variant set LOD
        blender_import="usdz",
        carries_light=True,
    ),
):
    EXPORT_FORMATS.register(_format.name, check_format(_format, EXPORT_FORMATS.values()))


def export_files(stem: str = "model", levels: bool = False) -> dict[str, str]:
    """Every registered export format's files by suffix (``{"glb": "model.glb", ...}``); with
    ``levels``, only those of the formats that hold every level in one file."""
    return {s: name for f in EXPORT_FORMATS.values() if f.levels_in_one_file or not levels for s, name in f.files(stem).items()}


def export_format_of(suffix: str) -> ExportFormat:
    """The export format that writes the file of ``suffix`` (``glb``, ``usdz``, ...); a
    ValueError naming the suffixes for any other."""
    for f in EXPORT_FORMATS.values():
        if suffix in f.suffixes:
            return f
    raise ValueError(f"no export format writes *.{suffix}; the suffixes are {', '.join(export_files())}")


#: the export folder's asset files as the table stands when the workflow reads it (what the
#: export rule declares), by suffix
EXPORT_FILES = export_files()
#: the suffixes of the files the Blender round trip may import (the choices of ``roundtrip.formats``)
BLENDER_IMPORTS = tuple(f.blender_import for f in EXPORT_FORMATS.values() if f.blender_import)
#: the file the report's 3D viewer shows
VIEWER_FILE = next(f.files()[f.viewer] for f in EXPORT_FORMATS.values() if f.viewer)

#: the stem of the lod stage's files that hold every level (``model_lods.<suffix>``)
LEVELS_STEM = "model_lods"
#: the lod stage's outputs (the combined asset in each format that holds levels in one file, the
#: figure and the metadata), relative to its folder
LOD_FILES = {
    **export_files(LEVELS_STEM, levels=True),
    "figure": "levels.png",
    "meta": "meta.json",
}
