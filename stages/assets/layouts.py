"""Which UV layout a bake writes into (``bake.uv``): the input's own, a second UV set beside it,
or a new xatlas atlas.

``keep`` bakes into the input's own layout and stops with one line saying what is wrong when it
is not usable; ``second`` bakes into a new layout made for the input's own triangles, which the
export writes as a second UV set of the input's glTF document (``TEXCOORD_1``,
:mod:`stages.assets.gltfuvset`; an OBJ holds one set, so there it stops); ``auto`` (the default)
keeps the input's layout where it is usable, else makes a second set where the input can hold
one, else unwraps a new atlas, with the reason logged and recorded; ``atlas`` always unwraps (the
traced mesh, welded). Usable is measured (:mod:`stages.geometry.uvlayout`): every face mapped, no
degenerate UV triangle, overlap within ``bake.uv_max_overlap`` (stacked copies of an island
excepted, and baked once: mirrored and stacked islands are how artists save texture space), every
face in one UV tile (an OBJ's UDIM tiles each get a texture set; a glTF sampler repeats or clamps
its UVs, so a glTF layout over several tiles holds no bake). The kept or second layout must also
be the traced mesh's: an input format that holds one (OBJ, glTF), and the traced faces the
input's own (a decimated mesh's are not; its asset is unwrapped anew).

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
from ..geometry.atlas import unwrap
from ..geometry.meshio import BUILTIN_PREFIX, TriMesh
from ..geometry.normalization import Similarity
from ..geometry.normals import unit_face_normals
from ..geometry.sourcemesh import LAYOUT_SUFFIXES, OBJ_SOURCE, SourceMesh, load_gltf_document, read_source
from ..geometry.tangents import CornerFrames, mikktspace
from ..geometry.uvlayout import LayoutCheck, check_layout, face_tiles, match_faces, udim
from .gltfuvset import set_refusal

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
    """A layout of the input's own triangles on the traced mesh (the input's own, or a second set
    made for the bake): the ``source`` surface, ``source_face (F,)`` (the input triangle each
    traced face is), ``uv (F, 3, 2)`` per traced face (None: a second set not yet made,
    :func:`second_layout`), the corner normals and tangents in the traced (normalised) frame and
    the ``check`` of the layout."""

    source: SourceMesh
    source_face: np.ndarray
    uv: np.ndarray | None
    normals: np.ndarray
    tangents: np.ndarray | None
    check: LayoutCheck | None
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


#: the layouts a bake writes into (``UvChoice.layout``): the input's own, a second set beside it, a new atlas
KEPT, SECOND, ATLAS = "kept", "second", "atlas"


@dataclass(frozen=True)
class UvChoice:
    """The layout a bake used (:data:`KEPT`, :data:`SECOND` or :data:`ATLAS`), ``why``, what was
    measured of the input's own (``check``), the input's material ``slots`` and the texture
    ``sets`` they use (and why so many)."""

    setting: str
    layout: str
    why: str
    check: LayoutCheck | None = None
    slots: tuple[str, ...] = ()
    sets: tuple[TextureSet, ...] = ()
    sets_why: str = ""
    #: what was measured of a second set made for the bake (:func:`second_layout`)
    made: LayoutCheck | None = None

    @property
    def kept(self) -> bool:
        """The bake wrote into the input's own layout."""
        return self.layout == KEPT

    @property
    def own_topology(self) -> bool:
        """The asset is the input's own (its layout kept, or a second set beside it)."""
        return self.layout != ATLAS

    def record(self) -> dict:
        out = {"setting": self.setting, "layout": self.layout, "why": self.why}
        if self.check is not None:
            out["check"] = self.check.to_json()
        if self.made is not None:
            out["second_check"] = self.made.to_json()
        if self.own_topology:
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
    For :data:`SECOND` the layout returned has no UVs yet (:func:`second_layout` makes them).

    Raises:
        StageInputError: ``keep`` and the layout is not usable, or ``second`` and the input
            cannot hold a second set (one line: what is wrong).
    """
    if setting == ATLAS:
        return UvChoice(setting, ATLAS, "bake.uv: atlas"), None
    found = _match_source(source, transform, mesh)
    if isinstance(found, str):
        return _refuse(setting, source, found), None
    src, order = found
    why, check = "bake.uv: second", None
    if setting != SECOND:
        own = _own_layout(src, order, transform, mesh, size, max_overlap)
        if isinstance(own, tuple):
            return dataclasses.replace(own[0], setting=setting), own[1]
        why, check = own.why, own.check
        if setting == "keep":
            _refuse(setting, source, why, check)
    refused = second_refusal(src)
    if refused is not None:
        return _refuse(setting, source, refused if setting == SECOND else f"{why}; and {refused}", check), None
    sets = (TextureSet("", tuple(range(len(src.slot_names)))),)
    said = why if setting == SECOND else f"auto: {why}; a second UV set made for the bake, the input's own kept"
    if setting != SECOND:
        log.info("bake.uv: %s", said)
    layout = KeptLayout(src, order, None, _normals(src, order, transform), None, None, sets)
    return UvChoice(setting, SECOND, said, check, src.slot_names, sets, "one texture set shared by every slot"), layout


def _own_layout(src: SourceMesh, order: np.ndarray, transform: Similarity, mesh: TriMesh, size: int, max_overlap: float):
    """``(choice, layout)`` where the input's own layout is usable, else a :data:`ATLAS` choice
    saying why not, with what was measured (no check: the input has no UVs)."""
    if not src.mapped.any():
        return UvChoice("", ATLAS, "the input has no texture coordinates")
    found = _read_layout(src, order, transform, mesh, size)
    c = found.check
    sets, sets_why, problems = _texture_sets(found, size, max_overlap)
    if problems:
        return UvChoice("", ATLAS, "; ".join(problems), c)
    stacked = f", {c.stacked:,} faces stacked copies baked once" if c.stacked else ""
    why = f"usable: {c.islands:,} islands{stacked}; {sets_why}"
    return UvChoice("", KEPT, why, c, src.slot_names, sets, sets_why), dataclasses.replace(found, sets=sets)


def second_refusal(src: SourceMesh) -> str | None:
    """Why the input cannot hold a second UV set, or None: an OBJ holds one set; a glTF document
    with compressed or sparse vertex data (:func:`~stages.assets.gltfuvset.set_refusal`)."""
    if src.kind == OBJ_SOURCE:
        return "an OBJ holds one UV set, so the bake cannot be a second one beside it"
    doc, _ = load_gltf_document(src.path)
    return set_refusal(doc)


def second_layout(layout: KeptLayout, mesh: TriMesh, size: int, padding: int, max_chart_share: float | None) -> KeptLayout:
    """The second UV set's layout for the traced ``mesh`` (its faces the input's, ``layout`` as
    :func:`choose_layout` returns it for :data:`SECOND`): an xatlas atlas
    (:func:`~stages.geometry.atlas.unwrap`, ``size`` texels, ``padding``, ``max_chart_share``) of
    the faces of each primitive's first instance; a mesh drawn again by other nodes reads the
    same coordinates there (one UV set per primitive), so its texels are baked once."""
    src, order = layout.source, layout.source_face
    face_of = np.empty_like(order)
    face_of[order] = np.arange(len(order))  # input triangle -> traced face
    rows, copies = _instances(src)
    sub_faces = mesh.faces[face_of[rows]]
    used, compact = np.unique(sub_faces, return_inverse=True)
    atlas = unwrap(TriMesh(mesh.vertices[used], compact.reshape(-1, 3)), size, padding, max_chart_share)
    corner = np.zeros((len(src.triangles), 3, 2))
    corner[rows] = atlas.uv
    for dst, origin, flip in copies:
        corner[dst] = corner[origin][:, [0, 2, 1]] if flip else corner[origin]
    check = check_layout(src.positions, src.triangles, corner, size)
    return dataclasses.replace(layout, uv=corner[order], check=check)


def _instances(src: SourceMesh) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray, bool]]]:
    """The input triangles of each primitive's first instance (all of an OBJ's), and for every
    further instance ``(its triangles, the first's, whether one of the two is mirrored)``."""
    if not src.parts:
        return np.arange(len(src.triangles)), []
    first: dict[tuple, int] = {}
    rows, copies = [], []
    for k, part in enumerate(src.parts):
        mine = np.flatnonzero(src.part == k)
        key = (part["mesh"], part["primitive"])
        if key not in first:
            first[key] = k
            rows.append(mine)
        else:
            origin = src.parts[first[key]]
            copies.append((mine, np.flatnonzero(src.part == first[key]), origin["mirrored"] != part["mirrored"]))
    return np.concatenate(rows), copies


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
    """A new atlas under ``auto`` (the reason logged and recorded); under ``keep`` or ``second`` a
    stop, one line naming the setting and ``why``."""
    if setting in ("keep", SECOND):
        remedy = "Set bake.uv: auto or atlas to bake into a new atlas"
        if "bake.uv_max_overlap" in why:
            remedy += ", or raise bake.uv_max_overlap (stages.quick: --uv-max-overlap) to bake over the overlap"
        raise StageInputError(source or "the mesh", f"bake.uv: {setting}, but {why}", remedy + ".")
    log.info("bake.uv: auto: a new atlas, because %s", why)
    return UvChoice(setting, ATLAS, f"auto: {why}", check)


def _match_source(source: str | None, transform: Similarity | None, mesh: TriMesh):
    """``(input surface, traced face -> input triangle)``, or a string saying why the traced
    ``mesh`` has no input surface whose layout it could take."""
    if source is None or transform is None:
        return "no input file was given to read a layout from"
    if source.startswith(BUILTIN_PREFIX):
        return f"{source} has no UV layout"
    if Path(source).suffix.lower() not in LAYOUT_SUFFIXES:
        return f"{Path(source).suffix} input holds no UV layout the tool reads (OBJ, GLB and glTF do)"
    src = read_source(source)
    face = match_faces(transform.forward(src.positions)[src.triangles], mesh)
    if len(src.triangles) != len(mesh.faces) or (face < 0).any():
        return (
            f"the traced mesh's faces are not the input's ({len(mesh.faces):,} traced, {len(src.triangles):,} in the input, "
            f"{int((face < 0).sum()):,} unmatched): a decimated mesh is baked into a new atlas"
        )
    order = np.empty_like(face)
    order[face] = np.arange(len(face))  # traced face -> input triangle
    return src, order


def _normals(src: SourceMesh, order: np.ndarray, transform: Similarity) -> np.ndarray:
    """The input's corner normals per traced face, in the traced frame (the similarity's rotation)."""
    return src.corner_normals()[order] @ transform.rotation.T


def _read_layout(src: SourceMesh, order: np.ndarray, transform: Similarity, mesh: TriMesh, size: int) -> KeptLayout:
    """The input's own :class:`KeptLayout` (one texture set) on the traced faces ``order``."""
    tri = src.triangles[order]
    check = check_layout(src.positions, src.triangles, src.corner_uv, size)
    tangents = None
    if src.tangents is not None:
        t = src.tangents[tri]
        tangents = np.concatenate([t[..., :3] @ transform.rotation.T, t[..., 3:]], axis=-1)
    return KeptLayout(src, order, src.uv[tri], _normals(src, order, transform), tangents, check)


def kept_materials(
    bake_stats: dict, source: SourceMesh, corner_uv: np.ndarray | None = None
) -> tuple[np.ndarray, tuple[str, ...], tuple[str, ...]]:
    """The asset's materials where the bake kept the input's layout (or made a second set,
    ``corner_uv``: :func:`second_set`): per input triangle its material ``(T,)``, the materials'
    names and the folders of their texture sets below ``textures/``, as the bake recorded the sets
    (``uv.texture_sets``). A material is an input slot in one UDIM tile, named after the slot
    (``<slot>.<tile>`` where the slot spans several tiles), in the order of the slots and then of
    the tiles."""
    sets = bake_stats.get("uv", {}).get("texture_sets", [])
    folder = {(name, int(ts.get("tile", 1001))): ts["folder"] for ts in sets for name in ts["slots"]}
    tile = udim(face_tiles(source.corner_uv if corner_uv is None else corner_uv))
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
    layout or made a second set for it, read again from ``source`` and checked to be the one
    baked; None for an atlas.

    Raises:
        StageInputError: no ``source`` given, or one whose faces or UVs are not the bake's.
    """
    layout = bake_stats.get("uv", {}).get("layout")
    if layout not in (KEPT, SECOND):
        return None
    if source is None:
        raise StageInputError(
            Path(bake_dir) / "meta.json",
            f"the bake {'kept the input' if layout == KEPT else 'made a second UV set for the input'}'s UV layout, but the "
            "input mesh was not given",
            "Pass --source with the input mesh (the workflow does).",
        )
    src = read_source(source)
    face = atlas.get("source_face")
    same = face is not None and len(face) == len(src.triangles) and np.array_equal(np.sort(face), np.arange(len(face)))
    if same and layout == KEPT:
        same = np.allclose(src.corner_uv[face], atlas["uv"], atol=1e-6)
    if not same:
        raise StageInputError(source, "is not the mesh whose triangles the bake baked (faces or UVs differ)", "Rerun the bake.")
    return src


def second_set(bake_stats: dict, atlas: dict) -> np.ndarray | None:
    """The second UV set the bake made (``bake.uv: second``), ``(T, 3, 2)`` per input triangle,
    from its ``atlas.npz`` arrays (per traced face, and the input triangle each is); None for
    another layout."""
    if bake_stats.get("uv", {}).get("layout") != SECOND:
        return None
    face = np.asarray(atlas["source_face"])
    corner = np.empty((len(face), 3, 2))
    corner[face] = atlas["uv"]
    return corner
