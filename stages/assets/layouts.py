"""Which UV layout a bake writes into (``bake.uv``): the input's own, or a new xatlas atlas.

``keep`` bakes into the input's own layout and stops with one line saying what is wrong when it
is not usable; ``auto`` (the default) keeps it where it is usable and otherwise unwraps a new
atlas, with the reason logged and recorded; ``atlas`` always unwraps. Usable is measured
(:mod:`stages.geometry.uvlayout`): every face mapped, no degenerate UV triangle, overlap within
``bake.uv_max_overlap`` (stacked copies of an island excepted, and baked once), every face in one
UV tile. The layout must also be the traced mesh's: an input format that holds one (OBJ, glTF),
and the traced faces the input's own (a decimated mesh's are not; its asset is unwrapped anew).

A mesh with several material slots keeps them, each its own material named after the input's.
Where no two slots' islands overlap (the overlap check over every face, across slots, passes), all
slots share one texture set; where they overlap each other (each material with its own 0-1 space,
common in real assets) but each slot's own layout is usable, every slot gets its own texture set,
in ``textures/<slot>/`` (the first in ``textures/``). The record lists the slots, the sets and why.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.safefiles import read_json
from ..geometry.meshio import BUILTIN_PREFIX, TriMesh
from ..geometry.normalization import Similarity
from ..geometry.normals import unit_face_normals
from ..geometry.sourcemesh import LAYOUT_SUFFIXES, OBJ_SOURCE, SourceMesh, read_source
from ..geometry.tangents import CornerFrames, mikktspace
from ..geometry.uvlayout import LayoutCheck, check_layout, face_tiles, match_faces, udim

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
        return Similarity.from_json(read_json(self.transform_path))


@dataclass(frozen=True)
class TextureSet:
    """One set of baked textures: the input material ``slots`` (indices) and the UDIM ``tile`` it
    serves, and its ``folder`` below ``textures/`` (``""``: ``textures/`` itself)."""

    folder: str
    slots: tuple[int, ...]
    tile: int = 1001


def set_folders(names: tuple[str, ...]) -> list[str]:
    """Folders for one texture set per slot ``names``: the first ``""`` (``textures/`` itself), the
    others the names made file-safe (letters, digits, ``_ . -``) and unique."""
    out, taken = [""], {""}
    for k, name in enumerate(names[1:], 1):
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or f"slot{k}"
        while safe in taken:
            safe += "_"
        taken.add(safe)
        out.append(safe)
    return out


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
    sets: tuple[TextureSet, ...] = (TextureSet("", ()),)

    @property
    def face_set(self) -> np.ndarray:
        """``(F,)``: the texture set of each traced face (its material slot's, in its UDIM tile)."""
        slot = self.source.slot[self.source_face]
        tile = udim(face_tiles(self.uv))
        out = np.zeros(len(slot), np.int64)
        for k, ts in enumerate(self.sets):
            out[np.isin(slot, ts.slots) & (tile == ts.tile)] = k
        return out

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
    """The layout a bake used: ``kept`` (the input's) or not, ``why``, what was measured, the
    input's material ``slots`` and the texture ``sets`` they use (and why so many)."""

    setting: str
    kept: bool
    why: str
    check: LayoutCheck | None = None
    slots: tuple[str, ...] = ()
    sets: tuple[TextureSet, ...] = ()
    sets_why: str = ""

    def record(self) -> dict:
        out = {"setting": self.setting, "layout": "kept" if self.kept else "atlas", "why": self.why}
        if self.check is not None:
            out["check"] = self.check.to_json()
        if self.kept:
            out["slots"] = list(self.slots)
            out["texture_sets"] = [
                {"folder": ts.folder, "slots": [self.slots[i] for i in ts.slots], "tile": ts.tile} for ts in self.sets
            ]
            out["texture_sets_why"] = self.sets_why
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
    c = found.check
    sets, sets_why, problems = _texture_sets(found, size, max_overlap)
    if problems:
        return _refuse(setting, source, "; ".join(problems), c), None
    layout = dataclasses.replace(found, sets=sets)
    stacked = f", {c.stacked:,} faces stacked copies baked once" if c.stacked else ""
    why = f"usable: {c.islands:,} islands{stacked}; {sets_why}"
    return UvChoice(setting, True, why, c, found.source.slot_names, sets, sets_why), layout


def _texture_sets(layout: KeptLayout, size: int, max_overlap: float):
    """``(sets, why, problems)``: one set for every slot where the whole layout is usable; else,
    for several slots each usable alone, one set per slot; else the whole layout's problems. Each
    set is then split by UDIM tile (:func:`_by_tile`)."""
    src = layout.source
    udim_ok = src.kind == OBJ_SOURCE
    slots = tuple(range(len(src.slot_names)))
    problems = layout.check.problems(max_overlap, udim_ok)
    if not problems:
        shared = f"{layout.check.overlapping:,} of {layout.check.faces:,} faces overlapping"
        why = f"{shared}; one texture set shared by every slot" if len(slots) > 1 else f"{shared}; one material"
        return _by_tile((TextureSet("", slots),), src, why)
    if len(slots) == 1:
        return (), "", problems
    alone = []
    for k in slots:
        mine = src.slot == k
        check = check_layout(src.positions, src.triangles[mine], src.corner_uv[mine], size)
        alone += [f"slot {src.slot_names[k]!r}: {p}" for p in check.problems(max_overlap, udim_ok)]
    if alone:
        return (), "", alone
    sets = tuple(TextureSet(folder, (k,)) for k, folder in zip(slots, set_folders(src.slot_names), strict=True))
    why = (
        f"one texture set per slot: the slots overlap each other in UV space ({layout.check.overlapping:,} faces), "
        "each alone does not"
    )
    return _by_tile(sets, src, why)


def _by_tile(groups: tuple[TextureSet, ...], src: SourceMesh, why: str):
    """``groups`` split by the UDIM tiles their faces lie in: one set per group and tile. With
    several tiles the first set stays in ``textures/``; a group's others go into a folder named
    after the tile (``textures/1002/``, ``textures/<slot>/1002/``)."""
    tile = udim(face_tiles(src.corner_uv))
    several = len(np.unique(tile)) > 1
    out = []
    for g in groups:
        for t in sorted(set(tile[np.isin(src.slot, g.slots)].tolist())):
            first = not out
            folder = g.folder if not several or first else "/".join(p for p in (g.folder, str(t)) if p)
            out.append(TextureSet(folder, g.slots, int(t)))
    if several:
        why += f"; one texture set per UDIM tile ({len(np.unique(tile))} tiles)"
    return tuple(out), why, []


def _refuse(setting: str, source: str | None, why: str, check: LayoutCheck | None = None) -> UvChoice:
    if setting == "keep":
        raise StageInputError(
            source or "the mesh", f"bake.uv: keep, but {why}", "Set bake.uv: auto or atlas to bake into a new atlas."
        )
    log.info("bake.uv: auto: a new atlas, because %s", why)
    return UvChoice(setting, False, f"auto: {why}", check)


def _read_layout(source: str | None, transform: Similarity | None, mesh: TriMesh, size: int):
    """The input's :class:`KeptLayout` (one texture set), or a string saying why it has none to keep."""
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
    return KeptLayout(src, order, src.uv[tri], normals, tangents, check)


def kept_materials(bake_stats: dict, source: SourceMesh) -> tuple[np.ndarray, tuple[str, ...], tuple[str, ...]]:
    """The asset's materials where the bake kept the input's layout: per input triangle its
    material ``(T,)``, the materials' names and the folders of their texture sets below
    ``textures/``, as the bake recorded the sets (``uv.texture_sets``). A material is an input slot
    in one UDIM tile, named after the slot (``<slot>.<tile>`` where the slot spans several tiles),
    in the order of the slots and then of the tiles."""
    sets = bake_stats.get("uv", {}).get("texture_sets", [])
    folder = {(name, int(ts.get("tile", 1001))): ts["folder"] for ts in sets for name in ts["slots"]}
    tile = udim(face_tiles(source.corner_uv))
    combos, names, folders = {}, [], []
    for k, slot in enumerate(source.slot_names):
        tiles = sorted(set(tile[source.slot == k].tolist()))
        for t in tiles:
            combos[(k, t)] = len(names)
            names.append(slot if len(tiles) == 1 else f"{slot}.{t}")
            folders.append(folder.get((slot, t), ""))
    material = np.array([combos[(int(s), int(t))] for s, t in zip(source.slot, tile, strict=True)], np.int64)
    return material, tuple(names), tuple(folders)


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
