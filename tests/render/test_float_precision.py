"""Float32 and bfloat16 against float64 at the extremes (``stages.testing.precision``, which
``python -m benchmarks.render.precision`` prints on its full grid). Its measure is checked on
formulas whose float32 behaviour is known from the textbook (an angle by ``acos`` of a dot product,
ill-conditioned near 0; by ``atan2`` of the cross and dot products, stable), its rule for inputs of
negligible gradient on hand-made numbers, and the renderer on the quick grid end to end."""

from __future__ import annotations

import math

import torch

from stages.testing import precision

F64 = torch.float64


def _angle_cases() -> list[precision.Case]:
    """Directions at 1e-4 to 1e-1 radians from a unit axis (the light's), float64."""
    g = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(torch.randn(1, 3, generator=g, dtype=F64), dim=-1)
    side = torch.nn.functional.normalize(torch.linalg.cross(axis, torch.randn(1, 3, generator=g, dtype=F64), dim=-1), dim=-1)
    angle = torch.logspace(-4, -1, 40, dtype=F64)[:, None]
    d = torch.cos(angle) * axis + torch.sin(angle) * side
    light = {"axis": axis, "sharpness": torch.ones(1, 1, dtype=F64), "amplitude": torch.ones(1, 3, dtype=F64)}
    return [precision.Case("angles", {"direction": d}, light, [f"angle {a:.1e}" for a in angle[:, 0].tolist()])]


def _acos_angle(p, lt, f):
    return torch.acos(torch.clamp((p["direction"] * lt["axis"]).sum(-1, keepdim=True), -1.0, 1.0))


def _kahan_angle(p, lt, f):
    apart, sum_ = p["direction"] - lt["axis"], p["direction"] + lt["axis"]
    norm = lambda x: torch.linalg.vector_norm(x, dim=-1, keepdim=True)  # noqa: E731
    return 2.0 * torch.atan2(norm(apart), norm(sum_))


def test_the_measure_tells_an_unstable_formula_from_a_stable_one():
    """The same angle two ways: ``acos(d . a)`` loses float32's precision as the angle nears 0
    (its derivative ``1 / sqrt(1 - x^2)`` from a rounded ``x``), Kahan's ``2 atan2(|d - a|,
    |d + a|)`` keeps it. The benchmark's float32 worst must show the first and clear the second."""
    results = precision.measure(_angle_cases(), {"acos": (("direction",), _acos_angle), "kahan": (("direction",), _kahan_angle)})
    unstable = results["acos"]["float32"]
    stable = results["kahan"]["float32"]
    assert unstable["value"].worst > 1e-2 and unstable["point grad"].worst > 1e-2
    assert stable["value"].worst < 1e-5 and stable["point grad"].worst < 1e-4
    assert unstable["value"].where.startswith("angle 1.0e-04")


def test_inputs_of_negligible_norm_are_reported_apart_not_skipped():
    errors = precision.Errors()
    ref = torch.tensor([[1.0], [2.0], [1.0], [1e-9]], dtype=F64)
    out = torch.tensor([[1.0], [2.2], [1.0], [0.0]], dtype=F64)
    errors.add(ref, out, ["a", "b", "c", "tiny"])
    s = errors.summary()
    assert math.isclose(s.worst, 0.2 / 2.0) and s.where == "b"
    assert s.apart == 1 and math.isclose(s.apart_worst, 1e-9 / 1.0)  # |0 - 1e-9| over the median, 1


def test_a_non_finite_output_is_an_infinite_error():
    errors = precision.Errors()
    errors.add(torch.ones(2, 3, dtype=F64), torch.tensor([[1.0, 1.0, 1.0], [1.0, math.nan, 1.0]], dtype=F64), ["a", "b"])
    assert errors.summary().worst == math.inf and errors.summary().where == "b"


