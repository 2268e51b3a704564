"""The BRDF models (``optimize.brdf``): what the settings know of each model, one row per model,
without torch.

What a model computes (its material channels, its diffuse and specular terms, its table of
directional albedo) is its object in :mod:`stages.render.brdf`, registered under the same name;
everything the settings need to decide about a model, and what its assets hold (the textures they
reference, USD's workflow, glTF's extensions, the MTL lines and how Blender reads them: plain
data the exporters read without torch), is a field of its row here, so that no caller compares
BRDF names (``tests/render/test_brdf_registry.py`` scans the package for such comparisons). The
object reads its row (:attr:`stages.render.brdf.base.Brdf.spec`). A new model is one row of
:data:`BRDFS` and one module of :mod:`stages.render.brdf` named after it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..core.registry import Registry

#: the factor ``KHR_materials_specular``'s colour takes to make glTF's dielectric F0 (``0.04 *
#: specularColorFactor * specularColorTexture``, IOR 1.5) the texture's F0
GLTF_SPECULAR_COLOR_FACTOR = 25.0


@dataclass(frozen=True)
class BrdfSpec:
    """One BRDF model: its name in the config, the parameters its networks predict, which
    settings and specular models apply to it, and what its bake and assets write."""

    #: its name in ``optimize.brdf``
    name: str
    #: the parameters the SVBRDF network's three heads predict, in head order: the colour, the
    #: specular parameter (the one :class:`~stages.model.field.MaterialEdit`'s specular scale
    #: scales) and the roughness
    parameters: tuple[str, str, str]
    #: the specular models it has (``optimize.specular_lobe``), the first the one that stands for
    #: the model where our renderer is measured against a reference (:mod:`stages.reference.limits`)
    lobes: tuple[str, ...]
    #: a field of it may go without its specular heads (``optimize.specular: false``, the paper's
    #: diffuse-only ablation)
    diffuse_only: bool
    #: the ``optimize`` setting that starts the specular head near a value everywhere
    start_setting: str
    #: each parameter's baked texture, named as :func:`stages.assets.baking.decode_textures` names
    #: them: ``albedo`` the base colour texture, ``specular`` the specular colour texture,
    #: ``roughness`` and ``metallic`` the green and blue channels of the metallic-roughness texture
    texture_of: Mapping[str, str]
    #: the bake's textures its assets reference (:data:`stages.config.layout.TEXTURES`), in the
    #: order a GLB's texture set holds them
    exported_textures: tuple[str, ...]
    #: ``UsdPreviewSurface``'s ``useSpecularWorkflow``: 1, the specular colour from
    #: ``specular.png``; 0, the metallic from the metallic-roughness texture's blue channel
    usd_specular_workflow: int
    #: the glTF extensions its material needs (``extensionsUsed``)
    gltf_extensions: tuple[str, ...]
    #: a glTF material's ``extensions``, each texture named by its name in :attr:`exported_textures`
    #: (``{"index": "specular"}``: :meth:`gltf_material_extensions` makes it the set's index)
    gltf_material: Mapping[str, Any]
    #: an OBJ material's lines for its specular parameter, ``{folder}`` the textures' folder
    #: (:meth:`mtl_lines`)
    mtl: tuple[str, ...]
    #: the Principled BSDF inputs its specular parameter arrives in when Blender imports its
    #: assets: input -> (texture, colour space, channel or None)
    #: (:func:`stages.reference.blender.check_import`)
    blender_wiring: Mapping[str, tuple[str, str, str | None]]
    #: the ``optimize`` settings that only this model reads, each with what it sets (a setting of
    #: another model's is refused: :func:`stray_settings`)
    settings: Mapping[str, str] = field(default_factory=dict)

    @property
    def model_lobe(self) -> str:
        """The specular model that stands for the BRDF against a reference: its first."""
        return self.lobes[0]

    def gltf_material_extensions(self, first: int, texcoord: int = 0) -> dict[str, Any]:
        """A glTF material's ``extensions`` for the texture set whose first texture is ``first``
        (in :attr:`exported_textures`' order), read through UV set ``texcoord``:
        :attr:`gltf_material` with each texture's name replaced by its index (and, for a set other
        than the first, its ``texCoord`` beside it)."""

        def resolved(value: Any, key: str = "") -> Any:
            if key == "index" and isinstance(value, str):
                return first + self.exported_textures.index(value)
            if isinstance(value, Mapping):
                out = {k: resolved(v, k) for k, v in value.items()}
                return {**out, "texCoord": texcoord} if texcoord and isinstance(value.get("index"), str) else out
            return [resolved(v) for v in value] if isinstance(value, tuple | list) else value

        return resolved(self.gltf_material)

    def mtl_lines(self, folder: str) -> list[str]:
        """An OBJ material's lines for its specular parameter, reading textures from ``folder``."""
        return [line.format(folder=folder) for line in self.mtl]


