"""Before any job runs: the judges a run needs, found or named with what to install.

A config that renders Mitsuba targets (image guidance with ``target_renderer: mitsuba``) needs
Mitsuba 3, in the variant its ``target.variant`` asks for; one that enables the ``roundtrip``
stage needs Blender. Without them the run would fail hours in (after the optimisations), so the
workflow asks :func:`missing_judges` when it starts and stops at once with its messages. A missing
libLLVM is no reason to stop: ``variant: auto`` falls back to ``scalar_rgb`` (slower; the doctor
says how much)."""

from __future__ import annotations

import importlib.util

from .blender import INSTALL_HINT, BlenderUnavailable, find_blender
from .mitsuba import choose_variant


def missing_judges(mitsuba_variants: set[str], roundtrip_cells: int) -> list[str]:
    """One message per judge the run needs and cannot have: ``mitsuba_variants`` are the
    ``target.variant`` settings of the meshes that get Mitsuba targets (empty: none needed),
    ``roundtrip_cells`` the cells with the round trip enabled. [] when all are there."""
    problems = []
    if mitsuba_variants:
        if importlib.util.find_spec("mitsuba") is None:
            problems.append(
                "This run renders image targets with Mitsuba 3 (image guidance), which is not installed. "
                "Install it: pip install -e '.[reference]' (bash scripts/setup.sh does), then run again."
            )
        else:
            for variant in sorted(mitsuba_variants):
                try:
                    choose_variant(variant)
                except ImportError as exc:
                    problems.append(f"target.variant: {variant}: {exc}.")
    if roundtrip_cells:
        try:
            find_blender()
        except BlenderUnavailable as exc:
            reason = str(exc).split(";")[0]
            problems.append(
                f"This run imports its assets into Blender (roundtrip: enabled in {roundtrip_cells} cell(s)): "
                f"{reason}. To get it: {INSTALL_HINT}. "
                "Or run without the round trip: set roundtrip: {enabled: false} in the config, or add the "
                "overlay config/overlays/no-blender.yaml after it (--configfile <config> config/overlays/no-blender.yaml)."
            )
    return problems
