"""The geometry every export format writes: indexed, in export space, with the bake's frame.

Geometry (:class:`ExportMesh`) carries the bake's frame (:class:`~stages.geometry.tangents.CornerFrames`):
the shading normals the field was trained with (flat, as TANGO shades, or smooth) and MikkTSpace
tangents, so viewers rebuild the frame the normal map was baked in. Vertices are shared wherever
position, normal, UV and tangent agree and split only at UV seams, creases (every edge, for flat
normals) and handedness changes; a viewer or Blender computing its own MikkTSpace on them welds
the same corners and gets the same frame. It is returned to the input's units and position
through the normalisation's inverse transform (the rotation that made the input's up axis +Y is
kept, so ``upAxis`` is Y), or left in the normalised frame (``units: normalized``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...config.layout import TEXTURE_FILES
from ...core.errors import StageInputError
from ...core.safefiles import DATA_LIMIT, open_read
from ...geometry.meshio import TriMesh
from ...geometry.normalization import Similarity


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


@dataclass
class Level:
    """One level of detail of an asset: its ``geom``, the folder of its four textures (relative to
    the folder the files that hold every level are written in) and its variant/node ``name``."""

    name: str
    geom: ExportMesh
    textures: str
