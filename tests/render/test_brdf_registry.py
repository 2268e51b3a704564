"""A BRDF is an object: one registry of names (the torch-free rows of :mod:`stages.config.brdfs`, one
module each in :mod:`stages.render.brdf`), no caller that compares BRDF names or tells a glTF
material by its metallic, and each object's shading the very numbers of the functions it replaced.

The golden file ``data/shading_golden.npz`` holds fixed random inputs (float64, and the same
rounded to float32) and what the renderer's entry points before the objects (``shade`` and
``shade_gltf`` of ``stages/render/shading.py`` at commit dbef3c0) returned for them: each BRDF
with each specular lobe model it has, TANGO's diffuse-only material, unshadowed and with random
visible shares."""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import REPO

from stages.config.brdfs import BRDFS
from stages.config.sections import SPECULAR_LOBES
from stages.model.field import shade_material
from stages.model.networks import MATERIAL_TYPES, Material
from stages.render import brdf as brdfs
from stages.render.light import Light
from stages.render.shading import SGLight

GOLDEN = Path(__file__).with_name("data") / "shading_golden.npz"
#: the BRDF package's modules that are not a model
INFRASTRUCTURE = {"__init__", "base", "table"}
#: where BRDF names may be compared: the registry and the table of names
REGISTRY = ("stages/render/brdf/", "stages/config/brdfs.py")
#: comparisons of a BRDF name's spelling that mean another concept, by (module, the other side),
#: each with why
OTHER_CONCEPTS = {
    ("stages/model/lights/sg.py", "init"): "optimize.light_init's tango is TANGO's draw of the light's sharpnesses",
}
#: a material's channels that only some BRDFs' materials have: testing them tells the BRDF apart
OWN_CHANNELS = ("metallic", "base")


def _names_in(node: ast.AST) -> bool:
    """Whether ``node`` is a BRDF name's string, or a tuple, list or set holding one."""
    if isinstance(node, ast.Constant):
        return node.value in tuple(BRDFS)
    if isinstance(node, ast.Tuple | ast.List | ast.Set):
        return any(_names_in(x) for x in node.elts)
    return False


def _pattern_names(pattern: ast.AST) -> bool:
    """Whether a ``match`` pattern matches a BRDF name's string."""
    if isinstance(pattern, ast.MatchValue):
        return _names_in(pattern.value)
    if isinstance(pattern, ast.MatchOr):
        return any(_pattern_names(p) for p in pattern.patterns)
    if isinstance(pattern, ast.MatchAs) and pattern.pattern is not None:
        return _pattern_names(pattern.pattern)
    return False


def _compare_findings(node: ast.Compare) -> list[tuple[str, str]]:
    """(what, the other side's source) for each comparison in ``node`` of a BRDF name, or of a
    BRDF's own channel with None."""
    found = []
    operands = [node.left, *node.comparators]
    for i, op in enumerate(node.ops):
        left, right = operands[i], operands[i + 1]
        for side, other in ((left, right), (right, left)):
            if isinstance(op, ast.Eq | ast.NotEq | ast.In | ast.NotIn | ast.Is | ast.IsNot) and _names_in(side):
                found.append(("compares a BRDF name", ast.unparse(other)))
            none = isinstance(other, ast.Constant) and other.value is None
            if isinstance(op, ast.Is | ast.IsNot) and none and isinstance(side, ast.Attribute) and side.attr in OWN_CHANNELS:
                found.append((f"tests .{side.attr} against None", ast.unparse(side)))
    return found


