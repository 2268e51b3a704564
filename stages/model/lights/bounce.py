"""The light component of kind ``bounce``: one bounce of the mesh's own light
(:class:`~stages.render.light.bounce.BounceLight`), where ``optimize.bounces`` asks for it.

It learns nothing: its table (the diffuse radiance each face side sends) is refreshed from the
field as the material learns (:func:`~stages.model.bounce.bounce_table`, every
``optimize.bounce_every`` steps) and kept in the field's state, so that a loaded field renders
what it was trained with. It has no part in a known light's fit (a map holds no bounce).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ...config.sections import FieldSettings
from ...render.light.bounce import BounceLight
from .base import LightComponentModule


class BounceModule(LightComponentModule):
    """The table of one bounce (``table (2 F, 3)``, a buffer: empty until the first refresh, when
    it adds nothing) and the first hits per point it is read through (``samples``)."""

    kind = "bounce"
    #: last: it takes nothing of a map
    fit_order = 10

    def __init__(self, samples: int = 16) -> None:
        super().__init__()
        self.samples = samples
        self.register_buffer("table", torch.zeros(0, 3))

    @classmethod
    def build(cls, settings: FieldSettings) -> BounceModule | None:
        """A bounce where ``optimize.bounces`` (as resolved) is 1, read through ``bounce_samples`` hits."""
        if settings.bounces == "auto":
            raise ValueError("optimize.bounces: auto is decided before a field is built (stages.model.bounce.resolve_bounces)")
        return cls(settings.bounce_samples) if settings.bounces else None

    def forward(self) -> BounceLight:
        return BounceLight(self.table, self.samples)

    @torch.no_grad()
    def set_table(self, table: Tensor) -> None:
        """Take ``table (2 F, C)`` (the refresh's :func:`~stages.model.bounce.bounce_table`)."""
        self.table = table.detach().to(self.table.device, self.table.dtype).clone()

    def fit(self, env: np.ndarray, iterations: int) -> dict:
        """Nothing to fit: a map holds no bounce."""
        return {}

    def left_of(self, env: np.ndarray) -> np.ndarray:
        """The map as it is (it takes nothing of it)."""
        return env

    def match_state(self, state: dict, prefix: str, parent: str) -> None:
        """Its table at the saved one's size (the mesh's face sides), before loading."""
        saved = state.get(f"{prefix}table")
        if saved is not None and saved.shape != self.table.shape:
            self.table = torch.zeros_like(saved, device=self.table.device)