#: the BRDF models by name, in the order the config's choices list them
BRDFS: Registry[BrdfSpec] = Registry("BRDF")
for _spec in (
    BrdfSpec(
        name="tango",
        parameters=("albedo", "specular", "roughness"),
        lobes=("isotropic", "split_sum", "fitted"),
        diffuse_only=True,
        start_setting="init_specular",
        texture_of={"albedo": "albedo", "specular": "specular", "roughness": "roughness"},
        exported_textures=("basecolor", "metallic_roughness", "normal", "specular"),
        usd_specular_workflow=1,
        gltf_extensions=("KHR_materials_specular",),
        # the specular texture as KHR_materials_specular's colour: glTF's dielectric F0 is
        # 0.04 * specularColorFactor * specularColorTexture, so the factor 25 makes it the
        # texture's F0 (clamped to 1 by glTF)
        gltf_material={
            "KHR_materials_specular": {
                "specularFactor": 1.0,
                "specularColorFactor": (GLTF_SPECULAR_COLOR_FACTOR,) * 3,
                "specularColorTexture": {"index": "specular"},
            }
        },
        mtl=("Pm 0", "Ks 1 1 1", "map_Ks {folder}/specular.png"),  # no metalness; the specular colour
        blender_wiring={"Specular Tint": ("specular", "sRGB", None)},  # the specular texture as the tint
        settings={"init_specular": "TANGO's specular colour"},
    ),
    BrdfSpec(
        name="gltf",
        parameters=("base", "metallic", "roughness"),
        lobes=("fitted", "split_sum"),
        diffuse_only=False,
        start_setting="init_metallic",
        texture_of={"base": "albedo", "metallic": "metallic", "roughness": "roughness"},
        exported_textures=("basecolor", "metallic_roughness", "normal"),
        usd_specular_workflow=0,
        gltf_extensions=(),
        gltf_material={},  # glTF's core material is the model itself
        # metalness from metallic.png (the metallic-roughness texture's blue channel), no specular colour
        mtl=("Pm 1", "Ks 0 0 0", "map_Pm {folder}/metallic.png"),
        blender_wiring={"Metallic": ("metallic_roughness", "Non-Color", "Blue")},  # the blue channel
        settings={"init_metallic": "glTF's metallic", "metallic_binary": "a prior on glTF's metallic"},
    ),
):
    BRDFS.register(_spec.name, _spec)


def brdf_spec(name: str | BrdfSpec) -> BrdfSpec:
    """The row of the BRDF ``name`` (a row is returned as it is); a ValueError naming the choices
    for any other name."""
    if isinstance(name, BrdfSpec):
        return name
    return BRDFS[name]


def stray_settings(name: str, values: Mapping[str, object], defaults: Mapping[str, object], label: str = "") -> list[str]:
    """The problems of settings that another BRDF than ``name`` reads, set away from their
    ``defaults`` in ``values`` (both by key; keys absent from ``values`` are not checked), one line
    each, as ``optimize.<key> is <what>, which brdf <name> does not have: ...`` (``label``: how the
    line names the BRDF, ``brdf <name>`` where empty)."""
    label = label or f"brdf {name}"
    problems = []
    for owner in BRDFS.values():
        if owner.name == name:
            continue
        for key, what in owner.settings.items():
            if key in values and values[key] != defaults[key]:
                problems.append(f"optimize.{key} is {what}, which {label} does not have: remove it, or set brdf: {owner.name}")
    return problems
