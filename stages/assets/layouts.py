"""Which UV layout a bake writes into (``bake.uv``): the input's own, or a new xatlas atlas.

``keep`` bakes into the input's own layout and stops with one line saying what is wrong when it
is not usable; ``auto`` (the default) keeps it where it is usable and otherwise unwraps a new
atlas, with the reason logged and recorded; ``atlas`` always unwraps. Usable is measured
(:mod:`stages.geometry.uvlayout`): every face mapped, no degenerate UV triangle, overlap within
``bake.uv_max_overlap`` (stacked copies of an island excepted, and baked once), every face in one
UV tile. The layout must also be the traced mesh's: an input format that holds one (OBJ, glTF),
and the traced faces the input's own (a decimated mesh's are not; its asset is unwrapped anew).

A mesh with several material slots keeps them: all slots share the one texture set, which is
sound because the overlap check covers every face, across slots too; the record lists the slots.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.safefiles import read_json_record
from ..geometry.meshio import BUILTIN_PREFIX, TriMesh
from ..geometry.normalization import Similarity
from ..geometry.normals import unit_face_normals
from ..geometry.sourcemesh import LAYOUT_SUFFIXES, SourceMesh, read_source
from ..geometry.tangents import CornerFrames, mikktspace
from ..geometry.uvlayout import LayoutCheck, check_layout, match_faces

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InputMesh:
    """The input a traced mesh was normalised from: its ``path`` (a file or ``builtin:<name>``;
    None: unknown) and the normalisation's ``transform.json``."""

    path: str | None
    transform_path: Path | None

    def transform(self) -> Similarity | None:
        if self.path is None or self.transform_path is None:
            return None
        return Similarity.from_json(read_json_record(self.transform_path))


@dataclass(frozen=True)
class KeptLayout:
    """The input's own layout on the traced mesh: the ``source`` surface, ``source_face (F,)`` (the
    input triangle each traced face is), ``uv (F, 3, 2)`` per traced face, the corner normals and
    tangents in the traced (normalised) frame and the ``check`` that found it usable."""

    source: SourceMesh
    source_face: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray | None
    check: LayoutCheck

    def frames(self, mesh: TriMesh) -> CornerFrames:
        """The normal-map frame a viewer rebuilds from the input's own data: its normals and its
        tangents (glTF ``TANGENT``), or MikkTSpace on its normals and UVs where it has none."""
        st = np.stack([self.uv[..., 0], 1.0 - self.uv[..., 1]], axis=-1)
        t, w = mikktspace(mesh.vertices[mesh.faces], self.normals, st)
        if self.tangents is not None:
            given = np.isfinite(self.tangents).all(-1)  # (F, 3)
            t = np.where(given[..., None], self.tangents[..., :3], t)
            w = np.where(given.all(1), np.sign(self.tangents[:, 0, 3]) + (self.tangents[:, 0, 3] == 0), w)
        return CornerFrames(self.normals, t, w, unit_face_normals(mesh.vertices, mesh.faces))


@dataclass(frozen=True)
class UvChoice:
    """The layout a bake used: ``kept`` (the input's) or not, ``why``, and what was measured."""

    setting: str
    kept: bool
    why: str
    check: LayoutCheck | None = None
    slots: tuple[str, ...] = ()

    def record(self) -> dict:
        out = {"setting": self.setting, "layout": "kept" if self.kept else "atlas", "why": self.why}
        if self.check is not None:
            out["check"] = self.check.to_json()
        if self.slots:
            out["slots"] = list(self.slots)
            out["texture_sets"] = "one set shared by every slot (no two slots overlap in UV space)"
        return out


