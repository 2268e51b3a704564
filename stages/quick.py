"""quick: stylise one's own mesh without writing YAML.

    python -m stages.quick MESH "PROMPT" [--preset fast|balanced|paper|...] [--image-guided MATERIAL | --test-clip]
                           [--uv auto|keep|second|atlas] [--name NAME] [--overlay FILE]...
                           [--cores N] [--dry-run]

1. checks the mesh the way the normalize stage reads it (a missing, empty, unreadable or faceless
   file stops here, with what to do);
2. writes a small experiment config, ``config/quick/<name>.yaml`` (``--config-dir`` elsewhere):
   the mesh by its absolute path, the prompt, the preset and the guidance; the config is validated
   like any other before it is written;
3. prints what it will run and the command that runs it again, with the UV layout the bake will
   write into (``--uv``, ``bake.uv``: the input's own where it is usable, measured here, else for
   a glTF input a second UV set beside it; ``--uv keep`` on a layout that is not usable stops
   here, with what is wrong);
4. starts Snakemake on that config (``--dry-run``: prints the plan, with its time estimate, and
   stops). Snakemake checks the CLIP weights before any job (without them it stops at once with one
   message per model) and prints the plan with its time estimate.

The result is an ordinary experiment: ``results/<name>/``, its report in ``results/<name>/report/``,
and ``snakemake --workflow-profile profiles/slurm --configfile config/quick/<name>.yaml`` runs it on
a cluster. ``--image-guided wood`` needs no CLIP weights: it recovers the procedural material from
targets path-traced by Mitsuba (every output says so); ``--test-clip`` guides by the tiny random test
CLIP (every output is marked TEST ONLY).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shlex
import subprocess
import sys
import unicodedata
from dataclasses import dataclass
from pathlib import Path

import yaml

from .assets.layouts import choose_layout
from .config.choices import preset_help
from .config.presets import DEFAULT_PRESET, PRESETS
from .config.schema import schema
from .config.sections import MATERIALS, UP_AXES, UV_LAYOUT_WORDS, UV_LAYOUTS, BakeSettings
from .config.workflow import (
    CONTROL,
    EXPERIMENT_RE,
    WorkflowConfig,
    experiment_name,
    merge_config,
    path_problem,
    read_yaml,
)
from .core.cli import stage_main
from .core.errors import ConfigError
from .core.provenance import atomic_path
from .geometry.meshio import load_mesh
from .geometry.normalization import check_face_count, normalize_mesh

log = logging.getLogger(__name__)

#: the workflow (results and configs go under the working directory, as with snakemake itself)
SNAKEFILE = Path(__file__).resolve().parents[1] / "Snakefile"
#: where the configs go (relative to the working directory)
CONFIG_DIR = Path("config/quick")
#: mesh ids that would put a cell's folder where the report's own folders are (results/<experiment>/report/)
RESERVED_MESH_IDS = ("report",)


def slug(text: str, limit: int) -> str:
    """``text`` as an id the config accepts: letters, digits, ``_``, ``.`` and ``-``, starting with a
    letter or digit, at most ``limit`` characters (``"a vase made of wood"`` -> ``"a-vase-made-of-wood"``;
    accents dropped: ``"Stühle"`` -> ``"Stuhle"``). Text with no such character at all becomes
    ``x-`` and 8 hex digits of its SHA-256, so that two such texts do not share an id."""
    ascii_text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    s = re.sub(r"[^A-Za-z0-9_.-]+", "-", ascii_text).strip("-._")[:limit].strip("-._")
    return s or f"x-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


def max_id() -> int:
    """The longest id the config schema accepts."""
    return int(schema()["$defs"]["id"]["maxLength"])


def mesh_entry(mesh: str) -> tuple[str, dict]:
    """The config's id and entry for the mesh argument: a file (by its absolute path) or a built-in
    mesh (``builtin:vase``)."""
    if mesh.startswith("builtin:"):
        name = mesh.split(":", 1)[1]
        return name, {"builtin": name}
    path = Path(mesh)
    mesh_id = slug(path.stem, 32)
    if mesh_id.lower() in RESERVED_MESH_IDS:  # the config refuses them in any case (Report, REPORT)
        mesh_id += "-mesh"
    return mesh_id, {"path": str(path.resolve()), "object": path.stem.replace("_", " ")}


def experiment_config(request: Request, name: str) -> dict:
    """The experiment config of the request's mesh and prompt (one cell: the mesh's id is its file's
    stem, the prompt's id the prompt made an id, :func:`slug`; variant ``base``), with the bake's UV
    layout and overlap threshold and the mesh's up axis where the request names them."""
    mesh, prompt, preset, image_guided, test_clip = (
        request.mesh,
        request.prompt,
        request.preset,
        request.image_guided,
        request.test_clip,
    )
    mesh_id, entry = mesh_entry(mesh)
    if request.up_axis is not None:
        entry["normalize"] = {"up_axis": request.up_axis}
    prompt_entry: dict = {"text": prompt, "preset": preset}
    config: dict = {"experiment": name, "meshes": {mesh_id: entry}, "prompts": {slug(prompt, 40): prompt_entry}}
    if image_guided:
        prompt_entry["optimize"] = {"guidance": "image", "target_material": image_guided}
        config["metrics"] = {"clip": False}  # no CLIP weights are needed: image-target metrics only
    if test_clip:
        config["optimize"] = {"clip_tiny_test": True}
        config["metrics"] = {**config.get("metrics", {}), "clip_tiny_test": True}
    bake = {"uv": request.uv, "uv_max_overlap": request.uv_max_overlap}
    if any(v is not None for v in bake.values()):
        config["bake"] = {k: v for k, v in bake.items() if v is not None}
    return config


