"""The smallest real use of each asset tool, for the doctor: usd-core writes and validates a tiny
USD stage, pygltflib reads a tiny GLB back, and the Khronos glTF-Validator (Node.js) validates it.
Each probe returns one line of what it did and raises when the tool fails."""

from __future__ import annotations

from pathlib import Path

from ..geometry.probes import PROBE_GLB_FACES
from .formats.gltf import validate_glb
from .formats.usd import validate_usd


def probe_usd(folder: Path) -> str:
    """A one-triangle ``UsdGeom.Mesh`` written to ``folder/probe.usda``, read back and run through
    every validator usd-core registers."""
    from pxr import Usd, UsdGeom

    path = Path(folder) / "probe.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/probe")
    stage.SetDefaultPrim(root.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/probe/triangle")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    stage.GetRootLayer().Save()
    reread = Usd.Stage.Open(str(path))  # held: a prim outlives no stage
    counts = UsdGeom.Mesh(reread.GetPrimAtPath("/probe/triangle")).GetFaceVertexCountsAttr().Get()
    if list(counts) != [3]:
        raise RuntimeError(f"usd-core read back {list(counts)} face(s), not the one triangle written")
    report = validate_usd(path)
    if report["errors"]:
        raise RuntimeError(f"usd-core's validators found {report['errors']} error(s) in a valid stage: {report['messages'][:3]}")
    return f"wrote and read back a USD stage; {report['validators']} validators ran on it"


def probe_gltf(glb: Path) -> str:
    """pygltflib reads the probe GLB (:func:`stages.geometry.probes.write_probe_glb`) back: one
    mesh whose index accessor holds every corner."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(glb))
    corners = gltf.accessors[gltf.meshes[0].primitives[0].indices].count
    if len(gltf.meshes) != 1 or corners != 3 * PROBE_GLB_FACES:
        raise RuntimeError(f"pygltflib read {len(gltf.meshes)} mesh(es) and {corners} corners, not 1 and {3 * PROBE_GLB_FACES}")
    return f"read a {PROBE_GLB_FACES}-face GLB back"


def probe_node_validator(glb: Path) -> str:
    """The Khronos glTF-Validator, run by Node.js as the export stage runs it, on the probe GLB:
    it must run and find no error."""
    report = validate_glb(glb)
    if not report["ran"]:
        raise RuntimeError(report["reason"])
    if report["errors"]:
        raise RuntimeError(f"the validator found {report['errors']} error(s) in a valid GLB: {report['messages'][:3]}")
    return f"{report['validator']} validated a GLB ({report['warnings']} warnings)"