def choose_layout(
    setting: str, source: str | None, transform: Similarity | None, mesh: TriMesh, size: int, max_overlap: float
) -> tuple[UvChoice, KeptLayout | None]:
    """Decide ``bake.uv`` (module docstring) for the traced ``mesh`` (normalised by ``transform``)
    of the input ``source`` (a path, ``builtin:<name>`` or None), measuring overlap at ``size``.

    Raises:
        StageInputError: ``keep`` and the layout is not usable (one line: what is wrong).
    """
    if setting == "atlas":
        return UvChoice(setting, False, "bake.uv: atlas"), None
    found = _read_layout(source, transform, mesh, size)
    if isinstance(found, str):
        return _refuse(setting, source, found), None
    layout, slots = found
    problems = layout.check.problems(max_overlap)
    if problems:
        return _refuse(setting, source, "; ".join(problems), layout.check), None
    c = layout.check
    stacked = f", {c.stacked:,} faces stacked copies baked once" if c.stacked else ""
    why = f"usable: {c.islands:,} islands, {c.overlapping:,} of {c.faces:,} faces overlapping{stacked}"
    return UvChoice(setting, True, why, layout.check, slots), layout


def _refuse(setting: str, source: str | None, why: str, check: LayoutCheck | None = None) -> UvChoice:
    if setting == "keep":
        raise StageInputError(
            source or "the mesh", f"bake.uv: keep, but {why}", "Set bake.uv: auto or atlas to bake into a new atlas."
        )
    log.info("bake.uv: auto: a new atlas, because %s", why)
    return UvChoice(setting, False, f"auto: {why}", check)


def _read_layout(source: str | None, transform: Similarity | None, mesh: TriMesh, size: int):
    """``(KeptLayout, slot names)``, or a string saying why the input has no layout to keep."""
    if source is None or transform is None:
        return "no input file was given to read a layout from"
    if source.startswith(BUILTIN_PREFIX):
        return f"{source} has no UV layout"
    if Path(source).suffix.lower() not in LAYOUT_SUFFIXES:
        return f"{Path(source).suffix} input holds no UV layout the tool reads (OBJ, GLB and glTF do)"
    src = read_source(source)
    if not src.mapped.any():
        return "the input has no texture coordinates"
    face = match_faces(transform.forward(src.positions)[src.triangles], mesh)
    if len(src.triangles) != len(mesh.faces) or (face < 0).any():
        return (
            f"the traced mesh's faces are not the input's ({len(mesh.faces):,} traced, {len(src.triangles):,} in the input, "
            f"{int((face < 0).sum()):,} unmatched): a decimated mesh is baked into a new atlas"
        )
    order = np.empty_like(face)
    order[face] = np.arange(len(face))  # traced face -> input triangle
    tri = src.triangles[order]
    check = check_layout(src.positions, src.triangles, src.corner_uv, size)
    normals = src.corner_normals()[order] @ transform.rotation.T  # the similarity's rotation only
    tangents = None
    if src.tangents is not None:
        t = src.tangents[tri]
        tangents = np.concatenate([t[..., :3] @ transform.rotation.T, t[..., 3:]], axis=-1)
    layout = KeptLayout(src, order, src.uv[tri], normals, tangents, check)
    return layout, src.slot_names


def kept_source(bake_stats: dict, atlas: dict, source: str | None, bake_dir: Path) -> SourceMesh | None:
    """The input's own surface where the bake (``bake_stats``, its ``atlas.npz`` arrays) kept its
    layout, read again from ``source`` and checked to be the one baked; None for an atlas.

    Raises:
        StageInputError: no ``source`` given, or one whose faces or UVs are not the bake's.
    """
    if bake_stats.get("uv", {}).get("layout") != "kept":
        return None
    if source is None:
        raise StageInputError(
            Path(bake_dir) / "meta.json",
            "the bake kept the input's UV layout, but the input mesh was not given",
            "Pass --source with the input mesh (the workflow does).",
        )
    src = read_source(source)
    face = atlas.get("source_face")
    if face is None or len(face) != len(src.triangles) or not np.allclose(src.corner_uv[face], atlas["uv"], atol=1e-6):
        raise StageInputError(
            source, "is not the mesh whose UV layout the bake kept (its faces or UVs differ)", "Rerun the bake."
        )
    return src