#: the config's first lines: fixed text only (a path or a prompt spliced into a comment could end
#: the comment with a character YAML reads as a line break, U+2028 say, and become a key)
HEADER = (
    "# Written by python -m stages.quick (it prints the command that made this file).\n"
    "# An ordinary experiment config: edit it, or run it with snakemake --configfile <this file>\n"
)


class _Dumper(yaml.SafeDumper):
    """PyYAML's safe dumper, writing every text that holds a control character, a line or
    paragraph separator or a bidirectional control in double quotes, where YAML escapes what it
    reads as a line break (it would otherwise write U+0085 bare, and read it back as a space)."""

    def choose_scalar_style(self):
        if isinstance(self.event, yaml.ScalarEvent) and CONTROL.search(self.event.value or ""):
            return '"'
        return super().choose_scalar_style()


def check_path_argument(what: str, text: str, mesh: bool = False) -> None:
    """Refuse a path argument that holds, in any of its components (the working directory's
    among them, where it is relative), a character that makes a name look other than it is, or
    (``mesh``, whose path the config carries) a brace: one line naming the argument and the
    character."""
    absolute = os.path.abspath(text)
    if CONTROL.search(absolute) or (mesh and re.search(r"[{}]", absolute)):
        raise ConfigError(f"{what} {ascii(absolute)[:200]} {path_problem(absolute)}")


def write_config(config: dict, path: Path, force: bool = False) -> None:
    """``config`` as YAML at ``path`` (atomically): :data:`HEADER`, then every value, path and
    text as the YAML dumper writes it (quoted and escaped where YAML needs it). An existing file
    with the same settings is left as it is (comments and all); one with other settings (edited
    by hand, or another mesh or prompt under the same name) is kept unless ``force``."""
    if path.is_file():
        try:
            old = read_yaml(path)
        except ConfigError:
            old = None
        if old == config:
            return
        if not force:
            raise ConfigError(
                f"{path} exists with other settings (edited, or another mesh or prompt of the same name); "
                f"run it as it is with snakemake --configfile {shlex.quote(str(path))}, pick another --name, or pass --force "
                "to replace it"
            )
    with atomic_path(path) as tmp:
        tmp.write_text(HEADER + yaml.dump(config, Dumper=_Dumper, sort_keys=False, allow_unicode=True), encoding="utf-8")


def check_name(name: str, path: Path, force: bool) -> None:
    """Refuse an experiment name that another experiment owns: a config of the repository's
    (``config/<name>.yaml``), or results made from another config file."""
    if not EXPERIMENT_RE.fullmatch(name) or len(name) > max_id():
        raise ConfigError(f"--name {name!r}: use letters, digits, '_', '.', '+' or '-' (for example {slug(name, max_id())!r})")
    if Path("config", f"{name}.yaml").is_file() and Path("config", f"{name}.yaml").resolve() != path.resolve():
        raise ConfigError(f"experiment {name!r} is config/{name}.yaml's: pick another --name")
    if Path("results", name).is_dir() and not path.is_file() and not force:
        raise ConfigError(
            f"results/{name}/ holds another config's experiment (no {path} made it): pick another --name, or pass --force"
        )


def guidance_text(cfg: WorkflowConfig, image_guided: str | None, test_clip: bool) -> str:
    """What guides the run, in words (from the resolved settings of its first cell)."""
    if image_guided:
        return f"image-guided: recovers the procedural material '{image_guided}' from Mitsuba renders (no CLIP weights needed)"
    if test_clip:
        return "the tiny random test CLIP (results marked TEST ONLY)"
    cell = cfg.cells[0]
    return f"CLIP {cfg.optimize_settings(cell.prompt, cell.variant).clip_model} (needs its weights)"


