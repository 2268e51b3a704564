"""The BRDF models, one module each (``tango.py``, ``gltf.py``) with one object of
:class:`~stages.render.brdf.base.Brdf`, found by name: :func:`get`, :func:`names`.

The names are the rows of :mod:`stages.config.brdfs` (the settings' view of each model, without
torch), one registry for both: a new model is one row there and one module here whose object this
registry lists (``tests/render/test_brdf_registry.py`` holds the two to each other, and scans the
library for comparisons of BRDF names outside them). Every caller asks a model's object: the
networks for its heads and channels, the field and the bake for its shading, the exporters and the
round trip for its textures, extensions and wiring.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from contextlib import contextmanager

from ...config.brdfs import BRDFS, BrdfSpec, brdf_spec
from .base import Brdf, Channels
from .gltf import GLTF
from .tango import TANGO

#: each model's object by name (filled as they are asked for: :func:`get`)
_MODELS: dict[str, Brdf] = {model.name: model for model in (TANGO, GLTF)}

__all__ = ["GLTF", "TANGO", "Brdf", "Channels", "get", "names", "temporarily"]


def get(name: str | Brdf) -> Brdf:
    """The object of the BRDF ``name`` (``optimize.brdf``; an object is returned as it is); a
    ValueError naming the choices for any other name."""
    if isinstance(name, Brdf):
        return name
    spec = brdf_spec(name)  # (an unknown name: the settings' error)
    model = _MODELS.get(spec.name)
    if model is None:  # a model's module is named after it and holds its object as MODEL
        model = _MODELS[spec.name] = importlib.import_module(f"{__name__}.{spec.name}").MODEL
    return model


@contextmanager
def temporarily(spec: BrdfSpec, model: Brdf) -> Iterator[Brdf]:
    """``model`` registered with its row ``spec`` for the block (a test's or a recipe's toy BRDF),
    both removed after it."""
    if model.name != spec.name:
        raise ValueError(f"the object {model!r} is not the model of the row {spec.name!r}")
    with BRDFS.temporarily(spec.name, spec):
        _MODELS[spec.name] = model
        try:
            yield model
        finally:
            del _MODELS[spec.name]


def names() -> tuple[str, ...]:
    """The BRDFs' names, in the settings' order (the rows of :data:`stages.config.brdfs.BRDFS`)."""
    return tuple(BRDFS)
