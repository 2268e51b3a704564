"""The guidance modes (``optimize.guidance``): what the workflow, the plan, the records and the
report know of each mode, one row per mode, without torch.

What a mode computes (its targets, loss, evaluation score and held-out metrics) is its class in
:mod:`stages.guidance.objective`, registered under the same name (``@register("image", "sg")``);
everything else a caller needs to decide about a mode is a field of its row here, so that no
caller compares mode names (``tests/guidance/test_mode_registry.py`` scans the package for such
comparisons). A new mode is one row of :data:`GUIDANCE_MODES` and one registered class; its
``calibration`` must be one that :mod:`stages.training.calibrate` knows, or the plan fails loudly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from ..core.errors import ConfigError
from ..core.provenance import origin_record
from ..core.registry import Registry


@dataclass(frozen=True)
class GuidanceMode:
    """One guidance mode: its name in the config, how results made by it are labelled, and what a
    run of it needs."""

    #: its name in ``optimize.guidance``
    name: str
    #: what it minimises, in the setting's description (schema and configuration reference)
    description: str
    #: the summary's ``guidance`` column and the report's word for it
    label: str
    #: the summary's ``weights`` column of a result it made that is not test-only (``{weights}``:
    #: the weights id; any optimisation setting by name, e.g. ``{target_material}``)
    weights: str
    #: the origin record's label (``{weights}``: the weights id); it starts with an upper-case
    #: warning when the result is not a real stylisation of its prompt
    origin: str
    #: what the plan names as the guide of an optimisation (``{clip}``: the guidance CLIP)
    plan: str
    #: the title of the report's table of its cells (made with real weights)
    table: str
    #: the report page's first line when some of its cells are of this mode (``{n}`` of
    #: ``{total}``); None: nothing to warn of
    banner: str | None
    #: how :mod:`stages.training.calibrate` times one of its steps (a key of its ``CALIBRATIONS``)
    calibration: str
    #: a CLIP guides it (``optimize.clip_*``: its weights unless ``clip_tiny_test``; ``image_size``
    #: its input size)
    uses_clip: bool
    #: it fits image targets of ``optimize.target_material`` rendered by ``optimize.target_renderer``
    #: (Mitsuba's, from the target stage, where that is ``mitsuba``), its class chosen by the renderer
    image_targets: bool
    #: its results are fitted to image targets, not stylised from their prompts (the origin's
    #: ``image_guided``)
    image_guided: bool
    #: the CPU threads one optimisation job of it takes on a CPU run (the optimize rule's
    #: ``threads``; :meth:`~stages.config.workflow.WorkflowConfig.optimize_threads`): a CLIP step
    #: is large matrix products that a second thread shares (1.27x faster on two), an image-target
    #: step thousands of points in small operations that a second thread does not speed up (0.74x
    #: measured), so that two one-thread jobs side by side do more than twice the work of one
    #: two-thread job (``benchmarks/training/threads.py``); on a GPU run every job takes two
    cpu_threads: int

    def weights_label(self, weights: str, test_only: bool, settings: dict[str, Any]) -> str:
        """The summary's ``weights`` column of a result: ``test-only random`` for the test CLIP."""
        return "test-only random" if test_only else self.weights.format(**{**settings, "weights": weights})

    def plan_label(self, settings) -> str:
        """What guides an optimisation of ``settings``, as the plan names it."""
        clip = "the tiny test CLIP" if settings.clip_tiny_test else settings.clip_model
        return self.plan.format(clip=clip)

    def origin_record(self, weights: str, test_only: bool, prompt: str | None = None) -> dict[str, Any]:
        """The origin record of a result this mode made (:func:`~stages.core.provenance.origin_record`)."""
        return origin_record(
            guidance=self.name,
            weights=weights,
            test_only=test_only,
            image_guided=self.image_guided,
            label=self.origin.format(weights=weights),
            prompt=prompt,
        )

    def mitsuba_targets(self, target_renderer: str) -> bool:
        """Whether a run of this mode under ``optimize.target_renderer`` trains on Mitsuba's targets
        (the target stage; Mitsuba must be installed)."""
        return self.image_targets and target_renderer == "mitsuba"


#: every guidance mode, by its name in ``optimize.guidance``
GUIDANCE_MODES: Registry[GuidanceMode] = Registry("guidance mode", ConfigError)
for _mode in (
    GuidanceMode(
        name="clip",
        description="CLIP similarity with the prompt",
        label="CLIP",
        weights="{weights}",
        origin="CLIP-guided ({weights})",
        plan="{clip}",
        table="CLIP-guided with real weights",
        banner=None,
        calibration="clip",
        uses_clip=True,
        image_targets=False,
        image_guided=False,
        cpu_threads=2,
    ),
    GuidanceMode(
        name="image",
        description="squared error against image targets of target_material",
        label="image-guided (procedural targets)",
        weights="image-guided ({target_material} target)",
        origin="IMAGE-GUIDED: fitted to image targets, not text-guided ({weights})",
        plan="image targets",
        table="Image-guided (procedural targets; verification, no CLIP)",
        banner=(
            "IMAGE-GUIDED: {n} of {total} cells were fitted to renders of procedural target materials "
            "(a verification run without CLIP), not stylised from their prompts."
        ),
        calibration="own_targets",
        uses_clip=False,
        image_targets=True,
        image_guided=True,
        cpu_threads=1,
    ),
):
    GUIDANCE_MODES.register(_mode.name, _mode)

#: the names ``optimize.guidance`` takes (the setting's type: the schema's choices)
GuidanceName = Annotated[str, GUIDANCE_MODES]
#: the setting's description, from the modes' own
GUIDANCE_DOC = " or ".join(f"{m.name} ({m.description})" for m in GUIDANCE_MODES.values())


def guidance_mode(name: str) -> GuidanceMode:
    """The mode named ``name`` (``optimize.guidance``); an unknown name is a :class:`ConfigError`."""
    return GUIDANCE_MODES[name]


def mode_of_label(label: str) -> GuidanceMode | None:
    """The mode whose summary label (:attr:`GuidanceMode.label`) is ``label``; None for another text."""
    return next((m for m in GUIDANCE_MODES.values() if m.label == label), None)