def workflow_args(cores: int | None = None) -> str:
    """The Snakemake options the printed commands need from the working directory: the workflow
    and its Slurm profile by absolute path unless it is the repository's root."""
    here = Path.cwd().resolve() == SNAKEFILE.parent
    snakefile = "" if here else f"--snakefile {SNAKEFILE} "
    if cores is None:
        profile = "profiles/slurm" if here else str(SNAKEFILE.parent / "profiles" / "slurm")
        return f"{snakefile}--workflow-profile {profile}"
    return f"{snakefile}--cores {cores}"


def layout_text(cfg: WorkflowConfig, mesh: str) -> str:
    """The UV layout the bake of the config's first cell will write into, and why, decided as the
    bake stage decides (:func:`~stages.assets.layouts.choose_layout`) on the mesh as the normalize
    stage writes it; a decimated mesh (``decimate.enabled``) is baked into a new atlas."""
    mesh_id = mesh_entry(mesh)[0]
    cell = cfg.cells[0]
    bake = cfg.cell_stage_settings("bake", cell.prompt, cell.variant)
    if bake.uv != "atlas" and cfg.decimated(mesh_id):
        why = "the mesh is decimated before tracing (decimate.enabled), so its asset has other faces"
        if bake.uv == "keep":
            raise ConfigError(f"--uv keep: {why}; set decimate.enabled: false, or use --uv auto")
        return f"a new atlas ({why})"
    normalized = normalize_mesh(mesh, cfg.stage_settings(mesh_id, "normalize"))
    traced = normalized.mesh
    choice, _ = choose_layout(bake.uv, mesh, normalized.transform, traced, bake.size_for(len(traced.faces)), bake.uv_max_overlap)
    return f"{UV_LAYOUT_WORDS[choice.layout]} ({choice.why})"


@dataclass(frozen=True)
class Request:
    """What the user asks for: a ``mesh`` (a file, or ``builtin:<name>``) and a ``prompt``, the
    optimisation ``preset``, the guidance (CLIP, ``image_guided`` by a procedural material, or the
    tiny ``test_clip``), the experiment's ``name`` (default: the mesh's stem and the prompt) and
    the bake's ``uv`` layout (``bake.uv``; None: the config's, ``auto``), its ``uv_max_overlap``
    and the mesh's ``up_axis`` (``normalize.up_axis``; None: the config's)."""

    mesh: str
    prompt: str
    preset: str = DEFAULT_PRESET
    image_guided: str | None = None
    test_clip: bool = False
    name: str | None = None
    uv: str | None = None
    uv_max_overlap: float | None = None
    up_axis: str | None = None


@dataclass(frozen=True)
class Launch:
    """Where the config goes (``config_dir``, with ``overlays`` laid over it) and how the workflow
    runs: on ``cores`` cores, or only its plan (``dry_run``); ``force`` replaces a config of the same
    name."""

    config_dir: Path = CONFIG_DIR
    overlays: tuple[Path, ...] = ()
    cores: int = 2
    dry_run: bool = False
    force: bool = False