def test_the_quick_grid_end_to_end():
    """Every term on the quick grid: the table, the placement of the worst cases, the inputs
    reported apart, the input's own float32 positions, and the last line (what the benchmark
    prints); float32 within 1e-2 for the light, its parametrisation, the hemisphere integral, the
    shadows' shares and a mesh at any scale, within 1e-3 for the light's gradient summed over many
    points, and the shading's values within 1e-2 (not every gradient: on this grid's rotation a sun
    reflected at the mirror direction of a mirror-like lobe is at float32's conditioning,
    docs/measurements/precision.md)."""
    lines = precision.summary_lines(precision.all_measurements(precision.QUICK))
    last = lines[-1]
    assert last.startswith("worst_grad_rel_f32=") and " worst_grad_rel_bf16=" in last
    figures = dict(part.split("=") for part in last.split())
    assert all(math.isfinite(float(v)) for v in figures.values())
    table = lines[: lines.index("")]  # the first table
    rows = {line.split(" | ")[0].lstrip("| "): [c.strip() for c in line.strip("| ").split(" | ")[1:]] for line in table[2:]}
    assert len(rows) == len(precision.TERMS) + 4
    many = f"light over {precision.MANY_POINTS[1]:,} points: glTF shading (fitted)"
    assert float(rows[many][2]) <= 1e-3, rows[many]  # each light leaf's gradient summed over the points
    for term in (
        "light radiance L(d)",
        "visible shares (512 directions)",
        "light parametrisation",
        "SG hemisphere integral",
        "mesh: glTF shading (fitted)",
    ):
        assert all(c == "-" or float(c) <= 1e-2 for c in rows[term][:3]), (term, rows[term])
    assert all(float(cells[0]) <= 1e-2 for cells in rows.values()), rows
    assert any("offset 1000 radii" in line and "degrees" in line for line in lines)


def _float32_point_grad(term: str, names: tuple[str, ...]) -> float:
    """The worst relative float32 error of the point gradient of ``term`` on the full grid's cases
    ``names`` (against float64 on the same float32 inputs)."""
    cases = [c for c in precision.shading_cases(precision.FULL) if c.name in names]
    assert len(cases) == len(names)
    return precision.measure(cases, {term: precision.TERMS[term]})[term]["float32"]["point grad"].worst


def test_split_sum_gradient_at_a_grazing_view_in_float32():
    """The split sum's average light is the ratio of two integrals of the same lobe; at n.v 1e-4 the
    warped lobe lies on the horizon, both integrals' gradients are dominated by its cut and their
    ratio's gradient by what is left of them (a cancellation of 5e6). The cosine fit's first term
    minus its second (32.7 and 31.7 times nearly equal numbers) kept float32's rounding at 4e-5 of
    the integral, and the gradient erred by 9.7e-2 (TANGO) and 6.6e-2 (glTF); within 1e-2 now."""
    for brdf in ("TANGO", "glTF"):
        cases = ("lam 0.1, n.l 0", "lam 0.1, n.l 0.0001", "lam 1, n.l -0.0001")
        worst = _float32_point_grad(f"specular split sum ({brdf})", cases)
        assert worst <= 1e-2, (brdf, worst)


def test_fitted_lobe_gradient_near_the_mirror_configuration_in_float32():
    """A glossy glTF lobe (roughness 0.05) at n.v 0.01: the half vector between the product lobe's
    axis and the view lay along the difference of the view's sine and the lobe's mean's, two
    numbers near 1 (the mean's from a tabulated angle near pi/2), which a sharp NDF amplifies; the
    gradient erred by 1.4e-2. Measured from the mirror direction by the table's tilt, within 5e-3."""
    assert _float32_point_grad("specular fitted (glTF)", ("lam 10, n.l -1", "lam 10, n.l -0.5")) <= 5e-3


def test_conditioning_is_what_turning_the_inputs_by_float32_roundoff_does():
    """``conditioning`` on ``d . a`` at an angle ``t`` from the axis: turning ``d`` by ``u`` moves
    the cosine by at most ``u sin t`` (to first order), a relative ``u tan t``; the largest of eight
    random turns lies between a third of that and that. No unit vector among the inputs: NaN."""
    u = precision.ROUNDOFF_F32
    for t in (0.3, 1.0, 1.4):
        axis = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
        d = torch.tensor([[math.sin(t), 0.0, math.cos(t)]], dtype=F64)
        case = precision.Case("dot", {"direction": d}, {"axis": axis}, ["d"])
        floor = precision.conditioning(
            lambda p, lt, f: (p["direction"] * lt["axis"]).sum(-1, keepdim=True), ("direction",), case, "value", 0
        )
        bound = 2 * u * math.tan(t)  # both vectors turn: each at most u sin t
        assert bound / 6 <= floor <= bound * 1.01, (t, floor / (u * math.tan(t)))
    plain = precision.Case("plain", {"lam": torch.ones(1, 1, dtype=F64)}, {}, ["x"])
    assert math.isnan(precision.conditioning(lambda p, lt, f: p["lam"] * 2, ("lam",), plain, "value", 0))
