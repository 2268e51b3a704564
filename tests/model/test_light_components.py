"""A light is a sum of components (:mod:`stages.render.light`, :mod:`stages.model.lights`): a toy
kind, a constant environment, added beside the SG lobes in a registry that holds it for the test
(:func:`stages.model.lights.registered`), and the field's render under the sum is the sum of its
renders under each component alone, bit for bit; its radiance, energy, description, arrays and fit
likewise. The recipe "to add a light" starts here: a kind is these two classes and a line in the
registry."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from stages import optimize
from stages.config.sections import FieldSettings, OptimizeSettings
from stages.model import lights
from stages.model.field import StyleField
from stages.model.lights import LightComponentModule, LightModule, build_light
from stages.model.lights.sg import SGLightModule
from stages.render.envmap import radiant_energy
from stages.render.light import Light
from stages.render.shading import Shading

#: a small optimisation (tests/training/test_optimize.py's)
TINY = dict(clip_tiny_test=True, image_size=64, width=32, crops=2, light_lobes=8, eval_width=32, material_frequencies=4)


class ConstantLight:
    """Radiance ``c (3,)`` from every direction. Its diffuse term is exact for a Lambertian
    surface, ``albedo / pi * int c max(n . w, 0) dw = albedo c``; the toy has no specular term and
    no shadows (its visibility input: none)."""

    kind = "constant"
    #: an asset draws it into its environment image
    in_environment = True

    def __init__(self, radiance: torch.Tensor) -> None:
        self.c = radiance

    @property
    def device(self) -> torch.device:
        return self.c.device

    def shade(self, brdf, normal, view, material, lobe, visibility) -> Shading:
        diffuse = material.albedo * self.c
        return Shading(diffuse, torch.zeros_like(diffuse))

    def radiance(self, directions: torch.Tensor) -> torch.Tensor:
        return self.c.expand(*directions.shape[:-1], 3)

    def energy(self) -> torch.Tensor:
        return 4.0 * math.pi * self.c

    def describe(self) -> dict:
        return {"kind": self.kind, "radiance": self.c.tolist()}

    def arrays(self) -> dict[str, np.ndarray]:
        return {"constant_radiance": self.c.detach().cpu().numpy()}

    def distant_lights(self) -> list:
        return []

    def shadowed_by(self, shadows, index):
        return None

    def like(self, leaf) -> ConstantLight:
        return ConstantLight(leaf(3))

    def visibility_like(self, leaf, points: int):
        return None

    def to(self, device) -> ConstantLight:
        return ConstantLight(self.c.to(device))

    def detach(self) -> ConstantLight:
        return ConstantLight(self.c.detach())


class ConstantLightModule(LightComponentModule):
    """A learnable constant environment (its radiance's logarithm), in every field."""

    kind = "constant"

    def __init__(self, radiance: float = 0.1) -> None:
        super().__init__()
        self.log_radiance = torch.nn.Parameter(torch.full((3,), math.log(radiance)))

    @classmethod
    def build(cls, settings: FieldSettings) -> ConstantLightModule:
        return cls()

    def forward(self) -> ConstantLight:
        return ConstantLight(torch.exp(self.log_radiance))

    def fit(self, env: np.ndarray, iterations: int) -> dict:
        """The map's mean radiance over the sphere (its energy over 4 pi)."""
        mean = radiant_energy(env) / (4.0 * math.pi)
        with torch.no_grad():
            self.log_radiance.copy_(torch.log(torch.from_numpy(mean).float().clamp(min=1e-30)))
        return {"constant_radiance": mean.tolist()}


@pytest.fixture
def with_constant():
    with lights.registered(ConstantLightModule):
        yield


def _hits(n: int = 200, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    points = torch.rand(n, 3, generator=g) * 2 - 1
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    view = torch.nn.functional.normalize(normals + 0.5 * torch.randn(n, 3, generator=g), dim=-1)
    return points, normals, view


def test_the_registry_holds_a_kind_for_the_block_only(with_constant):
    assert lights.names() == ("sg", "sun", "bounce", "constant") and lights.get("constant") is ConstantLightModule
    field = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    assert [c.kind for c in field.light.components] == ["sg", "constant"]
    assert field.light.lobes == 4  # the SG lobes alone
    with pytest.raises(ValueError, match="already registered: sg"):
        with lights.registered(SGLightModule):
            pass
    with pytest.raises(ValueError, match="one component of each kind"):
        LightModule([SGLightModule(2), SGLightModule(3)])
    with pytest.raises(ValueError, match="distinct kinds"):
        Light.of(ConstantLight(torch.ones(3)), ConstantLight(torch.ones(3)))


def test_outside_the_block_a_field_has_its_sg_lobes_only():
    with lights.registered(ConstantLightModule):
        pass
    assert lights.names() == ("sg", "sun", "bounce")
    field = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    assert [c.kind for c in field.light.components] == ["sg"]  # no suns nor bounce unless asked for
    with pytest.raises(ValueError, match="unknown light component 'constant'; the kinds are sg, sun, bounce"):
        lights.get("constant")


@pytest.mark.parametrize("brdf", ["tango", "gltf"])
def test_a_fields_render_under_a_sum_is_the_sum_of_its_renders_under_each(with_constant, brdf):
    """The field under its own light (SG lobes and the constant) equals, bit for bit, the sum of
    the field under each component alone (the relighting override), unshadowed and with the SG
    lobes' shares; the same field's SG lobes are those a field without the constant has (the
    constant is built after them from the same seeded draws)."""
    lobe = "fitted" if brdf == "gltf" else "isotropic"
    s = OptimizeSettings(width=16, light_lobes=6, light_init="tango", brdf=brdf, specular_lobe=lobe)
    field = StyleField(s.field_settings()).eval()
    with torch.no_grad():
        field.light.constant.log_radiance.copy_(torch.log(torch.tensor([0.3, 0.2, 0.1])))
    points, normals, view = _hits()
    shares = torch.rand(len(points), 6, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        light = field.light()
        sg, constant = light.components
        for visibility in (None, (shares, None)):
            both = field(points, normals, view, visibility=None if visibility is None else (lambda lt, v=visibility: v))
            only_sg = field(points, normals, view, Light.of(sg), visibility=visibility and (lambda lt: (shares,)))
            only_constant = field(points, normals, view, Light.of(constant))
            for part in ("diffuse", "specular"):
                total = getattr(only_sg.shading, part) + getattr(only_constant.shading, part)
                assert torch.equal(getattr(both.shading, part), total), part
            torch.testing.assert_close(only_constant.shading.diffuse, only_constant.material.albedo * constant.c)
    plain = StyleField(s.field_settings())
    for name, p in plain.light.sg.named_parameters():
        assert torch.equal(getattr(field.light.sg, name), p), name


def test_a_sums_radiance_energy_description_and_arrays_are_its_components(with_constant):
    field = StyleField(OptimizeSettings(width=16, light_lobes=4).field_settings())
    with torch.no_grad():
        light = field.light()
        sg, constant = light.components
        dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
        assert torch.equal(light.radiance(dirs), sg.radiance(dirs) + constant.c)
        assert torch.equal(field.light.energy(), sg.energy() + 4.0 * math.pi * constant.c)
        image = light.equirect(8, 16)
        assert image.shape == (8, 16, 3) and torch.equal(image, Light.of(sg).equirect(8, 16) + constant.c)
    assert [d["kind"] for d in field.light.describe()] == ["sg", "constant"]
    assert field.light.describe()[0]["lobes"] == 4 and all(d["learns"] for d in field.light.describe())
    assert sorted(light.arrays()) == ["amplitude", "axis", "constant_radiance", "sharpness"]
    assert field.light.colour_spread() is not None  # the SG lobes' alone (the constant has none)
    assert torch.equal(field.light.colour_spread(), field.light.sg.colour_spread())
    assert [p.kept for p in field.light.prune(0.5)] == [1]  # the SG lobes prune; the constant does not


def test_holding_an_environment_fits_each_component_to_what_the_others_left():
    """The known-light mode on a sum: the SG lobes fit the map, the constant what they left
    (clamped at zero), each records its fit, and nothing learns after."""
    module = LightModule([SGLightModule(4), ConstantLightModule()])
    record = module.hold("builtin:overcast", iterations=20)
    assert list(record) == ["map", "lobes", "sg_fit_relative_rms", "constant_radiance"]
    assert record["map"] == "builtin:overcast" and record["lobes"] == 4
    assert all(0.0 <= x for x in record["constant_radiance"])
    assert not any(p.requires_grad for p in module.parameters())


def test_a_state_saved_with_the_lobes_at_the_lights_top_loads_under_its_kind():
    """``light.axis_raw`` (a state written before lights were sums) loads as ``light.sg.axis_raw``,
    and the caller's dict is left as it was."""
    s = FieldSettings(light_lobes=3)
    torch.manual_seed(0)
    a, b = build_light(s), build_light(s)
    old = {f"light.{k.removeprefix('sg.')}": v for k, v in a.state_dict().items()}
    kept = dict(old)
    state = b.match_state(old, "light.")
    assert old == kept and sorted(state) == ["light.sg.axis_raw", "light.sg.log_energy", "light.sg.log_sharpness"]


def test_an_optimisation_writes_each_components_arrays_and_figures(with_constant, cache, tmp_path):
    """optimize under a sum (eager): ``light.npz`` holds the environment image and each
    component's arrays, ``meta.json`` each component's figures, and the field file both."""
    s = OptimizeSettings(iterations=2, **TINY)
    meta = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", tmp_path, s, "cpu")
    assert [c["kind"] for c in meta["light_components"]] == ["sg", "constant"]
    assert meta["light_lobes"] == TINY["light_lobes"] and len(meta["light_energy"]) == 3
    with np.load(tmp_path / "light.npz") as z:
        assert sorted(z.files) == ["amplitude", "axis", "constant_radiance", "equirect", "sharpness"]
        assert z["equirect"].shape == (128, 256, 3) and z["constant_radiance"].shape == (3,)
    assert json.loads((tmp_path / "meta.json").read_text())["light_components"][1]["kind"] == "constant"
    state = torch.load(tmp_path / "field.pt", weights_only=True)["state_dict"]
    assert "light.constant.log_radiance" in state and "light.sg.axis_raw" in state
