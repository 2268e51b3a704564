"""Is the input's own UV layout usable for baking (``bake.uv``)? Measured, not assumed.

A layout is usable when:

* every face is mapped (all three corners have texture coordinates);
* no UV triangle is degenerate (UV area at most ``DEGENERATE_UV_AREA`` of the tile while the face
  has area in 3D: its texels could not be located);
* faces overlap each other in UV space on at most ``bake.uv_max_overlap`` of the faces, measured at
  the bake's texture resolution (texel centres inside two or more UV triangles, every face over a
  texel found). Stacked islands are not overlap: faces whose UV triangle repeats another's
  exactly, and islands that lie over the same texels as another island (on at least
  ``COINCIDENT`` of the larger: mirrored halves and repeated parts, however triangulated) share
  texels by design and are baked once (from one of the copies), which the record says; partial
  overlaps between islands and folds inside one are overlap;
* every face lies in one UV tile: the unit square, or one UDIM tile (1001-1100: ten tiles across,
  upwards), within ``TILE_MARGIN`` (a corner may reach that far past its tile's edge, and the
  texture repeats there, as glTF's default sampler does). Several UDIM tiles get one texture set
  each, in an OBJ's asset; a glTF document's primitives are kept as they are and cannot read one
  set per tile, so there they are refused.

The layout must also belong to the traced mesh: the bake evaluates the field on the traced faces,
so each input triangle must be one of them (:func:`match_faces`; a decimated mesh's faces are not).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .meshio import TriMesh
from .tracing import EmbreeTracer

#: UV triangles of at most this area (in tile units) are degenerate
DEGENERATE_UV_AREA = 1e-12
#: how far (in tile units) a corner may reach past its face's tile
TILE_MARGIN = 0.125
#: corners of matched faces agree to this fraction of the traced mesh's radius (1)
MATCH_TOLERANCE = 1e-5


@dataclass(frozen=True)
class LayoutCheck:
    """What :func:`check_layout` measured of a UV layout (counts of faces unless named otherwise)."""

    faces: int
    unmapped: int
    degenerate: int
    stacked: int
    overlapping: int
    outside: int
    tiles: tuple[int, ...]
    islands: int
    seams: int
    resolution: int

    def problems(self, max_overlap: float, udim: bool = False) -> list[str]:
        """One line per reason the layout cannot be baked into (empty: usable); ``udim``: several
        UDIM tiles are usable (one texture set per tile: an OBJ's; a glTF document's UVs outside
        the unit square are tiling, which its samplers repeat, mirror or clamp)."""
        out = []

        def share(n):
            return f"{n:,} of the {self.faces:,} faces ({100 * n / self.faces:.3g}%)"

        if self.unmapped:
            out.append(f"{share(self.unmapped)} have no texture coordinates")
        if self.degenerate:
            out.append(f"{share(self.degenerate)} have a degenerate (zero-area) UV triangle")
        if self.overlapping > max_overlap * self.faces:
            out.append(
                f"{share(self.overlapping)} overlap other faces in UV space "
                f"(bake.uv_max_overlap: {max_overlap:g}; stacked copies of an island excepted)"
            )
        if self.outside:
            out.append(f"{share(self.outside)} reach more than {TILE_MARGIN:g} of a tile past their UV tile")
        if len(self.tiles) > 1 and not udim:
            out.append(
                f"the UVs span {len(self.tiles)} tiles, which a glTF sampler repeats, mirrors or clamps (tiling, not "
                "UDIM tiles): a texel baked for one face would show on the others"
            )
        if udim and any(t < 1001 or t > 1100 for t in self.tiles):
            out.append(f"UDIM tiles outside 1001-1100 ({', '.join(str(t) for t in self.tiles if t < 1001 or t > 1100)})")
        return out

    def to_json(self) -> dict:
        return {**asdict(self), "tiles": list(self.tiles)}


def uv_areas(uv: np.ndarray) -> np.ndarray:
    """Signed areas ``(F,)`` of UV triangles ``uv (F, 3, 2)``."""
    a, b = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


def face_tiles(uv: np.ndarray) -> np.ndarray:
    """Integer tile ``(F, 2)`` (u, v; glTF's v down) of each face ``uv (F, 3, 2)``: the tile of its
    UV centroid; but a face that lies within ``TILE_MARGIN`` of the unit square counts to the unit
    square unless its centroid's tile is one the layout uses (a face lies there beyond the
    margin): a corner reaching past the edge is not a UDIM tile of its own."""
    tiles = np.floor(uv.mean(axis=1)).astype(np.int64)
    near_unit = ((uv >= -TILE_MARGIN) & (uv <= 1 + TILE_MARGIN)).all(axis=(1, 2))
    used = {tuple(t) for t in np.unique(tiles[~near_unit], axis=0)} if (~near_unit).any() else set()
    borrowed = near_unit & np.array([tuple(t) not in used for t in tiles], bool).reshape(len(tiles))
    tiles[borrowed] = 0
    return tiles


def wrapped_copies(local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UV triangles ``local (F, 3, 2)`` (each in the unit square, up to ``TILE_MARGIN``) with a
    copy shifted by a whole tile wherever a face reaches past an edge, so that the parts past the
    edge land where a repeating sampler reads them: ``(K, 3, 2)`` triangles and the face of each."""
    lo, hi = local.min(axis=1), local.max(axis=1)
    tris, owner = [local], [np.arange(len(local))]
    for du in (-1, 0, 1):
        for dv in (-1, 0, 1):
            if du == dv == 0:
                continue
            shifted_lo = lo + (du, dv)
            shifted_hi = hi + (du, dv)
            hit = ((shifted_hi > 0) & (shifted_lo < 1)).all(axis=1)
            if hit.any():
                tris.append(local[hit] + np.array([du, dv], np.float64))
                owner.append(np.flatnonzero(hit))
    return np.concatenate(tris), np.concatenate(owner)


