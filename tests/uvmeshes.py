"""Meshes with their own UV layouts for the kept-layout tests, built here from the built-in shapes:
an xatlas layout stands in for an artist's, written as a skinned, animated, two-material GLB (with
a morph target, a camera and extras), as a multi-primitive GLB of two meshes, and as an OBJ."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def unwrapped(name: str = "vase") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A small vase (24 segments, 16 profile samples: about 700 faces) or knot with an xatlas
    layout: ``positions (V, 3)``, ``uv (V, 2)`` (glTF's v down), ``faces (F, 3)``, vertices split
    at the layout's seams."""
    import xatlas

    from stages.geometry.shapes import knot, vase

    v, f = vase(24, 16) if name == "vase" else knot(2, 3, 96, 8)
    vmapping, indices, uvs = xatlas.parametrize(v.astype(np.float32), f.astype(np.uint32))
    return v[vmapping].astype(np.float64), uvs.astype(np.float64), indices.astype(np.int64)


def smooth_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (positions welded, so seams do not crease)."""
    _, weld = np.unique(positions.round(9), axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    tri = positions[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    acc = np.zeros((weld.max() + 1, 3))
    np.add.at(acc, weld[faces].reshape(-1), np.repeat(fn, 3, axis=0))
    n = acc[weld]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


class _Blob:
    def __init__(self, g):
        self.g, self.data, self.views, self.accessors = g, bytearray(), [], []

    def add(self, arr: np.ndarray, kind: str, ctype: int, target=None, minmax=False) -> int:
        arr = np.ascontiguousarray(arr)
        self.data += b"\0" * ((-len(self.data)) % 4)
        self.views.append(self.g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=arr.nbytes, target=target))
        self.data += arr.tobytes()
        acc = self.g.Accessor(bufferView=len(self.views) - 1, componentType=ctype, count=len(arr), type=kind)
        if minmax:
            acc.min, acc.max = arr.min(0).tolist(), arr.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def skinned_glb(path: Path, name: str = "vase", offset=(3.0, 0.5, -1.0), fold: bool = False) -> dict:
    """A skinned, animated GLB of ``name`` with its xatlas layout: two primitives (materials
    ``Body`` and ``Rim``: the faces below and above mid-height) sharing one vertex set, a morph
    target, a skin of two joints (weights by height) of an armature placed at ``offset`` (the
    vertices, in the root skinned node's frame, placed there too), a rotation animation of the
    upper joint, a camera and extras. ``fold``: the layout folded about u = 0.5 and v = 0.5
    (``0.5 - |uv - 0.5|``), so that up to four islands overlap (a layout no bake can keep).
    Returns what was written: ``positions`` (as stored), ``uv`` and ``faces``."""
    import pygltflib as g

    pos, uv, faces = unwrapped(name)
    if fold:
        uv = 0.5 - np.abs(uv - 0.5)
    pos = pos + np.asarray(offset, np.float64)
    pos32, uv32 = pos.astype(np.float32), uv.astype(np.float32)
    normals = smooth_normals(pos, faces).astype(np.float32)
    h = (pos[:, 1] - pos[:, 1].min()) / np.ptp(pos[:, 1])
    joints = np.zeros((len(pos), 4), np.uint16)
    joints[:, 1] = h > 0  # no joint listed with zero weight
    weights = np.zeros((len(pos), 4), np.float32)
    weights[:, 1] = h.astype(np.float32)
    weights[:, 0] = 1.0 - weights[:, 1]
    upper = pos[faces].mean(axis=1)[:, 1] > np.median(pos[:, 1])
    b = _Blob(g)
    attrs = g.Attributes(
        POSITION=b.add(pos32, g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True),
        NORMAL=b.add(normals, g.VEC3, g.FLOAT, g.ARRAY_BUFFER),
        TEXCOORD_0=b.add(uv32, g.VEC2, g.FLOAT, g.ARRAY_BUFFER),
        JOINTS_0=b.add(joints, g.VEC4, g.UNSIGNED_SHORT, g.ARRAY_BUFFER),
        WEIGHTS_0=b.add(weights, g.VEC4, g.FLOAT, g.ARRAY_BUFFER),
    )
    morph = b.add((0.05 * normals).astype(np.float32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True)
    prims = []
    for k, sel in enumerate((~upper, upper)):
        idx = b.add(faces[sel].reshape(-1).astype(np.uint32), g.SCALAR, g.UNSIGNED_INT, g.ELEMENT_ARRAY_BUFFER)
        prims.append(g.Primitive(attributes=attrs, indices=idx, material=k, targets=[{"POSITION": morph}]))
    mid = float(np.median(pos[:, 1]))  # the neck joint's height (world)
    ibm = np.stack([_translation(-np.asarray(offset)), _translation(-(np.asarray(offset) + [0, mid - offset[1], 0]))])
    # glTF matrices are column-major: each 4x4 written transposed
    inverse_bind = b.add(ibm.transpose(0, 2, 1).reshape(2, 16).astype(np.float32), g.MAT4, g.FLOAT)
    times = b.add(np.array([0.0, 1.0], np.float32)[:, None], g.SCALAR, g.FLOAT, minmax=True)
    turn = np.array([[0, 0, 0, 1], [0, 0, np.sin(0.3), np.cos(0.3)]], np.float32)
    rotations = b.add(turn, g.VEC4, g.FLOAT)
    doc = g.GLTF2(
        asset=g.Asset(version="2.0", generator="tango-stylize tests", extras={"author": "test"}),
        scene=0,
        scenes=[g.Scene(nodes=[0, 3, 4], name="Scene")],
        nodes=[
            g.Node(name="Root", translation=list(map(float, offset)), children=[1]),
            g.Node(name="Hip", children=[2]),
            g.Node(name="Neck", translation=[0.0, mid - offset[1], 0.0], extras={"bone": "neck"}),
            g.Node(name="Vase", mesh=0, skin=0, extras={"asset_id": 42}),
            g.Node(name="Camera", camera=0, translation=[0.0, 0.5, 4.0]),
        ],
        meshes=[g.Mesh(name="VaseMesh", primitives=prims, weights=[0.0], extras={"targetNames": ["Bulge"]})],
        skins=[g.Skin(name="Armature", joints=[1, 2], inverseBindMatrices=inverse_bind)],
        animations=[
            g.Animation(
                name="Nod",
                samplers=[g.AnimationSampler(input=times, output=rotations, interpolation="LINEAR")],
                channels=[g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=2, path="rotation"))],
            )
        ],
        cameras=[g.Camera(type="perspective", perspective=g.Perspective(yfov=0.8, znear=0.1))],
        materials=[
            g.Material(name="Body", pbrMetallicRoughness=g.PbrMetallicRoughness(baseColorFactor=[0.8, 0.2, 0.2, 1.0])),
            g.Material(name="Rim", pbrMetallicRoughness=g.PbrMetallicRoughness(baseColorFactor=[0.2, 0.2, 0.8, 1.0])),
        ],
        accessors=b.accessors,
        bufferViews=b.views,
        buffers=[g.Buffer(byteLength=len(b.data))],
    )
    doc.set_binary_blob(bytes(b.data))
    doc.save_binary(str(path))
    return {"positions": pos32.astype(np.float64), "uv": uv, "faces": faces}


def _translation(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def write_obj(path: Path, name: str = "vase", materials: tuple[str, ...] = ("Glaze",), udim: bool = False) -> dict:
    """``name`` with its xatlas layout as an OBJ: shared ``v`` (welded positions), ``vt`` and ``vn``
    lines, ``f v/vt/vn`` faces (``materials`` assigned to consecutive runs of faces), an ``o``,
    ``s`` and a comment the copy must keep. ``udim``: the second half of the faces reads a copy of
    the layout moved one tile to the right (UDIM 1002)."""
    pos, uv, faces = unwrapped(name)
    normals = smooth_normals(pos, faces)
    wpos, wv = np.unique(pos.round(12), axis=0, return_inverse=True)
    wv = wv.reshape(-1)
    lines = ["# a test mesh with its own layout", f"mtllib {Path(path).stem}.mtl", f"o {name}"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in wpos]
    lines += [f"vt {u:.9g} {1.0 - v:.9g}" for u, v in uv]
    if udim:
        lines += [f"vt {u + 1.0:.9g} {1.0 - v:.9g}" for u, v in uv]
    lines += [f"vn {x:.9g} {y:.9g} {z:.9g}" for x, y, z in normals]
    lines.append("s 1")
    runs = np.array_split(np.arange(len(faces)), len(materials))
    moved = np.arange(len(faces)) >= len(faces) // 2 if udim else np.zeros(len(faces), bool)
    for mat, run in zip(materials, runs, strict=True):
        lines.append(f"usemtl {mat}")
        for k in run:
            shift = len(uv) if moved[k] else 0
            lines.append("f " + " ".join(f"{wv[i] + 1}/{i + 1 + shift}/{i + 1}" for i in faces[k]))
    Path(path).write_text("\n".join(lines) + "\n")
    return {"positions": pos, "uv": uv, "faces": faces, "welded": wpos}


def multi_glb(path: Path) -> dict:
    """A GLB of two meshes with their xatlas layouts under two nodes: the vase (material
    ``Glaze``, rotated, scaled and moved by its node's TRS, with a second primitive that draws
    lines and is not surface) and the knot (no material, moved by a matrix). Returns the nodes'
    world matrices and the meshes' ``(positions, uv, faces)``."""
    import pygltflib as g
    from scipy.spatial.transform import Rotation

    b = _Blob(g)
    meshes, parts = [], []
    for name in ("vase", "knot"):
        pos, uv, faces = unwrapped(name)
        attrs = g.Attributes(
            POSITION=b.add(pos.astype(np.float32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True),
            NORMAL=b.add(smooth_normals(pos, faces).astype(np.float32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER),
            TEXCOORD_0=b.add(uv.astype(np.float32), g.VEC2, g.FLOAT, g.ARRAY_BUFFER),
        )
        idx = b.add(faces.reshape(-1).astype(np.uint16), g.SCALAR, g.UNSIGNED_SHORT, g.ELEMENT_ARRAY_BUFFER)
        prims = [g.Primitive(attributes=attrs, indices=idx, material=0 if name == "vase" else None)]
        if name == "vase":
            lines = b.add(faces[:8, :2].reshape(-1).astype(np.uint16), g.SCALAR, g.UNSIGNED_SHORT, g.ELEMENT_ARRAY_BUFFER)
            prims.append(g.Primitive(attributes=g.Attributes(POSITION=attrs.POSITION), indices=lines, mode=g.LINES))
        meshes.append(g.Mesh(name=name, primitives=prims))
        parts.append((pos, uv, faces))
    quat = Rotation.from_euler("xyz", [0.2, 0.7, -0.4]).as_quat()
    vase_node = g.Node(name="VaseNode", mesh=0, translation=[0.5, 0.0, -0.3], rotation=list(quat), scale=[1.5, 1.5, 1.5])
    knot_matrix = np.eye(4)
    knot_matrix[:3, 3] = [2.5, 0.2, 0.0]
    knot_node = g.Node(name="KnotNode", mesh=1, matrix=list(knot_matrix.T.reshape(-1)))
    doc = g.GLTF2(
        asset=g.Asset(version="2.0", generator="tango-stylize tests"),
        scene=0,
        scenes=[g.Scene(nodes=[0, 1])],
        nodes=[vase_node, knot_node],
        meshes=meshes,
        materials=[g.Material(name="Glaze", doubleSided=False)],
        accessors=b.accessors,
        bufferViews=b.views,
        buffers=[g.Buffer(byteLength=len(b.data))],
    )
    doc.set_binary_blob(bytes(b.data))
    doc.save_binary(str(path))
    world = np.eye(4)
    world[:3, :3] = Rotation.from_quat(quat).as_matrix() * 1.5
    world[:3, 3] = [0.5, 0.0, -0.3]
    return {"parts": parts, "worlds": [world, knot_matrix]}