def brdf_branches(root: Path) -> list[str]:
    """Every place in ``root``'s ``stages/`` outside the registry (:data:`REGISTRY`) that compares
    a BRDF name (``==``, ``!=``, ``in``, ``is``, ``match``) or tests a BRDF's own material channel
    (``.metallic``, ``.base``) against None, but for the other concepts of :data:`OTHER_CONCEPTS`:
    ``path:line: what (the other side)``."""
    out = []
    for path in sorted((root / "stages").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel.startswith(REGISTRY):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            found, line = [], getattr(node, "lineno", 0)
            if isinstance(node, ast.Compare):
                found = _compare_findings(node)
            elif isinstance(node, ast.match_case) and _pattern_names(node.pattern):
                found, line = [("matches a BRDF name", "case")], node.pattern.lineno
            out += [f"{rel}:{line}: {what} ({other})" for what, other in found if (rel, other) not in OTHER_CONCEPTS]
    return out


def test_no_caller_compares_brdf_names():
    """Only the registry knows the models by name; everyone else asks the object (``brdf.shade``,
    ``brdf.parameters``, ``brdf.exported_textures``, ...). On the code before the objects
    (``git worktree add /tmp/old68 dbef3c0``, then ``brdf_branches`` of it) this found 40 places:
    36 branches on the BRDF in 12 modules, and 4 comparisons of a source mesh's kind with
    ``"gltf"``, since spelt :data:`~stages.geometry.sourcemesh.GLTF_SOURCE`."""
    assert brdf_branches(REPO) == []


def test_the_scan_finds_each_kind_of_branch(tmp_path):
    """The scan itself: a comparison, a membership, a ``match`` and a test of ``.metallic`` are
    found; the same outside ``stages/``, or in the registry, are not."""
    (tmp_path / "stages" / "render" / "brdf").mkdir(parents=True)
    (tmp_path / "stages" / "a.py").write_text(
        'if brdf == "gltf":\n    pass\nx = b in ("tango", "x")\nmatch b:\n    case "tango" | "y":\n        pass\n'
        "y = m.metallic is not None\nz = brdf != kind\n"
    )
    (tmp_path / "stages" / "render" / "brdf" / "gltf.py").write_text('if lobe == "gltf":\n    pass\n')
    found = brdf_branches(tmp_path)
    assert [f.split(":")[1] for f in found] == ["1", "3", "5", "7"], found


def test_each_name_has_a_row_a_module_an_object_and_a_material_class():
    modules = {p.stem for p in (REPO / "stages" / "render" / "brdf").glob("*.py")} - INFRASTRUCTURE
    assert modules == set(tuple(BRDFS)) == set(brdfs.names()) == set(MATERIAL_TYPES)
    for name in tuple(BRDFS):
        brdf = brdfs.get(name)
        assert brdf.name == name and brdf.spec is BRDFS[name] and brdfs.get(brdf) is brdf
        assert type(brdf).__module__ == f"stages.render.brdf.{name}"
        assert MATERIAL_TYPES[name].brdf is brdf
        assert set(brdf.lobes) <= set(SPECULAR_LOBES) and brdf.model_lobe in brdf.lobes
        assert set(brdf.texture_of) == set(brdf.parameters) and len(brdf.widths) == len(brdf.parameters) == 3
        assert brdf.table_path.is_file(), brdf.table_path
    with pytest.raises(ValueError, match="unknown BRDF 'phong'; choose one of tango, gltf"):
        brdfs.get("phong")


def test_material_of_carries_its_brdf():
    """A material of each BRDF, from its parameters in head order, carries that BRDF through
    every copy (:func:`dataclasses.replace`, as the compiled field's padding makes them)."""
    g = torch.Generator().manual_seed(0)
    for name in tuple(BRDFS):
        brdf = brdfs.get(name)
        heads = [torch.rand(4, w, generator=g) for w in brdf.widths]
        m = Material.of(name, *heads)
        assert m.brdf is brdf and type(m) is MATERIAL_TYPES[name]
        assert list(m.parameters()) == list(brdf.parameters)
        for got, want in zip(m.parameters().values(), heads, strict=True):
            assert got is want
    assert Material(torch.ones(2, 3), None, None).brdf is brdfs.TANGO


def _golden_inputs(z, dtype: str) -> dict[str, torch.Tensor]:
    return {k.split("/")[-1]: torch.from_numpy(z[k]) for k in z.files if k.startswith(f"{dtype}/in/")}


def _golden_cases(x: dict[str, torch.Tensor]):
    """(key, BRDF, lobe, material) of every case of the golden file."""
    tango = SimpleNamespace(albedo=x["albedo"], specular=x["specular"], roughness=x["roughness"], base=None, metallic=None)
    diffuse = SimpleNamespace(albedo=x["albedo"], specular=None, roughness=None, base=None, metallic=None)
    gltf = SimpleNamespace(albedo=None, specular=None, roughness=x["roughness"], base=x["base"], metallic=x["metallic"])
    cases = [(f"tango/{lobe}", "tango", lobe, tango) for lobe in ("isotropic", "split_sum", "fitted")]
    cases.append(("tango/diffuse_only", "tango", "isotropic", diffuse))
    return cases + [(f"gltf/{lobe}", "gltf", lobe, gltf) for lobe in ("split_sum", "fitted")]


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("shadowed", [False, True], ids=["lit", "shadowed"])
def test_each_brdf_shades_as_the_functions_it_replaced(dtype, shadowed):
    """Every BRDF x lobe model (and TANGO's diffuse-only material), unshadowed and shadowed, in
    float64 and float32: the objects' ``shade`` returns the golden numbers (measured: bit for bit;
    held to 1e-6 of each term's largest value), as does the field's path through a
    :class:`~stages.model.networks.Material` under a light of the SG lobes alone
    (:func:`~stages.model.field.shade_material`, :class:`~stages.render.light.Light`), bit for bit
    the object's numbers (a sum of one component is that component)."""
    with np.load(GOLDEN) as z:
        x = _golden_inputs(z, dtype)
        light = SGLight(x["axis"], x["sharpness"], x["amplitude"])
        vis = x["visibility"] if shadowed else None
        cases = _golden_cases(x)
        assert len(cases) == sum(len(s.lobes) for s in BRDFS.values()) + 1  # every lobe of every BRDF
        for key, name, lobe, m in cases:
            out = brdfs.get(name).shade(x["normal"], x["view"], m, light, lobe, vis)
            parameters = [getattr(m, p) for p in BRDFS[name].parameters]
            material = Material.of(name, *parameters)
            through_field = shade_material(
                x["normal"], x["view"], material, Light.of(light), lobe, None if vis is None else (vis,)
            )
            for part in ("diffuse", "specular"):
                want = z[f"{dtype}/{key}/{'shadowed' if shadowed else 'lit'}/{part}"]
                scale = 1e-6 * float(np.abs(want).max())
                np.testing.assert_allclose(getattr(out, part).numpy(), want, rtol=1e-6, atol=scale, err_msg=f"{key} {part}")
                assert torch.equal(getattr(through_field, part), getattr(out, part)), f"{key} {part}"


@pytest.mark.parametrize("name", tuple(BRDFS))
def test_a_brdf_refuses_the_lobes_it_does_not_have(name):
    """Each BRDF shades by exactly the lobe models of its row (``BrdfSpec.lobes``) and refuses the
    others with the ones it has."""
    brdf = brdfs.get(name)
    g = torch.Generator().manual_seed(1)
    n = torch.nn.functional.normalize(torch.randn(5, 3, generator=g, dtype=torch.float64), dim=-1)
    light = SGLight(n[:2], torch.full((2, 1), 4.0, dtype=torch.float64), torch.ones(2, 3, dtype=torch.float64))
    material = Material.of(brdf, *(torch.rand(5, w, generator=g, dtype=torch.float64) for w in brdf.widths))
    for lobe in SPECULAR_LOBES:
        if lobe in brdf.lobes:
            assert torch.isfinite(brdf.shade(n, n, material, light, lobe).rgb).all()
        else:
            with pytest.raises(ValueError, match=f"has no '{lobe}' specular model; use {' or '.join(brdf.lobes)}"):
                brdf.shade(n, n, material, light, lobe)