def udim(tiles: np.ndarray) -> np.ndarray:
    """UDIM numbers of tiles ``(N, 2)`` in glTF's convention (v down): 1001 + u + 10 * (-v)
    counted upwards from the unit square (OBJ/Blender's ``v`` up)."""
    return 1001 + tiles[:, 0] + 10 * (-tiles[:, 1])


def stacked_faces(uv: np.ndarray) -> np.ndarray:
    """``(F,) int64``: for each face the first face with the same UV triangle (its three corners
    as a set, to 1e-6), itself where none came before: copies of a stacked or mirrored island."""
    corners = np.round(uv * 1e6).astype(np.int64)
    order = np.lexsort((corners[..., 1], corners[..., 0]))  # (F, 3): each face's corners sorted
    key = np.take_along_axis(corners, order[..., None], axis=1).reshape(len(uv), 6)
    _, first_index, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first_index[inverse.reshape(-1)]


#: texel centres are cast at from this fraction of a texel off centre, so that an edge running
#: exactly through centres (a 45-degree diagonal of a grid-aligned quad) does not count as overlap
CENTRE_JITTER = (1.37e-3, 2.91e-3)


def texel_cover(uv: np.ndarray, size: int, max_depth: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Every (texel, face) with the texel's centre inside the face's UV triangle, on a
    ``size``-texel tile, each face moved into its own tile and wrapped at its edges
    (:func:`wrapped_copies`): ``(texel index, face index)`` arrays. Each face is lifted to its own
    height (its index) and every texel centre is cast at from above, again and again from just
    below the last hit, so that every face over it is found (up to ``max_depth`` deep)."""
    n = len(uv)
    tris, owner = wrapped_copies(uv - face_tiles(uv)[:, None, :])
    z = np.repeat(owner.astype(np.float64), 3)[:, None]
    tri = np.concatenate([tris.reshape(-1, 2) * size, z], axis=1)
    tracer = EmbreeTracer(TriMesh(tri, np.arange(3 * len(tris)).reshape(-1, 3)))
    c = np.arange(size) + 0.5
    cols, rows = np.meshgrid(c + CENTRE_JITTER[0], c + CENTRE_JITTER[1])
    xy = np.stack([cols.ravel(), rows.ravel()], axis=1)
    top = np.full(len(xy), n + 1.0)
    live = np.arange(len(xy))
    texels, faces = [], []
    for _ in range(max_depth):
        origins = np.concatenate([xy[live], top[live, None]], axis=1)
        hits = tracer.trace(origins, np.broadcast_to([0.0, 0.0, -1.0], origins.shape))
        hit = hits.face >= 0
        live, face = live[hit], owner[hits.face[hit]]
        if not len(live):
            break
        texels.append(live)
        faces.append(face)
        top[live] = face - 0.5
    if not texels:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(texels), np.concatenate(faces)


def overlap_faces(uv: np.ndarray, size: int) -> np.ndarray:
    """``(F,) bool``: faces with a texel centre that another face's UV triangle also covers
    (:func:`texel_cover`)."""
    texel, face = texel_cover(uv, size)
    count = np.bincount(texel, minlength=size * size)
    out = np.zeros(len(uv), bool)
    out[face[count[texel] >= 2]] = True
    return out


#: two islands over the same texels on at least this share of the larger one are stacked copies
COINCIDENT = 0.8


def classify_overlap(uv: np.ndarray, size: int, island: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(overlapping, stacked)``, ``(F,) bool`` each, of faces ``uv (F, 3, 2)`` in UV charts
    ``island (F,)`` (:func:`uv_islands`): faces sharing texels with other faces (:func:`texel_cover`)
    are *stacked* where all those faces belong to charts that cover the same texels as theirs (on
    at least ``COINCIDENT`` of the larger chart: mirrored halves and repeated parts, however
    triangulated), and *overlapping* otherwise (partial overlaps between charts, and folds inside
    one)."""
    texel, face = texel_cover(uv, size)
    isl = island[face]
    n_isl = int(island.max(initial=-1)) + 1
    area = np.bincount(isl, minlength=n_isl)  # texels each island covers (its own faces never double)
    # pairs of distinct faces over one texel
    order = np.lexsort((face, texel))
    texel, face, isl = texel[order], face[order], isl[order]
    starts = np.flatnonzero(np.r_[True, texel[1:] != texel[:-1]])
    counts = np.diff(np.r_[starts, len(texel)])
    pairs_a, pairs_b = [], []
    for depth in range(2, int(counts.max(initial=1)) + 1):
        group = starts[counts == depth]
        for i in range(depth):
            for j in range(i + 1, depth):
                pairs_a.append(group + i)
                pairs_b.append(group + j)
    overlapping = np.zeros(len(uv), bool)
    stacked = np.zeros(len(uv), bool)
    if not pairs_a:
        return overlapping, stacked
    a, b = np.concatenate(pairs_a), np.concatenate(pairs_b)
    ia, ib = isl[a], isl[b]
    lo, hi = np.minimum(ia, ib), np.maximum(ia, ib)
    key = lo * n_isl + hi
    uniq, inverse, shared = np.unique(key, return_inverse=True, return_counts=True)
    big = np.maximum(area[uniq // n_isl], area[uniq % n_isl])
    coincident = (uniq // n_isl != uniq % n_isl) & (shared >= COINCIDENT * big)
    good = coincident[inverse]
    overlapping[face[a[~good]]] = True
    overlapping[face[b[~good]]] = True
    stacked[face[a[good]]] = True
    stacked[face[b[good]]] = True
    return overlapping, stacked & ~overlapping


def seams_and_islands(positions: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> tuple[int, int]:
    """UV seams (3D edges shared by two faces whose UVs differ along it; positions compared
    exactly) and islands (faces connected through edges that are not seams)."""
    seams, labels, _ = uv_islands(positions, faces, uv)
    return seams, int(labels.max(initial=-1)) + 1


def uv_islands(positions: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """The UV seams (:func:`seams_and_islands`), each face's island ``(F,)`` and its chart ``(F,)``:
    its island split where the UV orientation flips (mirrored halves glued along their symmetry
    line are one island of two charts, laid over each other)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, pid = np.unique(positions, axis=0, return_inverse=True)
    pid = pid.reshape(-1)[faces]  # (F, 3) position ids
    f = len(faces)
    a = pid.reshape(-1)
    b = pid[:, [1, 2, 0]].reshape(-1)
    ua = uv.reshape(-1, 2)
    ub = uv[:, [1, 2, 0]].reshape(-1, 2)
    swap = a > b
    lo, hi = np.where(swap, b, a), np.where(swap, a, b)
    uv_lo, uv_hi = np.where(swap[:, None], ub, ua), np.where(swap[:, None], ua, ub)
    edge_face = np.repeat(np.arange(f), 3)
    order = np.lexsort((hi, lo))
    same_edge = (lo[order][1:] == lo[order][:-1]) & (hi[order][1:] == hi[order][:-1])
    i, j = order[:-1][same_edge], order[1:][same_edge]
    joined = (np.abs(uv_lo[i] - uv_lo[j]).max(1) <= 1e-9) & (np.abs(uv_hi[i] - uv_hi[j]).max(1) <= 1e-9)
    seams = int((~joined).sum())
    fi, fj = edge_face[i][joined], edge_face[j][joined]
    _, islands = connected_components(coo_matrix((np.ones(len(fi)), (fi, fj)), shape=(f, f)), directed=False)
    side = uv_areas(uv) > 0
    keep = side[fi] == side[fj]
    _, charts = connected_components(coo_matrix((np.ones(int(keep.sum())), (fi[keep], fj[keep])), shape=(f, f)), directed=False)
    return seams, islands.astype(np.int64), charts.astype(np.int64)


def check_layout(positions: np.ndarray, faces: np.ndarray, uv: np.ndarray, resolution: int) -> LayoutCheck:
    """Measure the layout ``uv (F, 3, 2)`` (NaN where unmapped) of the mesh ``positions (V, 3)``,
    ``faces (F, 3)`` at a ``resolution``-texel tile (module docstring)."""
    mapped = np.isfinite(uv).all(axis=(1, 2))
    area3d = 0.5 * np.linalg.norm(np.cross(*(positions[faces][:, k] - positions[faces][:, 0] for k in (1, 2))), axis=1)
    extent = float(np.ptp(positions, axis=0).max()) or 1.0
    m_uv = uv[mapped]
    degenerate = (np.abs(uv_areas(m_uv)) <= DEGENERATE_UV_AREA) & (area3d[mapped] > (1e-9 * extent) ** 2)
    tiles = face_tiles(m_uv)
    reach = np.abs(m_uv - (tiles[:, None, :] + 0.5)).max(axis=(1, 2)) - 0.5
    seams, island, chart = (
        uv_islands(positions, faces[mapped], m_uv) if len(m_uv) else (0, np.zeros(0, np.int64), np.zeros(0, np.int64))
    )
    first = stacked_faces(m_uv)  # exact copies of a UV triangle: one is rasterised
    reps = np.flatnonzero(first == np.arange(len(m_uv)))
    overlapping, coincident = (
        classify_overlap(m_uv[reps], resolution, chart[reps]) if len(reps) else (np.zeros(0, bool), np.zeros(0, bool))
    )
    copies = np.bincount(first, minlength=len(m_uv))[first] > 1
    stacked_islands = np.zeros(len(m_uv), bool)
    stacked_islands[reps[coincident]] = True
    stacked = int((copies | stacked_islands[first]).sum())
    islands = int(island.max(initial=-1)) + 1
    return LayoutCheck(
        faces=len(faces),
        unmapped=int((~mapped).sum()),
        degenerate=int(degenerate.sum()),
        stacked=stacked,
        overlapping=int(overlapping.sum()),
        outside=int((reach > TILE_MARGIN).sum()),
        tiles=tuple(sorted(int(t) for t in np.unique(udim(tiles)))),
        islands=islands,
        seams=seams,
        resolution=int(resolution),
    )


def density_percentiles(positions: np.ndarray, faces: np.ndarray, uv: np.ndarray, size: int) -> dict[str, float]:
    """Texel density per face (texels of a ``size``-texel texture per unit of surface area: UV area
    times ``size`` squared over 3D area) at the 10th, 50th and 90th percentile of the surface area
    (faces without area left out): how evenly a layout spends its texels."""
    tri = positions[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    ok = area > 0
    density = np.abs(uv_areas(uv[ok])) * size**2 / area[ok]
    order = np.argsort(density)
    cum = np.cumsum(area[ok][order]) / area[ok].sum()
    return {f"p{q}": float(density[order][min(np.searchsorted(cum, q / 100), len(cum) - 1)]) for q in (10, 50, 90)}


def match_faces(source: np.ndarray, traced: TriMesh) -> np.ndarray:
    """For each input triangle ``source (T, 3, 3)`` (positions in the traced mesh's frame) the
    traced face with the same three corners (any rotation; within ``MATCH_TOLERANCE``), each
    traced face used once; -1 where none."""
    from scipy.spatial import cKDTree

    tri = traced.vertices[traced.faces]
    tree = cKDTree(tri.mean(axis=1))
    k = min(8, len(tri))
    _, cand = tree.query(source.mean(axis=1), k=k)
    cand = np.asarray(cand).reshape(len(source), k)
    used = np.zeros(len(tri), bool)
    out = np.full(len(source), -1, np.int64)
    for col in range(k):
        c = np.minimum(cand[:, col], len(tri) - 1)
        err = np.min([np.abs(np.roll(tri[c], r, axis=1) - source).max(axis=(1, 2)) for r in range(3)], axis=0)
        ok = (out < 0) & (err <= MATCH_TOLERANCE) & ~used[c]
        for i in np.flatnonzero(ok):  # duplicate faces: each traced face once
            if not used[c[i]]:
                used[c[i]] = True
                out[i] = c[i]
    return out