def run(request: Request, launch: Launch = Launch()) -> int:
    """Check the request's mesh, write its experiment config, say what will run and run it (see
    the module docstring); returns Snakemake's exit status (or the plan's, with ``dry_run``).
    Nothing is written when an argument or the mesh is bad."""
    mesh, prompt, preset, image_guided = request.mesh, request.prompt, request.preset, request.image_guided
    overlays, cores = launch.overlays, launch.cores
    if not mesh.startswith("builtin:"):
        check_path_argument("the mesh", mesh, mesh=True)
    check_path_argument("--config-dir", str(launch.config_dir))
    for overlay in overlays:
        check_path_argument("--overlay", str(overlay))
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}: use one of {', '.join(sorted(PRESETS))}")
    if request.uv is not None and request.uv not in UV_LAYOUTS:
        raise ConfigError(f"unknown UV layout {request.uv!r} for --uv: use one of {', '.join(UV_LAYOUTS)}")
    if image_guided is not None and image_guided not in MATERIALS:
        raise ConfigError(f"unknown material {image_guided!r} for --image-guided: use one of {', '.join(MATERIALS)}")
    if not prompt.strip():
        raise ConfigError('the prompt is empty: say what the object should look like, e.g. "a vase made of wood"')
    if len(prompt) > 2000:
        raise ConfigError(f"the prompt is {len(prompt)} characters long; CLIP reads about 77 tokens: shorten it")
    checked = load_mesh(mesh, given_in=f"the command (relative paths start at {Path.cwd()})")  # raises with what to do
    name = request.name or slug(f"{mesh_entry(mesh)[0]}-{slug(prompt, 40)}", max_id())
    path = Path(launch.config_dir) / f"{name}.yaml"
    check_name(name, path, launch.force)
    config = experiment_config(request, name)
    configfiles = [path, *overlays]
    merged = config
    for overlay in overlays:
        merged = merge_config(merged, read_yaml(overlay))
    cfg = WorkflowConfig(merged, ", ".join(map(str, configfiles)))  # validated as the workflow will, before writing
    check_face_count(mesh, checked, cfg.stage_settings(mesh_entry(mesh)[0], "normalize"))  # as the normalize stage will
    experiment = experiment_name(cfg.raw, configfiles)
    guidance = guidance_text(cfg, image_guided, request.test_clip)
    layout = layout_text(cfg, mesh)  # raises where bake.uv: keep cannot keep the layout
    write_config(config, path, launch.force)
    files = " ".join(shlex.quote(str(p)) for p in configfiles)
    lines = [
        f"mesh {mesh}: {len(checked.vertices):,} vertices, {len(checked.faces):,} faces",
        f'prompt "{prompt}", preset {preset}, {guidance}',
        f"UV layout: {layout}",
        f"config: {path} (experiment {experiment}); results in results/{experiment}/, the report in "
        f"results/{experiment}/report/index.html",
        f"the same run again: snakemake {workflow_args(cores)} --configfile {files}",
        f"on a Slurm cluster: snakemake {workflow_args()} --configfile {files}",
    ]
    sys.stdout.write("\n".join(lines) + "\n")
    sys.stdout.flush()
    if launch.dry_run:
        cmd = [sys.executable, "-m", "stages.plan", "--configfile", *map(str, configfiles), "--cores", str(cores)]
        cmd += ["--no-calibrate"] if os.environ.get("TANGO_PLAN_CALIBRATE") == "0" else []  # as the workflow's plan
    else:
        cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE), "--cores", str(cores)]
        cmd += ["--configfile", *map(str, configfiles)]
    # the stages' own `python -m` must find this interpreter's packages first
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run(cmd, env=env).returncode


def main(argv: list[str] | None = None) -> int:
    result = {}

    def arguments(parser):
        parser.add_argument("mesh", help="the mesh file (OBJ, PLY, STL, OFF, GLB, GLTF), or builtin:vase|candle|knot")
        parser.add_argument("prompt", help='what it should look like, e.g. "a vase made of wood"')
        presets = (
            f"optimisation preset: {preset_help()} (default {DEFAULT_PRESET}; the times: one optimisation under image "
            "guidance on a 2-core CPU, measured; --dry-run estimates this mesh's here)"
        )
        parser.add_argument("--preset", default=DEFAULT_PRESET, help=presets)  # an unknown one: the run's own one-line error
        guidance = parser.add_mutually_exclusive_group()
        guidance.add_argument("--image-guided", metavar="MATERIAL", help=f"no CLIP: recover one of {', '.join(MATERIALS)}")
        guidance.add_argument("--test-clip", action="store_true", help="the tiny random test CLIP (results marked TEST ONLY)")
        parser.add_argument("--uv", choices=UV_LAYOUTS, help="the UV layout baked into (bake.uv; default auto)")
        parser.add_argument(
            "--uv-max-overlap",
            type=float,
            metavar="SHARE",
            help=f"the share of faces (0-1) that may overlap in the input's UV layout for it to be kept (bake.uv_max_overlap; "
            f"default {BakeSettings().uv_max_overlap:g})",
        )
        parser.add_argument(
            "--up-axis",
            choices=("auto", *UP_AXES),
            help="the mesh's up axis, turned to +y (normalize.up_axis; default +y; auto: the format's or a guess)",
        )
        parser.add_argument("--name", help="experiment name (default: the mesh's stem and the prompt)")
        parser.add_argument("--config-dir", type=Path, default=CONFIG_DIR, help=f"where the config goes (default {CONFIG_DIR})")
        parser.add_argument(
            "--overlay", type=Path, action="append", default=[], help="a config file laid over the written one (repeatable)"
        )
        parser.add_argument("--cores", type=int, default=2, help="CPU cores Snakemake may use (default 2)")
        parser.add_argument("--dry-run", action="store_true", help="write the config and print the plan; run nothing")
        parser.add_argument("--force", action="store_true", help="replace an existing config of this name with other settings")

    def body(args):
        request = Request(
            args.mesh,
            args.prompt,
            args.preset,
            args.image_guided,
            args.test_clip,
            args.name,
            args.uv,
            args.uv_max_overlap,
            args.up_axis,
        )
        launch = Launch(args.config_dir, tuple(args.overlay), args.cores, args.dry_run, args.force)
        result["code"] = run(request, launch)

    status = stage_main("quick", __doc__, arguments, body, argv)
    return status or result.get("code", 0)


if __name__ == "__main__":
    raise SystemExit(main())
