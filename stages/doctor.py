"""doctor: check, in a few seconds, what a run of a config needs, and say how to fix each missing piece.

    python -m stages.doctor [--configfile config/config.yaml [overlay.yaml ...]] [--json]

Checked: the torch build and the device the config's torch stages will use; the ray tracer
(Embree through embreex), pymeshlab (decimation), xatlas (texture atlases), usd-core and
pygltflib (the asset formats); the CLIP weights of the models the config needs (guidance and
evaluation, one line each); Node.js with the bundled model-viewer (the report's 3D viewers) and
the glTF validator; the independent judges, Mitsuba 3 (with libLLVM for its fast CPU variant)
and Blender; Chromium (the browser tests); and the cluster pieces (Slurm's commands and the
Snakemake executor plugin). A piece is *needed* when this config's run would fail without it, else
*optional* (what it adds is said). Exit status 1 when a needed piece is missing, else 0.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import logging
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from .config.workflow import load_config_files
from .core.cli import bf16_support, resolve_device, stage_main
from .guidance.clip import ClipWeightsUnavailable, resolve_weights
from .reference.blender import INSTALL_HINT, BlenderUnavailable, find_blender
from .reference.mitsuba import find_libllvm

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
SETUP = "bash scripts/setup.sh"


@dataclass
class Check:
    name: str
    ok: bool
    needed: bool
    detail: str
    fix: str = ""

    @property
    def status(self) -> str:
        return "ok" if self.ok else "MISSING" if self.needed else "optional"


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def _run(cmd: list[str], timeout: float = 5.0) -> str | None:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return (out.stdout or out.stderr).strip().splitlines()[0] if out.returncode == 0 and (out.stdout or out.stderr) else None


def check_torch(cfg) -> Check:
    import torch

    device = resolve_device(cfg.device if cfg.device != "auto" else "auto")
    build = f"CUDA {torch.version.cuda} build" if torch.version.cuda else "CPU build"
    gpu = f"{torch.cuda.device_count()} GPU(s): {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else "no GPU"
    bf16, why = bf16_support(device)
    detail = (
        f"torch {torch.__version__} ({build}, {gpu}); this config's torch stages run on {device.type} "
        f"(device: {cfg.device}); {torch.get_num_threads()} CPU threads; bfloat16: {why}"
    )
    if cfg.device == "cuda" and not torch.cuda.is_available():
        return Check(
            "torch and device",
            False,
            True,
            detail,
            "device: cuda but torch sees no GPU: install a CUDA build of torch (README, 'GPU') or set device: auto",
        )
    return Check("torch and device", True, True, detail)


def check_module(name: str, module: str, dist: str, what: str, fix: str, needed: bool = True) -> Check:
    found = importlib.util.find_spec(module) is not None
    version = _version(dist)
    if found:
        return Check(name, True, needed, f"{dist} {version or '(version unknown)'}: {what}")
    return Check(name, False, needed, f"{dist} is not installed: {what}", fix)


def check_clip(cfg) -> list[Check]:
    specs = cfg.clip_specs()
    if not specs:
        return [Check("CLIP weights", True, False, "this config needs no real CLIP weights (image guidance or the test CLIP)")]
    out = []
    for spec in specs:
        role = "guidance" if spec.section == "optimize" else "evaluation"
        name = f"CLIP weights ({role})"
        try:
            path, weights_id, _ = resolve_weights(spec)
        except ClipWeightsUnavailable as exc:
            first, _, rest = str(exc).partition("\n")
            out.append(Check(name, False, True, first, rest))
        else:
            out.append(Check(name, True, True, f"{weights_id} for {spec.section}: {path}"))
    return out


def check_node() -> list[Check]:
    node = shutil.which("node")
    viewer = REPO / "node_modules" / "@google" / "model-viewer" / "dist" / "model-viewer-umd.min.js"
    validator = REPO / "node_modules" / "gltf-validator"
    fix = f"install Node.js and npm (Debian: apt-get install nodejs npm), then rerun {SETUP} (it runs npm ci)"
    if node is None:
        return [
            Check(
                "Node.js and the report's viewer",
                False,
                False,
                "node not found: the report shows static previews "
                "instead of 3D viewers, and the export skips the Khronos glTF validator",
                fix,
            )
        ]
    version = _run([node, "--version"]) or "?"
    missing = [p.name for p in (viewer, validator) if not p.exists()]
    if missing:
        return [
            Check(
                "Node.js and the report's viewer",
                False,
                False,
                f"node {version}, but {', '.join(missing)} not installed "
                "in node_modules: no 3D viewers in the report / no glTF validation",
                f"run {SETUP} (or npm ci)",
            )
        ]
    return [
        Check(
            "Node.js and the report's viewer",
            True,
            False,
            f"node {version}; model-viewer and the Khronos glTF validator in node_modules",
        )
    ]


def check_mitsuba(cfg) -> Check:
    needed = any(cfg.target_material(c.prompt, c.variant) for c in cfg.cells)
    use = "renders this config's image targets" if needed else "the ground-truth judge of image-guided runs (not used here)"
    version = _version("mitsuba")
    fix = f"pip install -e '.[reference]' ({SETUP} installs it)"
    if version is None:
        return Check("Mitsuba 3", False, needed, f"mitsuba is not installed: it {use}", fix)
    lib = find_libllvm()
    if lib is None:
        return Check(
            "Mitsuba 3",
            True,
            needed,
            f"mitsuba {version} ({use}); no libLLVM 16+: only the slow scalar_rgb variant "
            "(apt-get install libllvm19 for llvm_ad_rgb)",
        )
    return Check("Mitsuba 3", True, needed, f"mitsuba {version} with {lib} (llvm_ad_rgb): {use}")


def check_blender(cfg) -> Check:
    needed = any(cfg.cell_stage_settings("roundtrip", c.prompt, c.variant).enabled for c in cfg.cells)
    use = "this config's roundtrip stage imports the assets into it" if needed else "the asset judge (roundtrip stage, off here)"
    try:
        cmd = find_blender()
    except BlenderUnavailable as exc:
        return Check("Blender", False, needed, f"{exc}: {use}".split(";")[0], INSTALL_HINT)
    if len(cmd) == 1:  # a Python with bpy: read its version without importing bpy (seconds)
        version = _run([cmd[0], "-c", "import importlib.metadata as m; print('bpy', m.version('bpy'))"])
    else:
        version = _run([cmd[0], "--version"], timeout=30)
    if version is None:
        return Check("Blender", False, needed, f"{cmd[0]} does not answer: {use}", INSTALL_HINT)
    return Check("Blender", True, needed, f"{version} ({cmd[0]}): {use}")


def check_slurm() -> Check:
    tools = {t: shutil.which(t) for t in ("sbatch", "squeue", "sacct", "sinfo")}
    plugin = _version("snakemake-executor-plugin-slurm")
    use = "only for running on a cluster (--workflow-profile profiles/slurm)"
    missing = [t for t, p in tools.items() if p is None]
    if missing or plugin is None:
        what = ", ".join(missing + ([] if plugin else ["snakemake-executor-plugin-slurm"]))
        return Check(
            "Slurm",
            False,
            False,
            f"{what} not found: {use}",
            "pip install -e '.[cluster]'; Slurm itself comes "
            "from your cluster (or scripts/slurm-cluster.sh start: a one-node test cluster)",
        )
    answer = _run([tools["sinfo"], "-h", "-o", "%P %a %D"], timeout=5)
    state = f"sinfo: {answer}" if answer else "no controller answers sinfo (scripts/slurm-cluster.sh start: a test one)"
    return Check("Slurm", True, False, f"plugin {plugin}; {state}: {use}")


def run(configfiles: list[Path]) -> list[Check]:
    """Every check, for the config made of ``configfiles`` (later files update earlier ones)."""
    cfg = load_config_files(configfiles)
    cells = cfg.cells
    embree = any(cfg.stage_settings(m, "raycache").backend == "embree" for m in cfg.grid_meshes)
    meshlab = any(cfg.decimated(m) for m in cfg.grid_meshes) or any(
        cfg.cell_stage_settings("lod", c.prompt, c.variant).enabled for c in cells
    )
    checks = [check_torch(cfg)]
    checks += [
        check_module("Embree", "embreex", "embreex", "ray casting (ray cache, bake)", f"pip install embreex ({SETUP})", embree),
        check_module("pymeshlab", "pymeshlab", "pymeshlab", "decimation, LODs", f"pip install pymeshlab ({SETUP})", meshlab),
        check_module("xatlas", "xatlas", "xatlas", "the bake's texture atlas", f"pip install xatlas ({SETUP})"),
        check_module("usd-core", "pxr", "usd-core", "USD and USDZ export", f"pip install usd-core ({SETUP})"),
        check_module("pygltflib", "pygltflib", "pygltflib", "glTF export", f"pip install pygltflib ({SETUP})"),
    ]
    checks += check_clip(cfg)
    checks += check_node()
    checks.append(check_mitsuba(cfg))
    checks.append(check_blender(cfg))
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    checks.append(
        Check(
            "Chromium",
            chromium is not None,
            False,
            f"{chromium or 'not found'}: only for the browser tests",
            "" if chromium else "apt-get install chromium",
        )
    )
    checks.append(check_slurm())
    return checks


def report(checks: list[Check], configfiles: list[Path]) -> str:
    width = max(len(c.name) for c in checks)
    lines = [f"tango-stylize doctor: what a run of {' + '.join(str(f) for f in configfiles)} needs"]
    for c in checks:
        lines.append(f"  {c.status:<8} {c.name:<{width}}  {c.detail}")
        if c.fix and not c.ok:
            lines += [
                f"  {'':<8} {'':<{width}}  fix: {line}" if i == 0 else f"  {'':<8} {'':<{width}}       {line}"
                for i, line in enumerate(c.fix.splitlines())
            ]
    needed = [c.name for c in checks if not c.ok and c.needed]
    optional = [c.name for c in checks if not c.ok and not c.needed]
    if needed:
        lines.append(f"{len(needed)} needed piece(s) missing ({', '.join(needed)}): the run would stop; fix them first.")
    else:
        lines.append("Everything this config's run needs is here.")
    if optional:
        lines.append(f"{len(optional)} optional piece(s) missing ({', '.join(optional)}): see what each adds above.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    result = {}

    def arguments(parser):
        parser.add_argument("--configfile", type=Path, nargs="+", default=[Path("config/config.yaml")])
        parser.add_argument("--json", action="store_true", help="print the checks as JSON")

    def body(args):
        checks = run(args.configfile)
        if args.json:
            sys.stdout.write(json.dumps([{**asdict(c), "status": c.status} for c in checks], indent=1) + "\n")
        else:
            sys.stdout.write(report(checks, args.configfile))
        result["needed_missing"] = any(not c.ok and c.needed for c in checks)

    status = stage_main("doctor", __doc__, arguments, body, argv)
    return status or int(result.get("needed_missing", False))


if __name__ == "__main__":
    raise SystemExit(main())
