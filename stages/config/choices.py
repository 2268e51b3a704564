"""The choices a front end offers its user (the Blender add-on's menus), from the one place each is
defined: ``python -m stages.config.choices`` prints them as JSON.

* ``presets``: each optimisation preset (:data:`~stages.config.presets.PRESETS`) with its steps
  (the preset's ``iterations``, else ``optimize.iterations``' default) and the optimisation's
  measured wall time (:func:`preset_seconds`), and the ``default_preset``;
* ``materials``: the procedural materials an image-guided run recovers
  (:data:`~stages.config.sections.MATERIALS`);
* ``uv_layouts``: the values of ``bake.uv`` (:data:`~stages.config.sections.UV_LAYOUTS`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ..core.safefiles import read_json
from .presets import DEFAULT_PRESET, PRESETS
from .sections import MATERIALS, UV_LAYOUTS, OptimizeSettings

#: the presets' measured quality and optimisation time (benchmarks/quality/recovery.py writes it)
PRESET_COSTS = Path(__file__).resolve().parents[2] / "benchmarks" / "figures" / "preset_costs.json"
#: the settings that set what an optimisation costs
COST_KEYS = ("iterations", "views_per_step", "crops", "width")


def preset_steps() -> dict[str, int]:
    """Each preset's optimisation steps: its own ``iterations``, else ``optimize.iterations``' default."""
    default = OptimizeSettings().iterations
    return {name: int(p.get("iterations", default)) for name, p in PRESETS.items()}


def _cost(preset: dict) -> tuple:
    defaults = OptimizeSettings()
    return tuple(preset.get(k, getattr(defaults, k)) for k in COST_KEYS)


def preset_seconds(costs: dict | None = None) -> dict[str, dict]:
    """Each preset's measured optimisation wall time: ``{"seconds": [low, high], "as": measured preset,
    "measured": when and where}`` from :data:`PRESET_COSTS`, a preset without its own figures taking
    those of a measured preset of the same cost (:data:`COST_KEYS`: ``rough`` and ``metal`` cost what
    ``paper`` does); a preset of no measured cost is left out."""
    if costs is None:
        costs = read_json(PRESET_COSTS) if PRESET_COSTS.is_file() else {}
    measured = {name: p["seconds"] for name, p in costs.get("presets", {}).items() if p.get("seconds") and name in PRESETS}
    out = {}
    for name, preset in PRESETS.items():
        same = name if name in measured else next((m for m in measured if _cost(PRESETS[m]) == _cost(preset)), None)
        if same is not None:
            times = measured[same]
            out[name] = {"seconds": [min(times), max(times)], "as": same, "measured": costs.get("measured", "")}
    return out


def preset_help() -> str:
    """One phrase per preset for a ``--preset`` help: its steps and measured time."""
    seconds = preset_seconds()
    parts = []
    for name, steps in preset_steps().items():
        t = seconds.get(name)
        said = f"{steps:,} steps"
        if t:
            low, high = (round(x / 60, 1) if t["seconds"][1] >= 120 else round(x) for x in t["seconds"])
            unit = "min" if t["seconds"][1] >= 120 else "s"
            said += f", {low}-{high} {unit}" + (f" as {t['as']}" if t["as"] != name else "")
        parts.append(f"{name} ({said})")
    return ", ".join(parts)


def choices() -> dict:
    """The choices (module docstring) as a JSON-ready dictionary."""
    seconds = preset_seconds()
    return {
        "presets": {name: {"iterations": n, **seconds.get(name, {})} for name, n in preset_steps().items()},
        "default_preset": DEFAULT_PRESET,
        "materials": list(MATERIALS),
        "uv_layouts": list(UV_LAYOUTS),
    }


def main(argv: list[str] | None = None) -> int:
    """Print :func:`choices` as one line of JSON."""
    if argv if argv is not None else sys.argv[1:]:
        sys.stderr.write("usage: python -m stages.config.choices (no arguments): prints the choices as JSON\n")
        return 2
    sys.stdout.write(json.dumps(choices()) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
