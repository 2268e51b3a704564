"""The choices a front end offers its user (the Blender add-on's menus), from the one place each is
defined: ``python -m stages.config.choices`` prints them as JSON.

* ``presets``: each optimisation preset (:data:`~stages.config.presets.PRESETS`) with its steps
  (the preset's ``iterations``, else ``optimize.iterations``' default), and the ``default_preset``;
* ``materials``: the procedural materials an image-guided run recovers
  (:data:`~stages.config.sections.MATERIALS`);
* ``uv_layouts``: the values of ``bake.uv`` (:data:`~stages.config.sections.UV_LAYOUTS`).
"""

from __future__ import annotations

import json
import sys

from .presets import DEFAULT_PRESET, PRESETS
from .sections import MATERIALS, UV_LAYOUTS, OptimizeSettings


def preset_steps() -> dict[str, int]:
    """Each preset's optimisation steps: its own ``iterations``, else ``optimize.iterations``' default."""
    default = OptimizeSettings().iterations
    return {name: int(p.get("iterations", default)) for name, p in PRESETS.items()}


def choices() -> dict:
    """The choices (module docstring) as a JSON-ready dictionary."""
    return {
        "presets": {name: {"iterations": n} for name, n in preset_steps().items()},
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
