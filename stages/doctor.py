"""doctor: check, in seconds, what a run of a config needs, and say how to fix each missing piece.

    python -m stages.doctor [--configfile config/config.yaml [overlay.yaml ...]] [--json] [--offline]

Checked: the torch build and the device the config's torch stages will use; the ray tracer
(Embree through embreex), pymeshlab (decimation), xatlas (texture atlases), usd-core and
pygltflib (the asset formats); the CLIP weights of the models the config needs (guidance and
evaluation, one line each: a local file or the Hugging Face cache, else whether the model hub,
huggingface.co, would give them: the doctor logs that it asks before it does, asks nothing with
``--offline`` or ``HF_HUB_OFFLINE=1``, and never downloads); Node.js with the bundled
model-viewer (the report's 3D viewers) and the glTF validator; the independent judges, Mitsuba 3
(with libLLVM for its fast CPU variant) and Blender; Chromium (the browser tests); and the cluster
pieces (Slurm's commands and the Snakemake executor plugin). A piece is *needed* when this config's
run would fail without it, else *optional* (what it adds is said). Exit status 1 when a needed
piece is missing, else 0.

A piece is not called ok because it imports: each one the run uses does the smallest real job
first (:mod:`stages.geometry.probes`, :mod:`stages.assets.probes`, a few-pixel Mitsuba render of
the target scene in the variant the run will use, a Blender import of a tiny GLB, the glTF
validator on it, a headless Chromium page, a matrix product on the torch device), in parallel.
When Mitsuba can only use its slow ``scalar_rgb`` variant, the doctor says how long this config's
targets will take in it, from the rate it measured.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from .assets.probes import probe_gltf, probe_node_validator, probe_usd
from .config.workflow import load_config_files
from .core.allocator import allocator_plan
from .core.cli import add_configfile, stage_main
from .core.device import (
    bf16_choice,
    bf16_support,
    cpu_isa,
    precision_summary,
    resolve_device,
)
from .core.progress import duration
from .core.tools import GLTF_VALIDATOR, MODEL_VIEWER
from .geometry.probes import PROBE_GLB_FACES, PROBE_TIMEOUT_S, probe_embree, probe_pymeshlab, probe_xatlas, write_probe_glb
from .guidance.clip import HUB_HOST, ClipWeightsUnavailable, hub_offline, resolve_weights
from .model.compiled import planned_path
from .reference import blender as blender_ref
from .reference import targets as targets_ref
from .reference.blender import INSTALL_HINT, BlenderUnavailable, find_blender
from .reference.mitsuba import LLVM_WHEEL, choose_variant, locate_libllvm
from .reference.targets import probe as probe_targets
from .render.products import run_choice

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
SETUP = "bash scripts/setup.sh"
#: Chromium's flags for a headless page on a machine without a screen or a network (as root)
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


@dataclass
class Check:
    name: str
    ok: bool
    needed: bool
    detail: str
    fix: str = ""
    #: what the smallest real use did (empty when the piece was not tried), and its seconds
    tried: str = ""
    seconds: float = 0.0

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


def tried(check: Check, use: Callable[[], str], fix: str) -> Check:
    """``check`` after its smallest real use: ``use()`` returns what it did; when it raises, the
    piece is not ok, the error is the detail's last words and ``fix`` the fix."""
    t0 = time.perf_counter()
    try:
        done = use()
    except Exception as exc:  # noqa: BLE001 - any failure of a tool is what the doctor reports
        check.ok = False
        check.detail += f"; but its first real use failed: {type(exc).__name__}: {str(exc).strip()[:400]}"
        check.fix = check.fix or fix
    else:
        check.tried = done
    check.seconds = time.perf_counter() - t0
    return check


def _products_plan(settings: list, device) -> str:
    """Who runs training's float32 linear layers under each of these runs' settings
    (:func:`~stages.render.products.run_choice`; ``auto`` times both kernels here, 0.05 s)."""
    plans = []
    for s in settings:
        clip = (bf16_choice(s.bf16, device, "bf16")[0], s.clip_tower) if s.guidance_mode().uses_clip else None
        networks_bf16 = bf16_choice(s.bf16_networks, device, "bf16_networks")[0]
        plans.append(run_choice(s.onednn_products, device, networks_bf16, clip)[1])
    return "; ".join(dict.fromkeys(plans))


def check_torch(cfg) -> Check:
    import torch

    device = resolve_device(cfg.device if cfg.device != "auto" else "auto")
    build = f"CUDA {torch.version.cuda} build" if torch.version.cuda else "CPU build"
    gpu = f"{torch.cuda.device_count()} GPU(s): {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else "no GPU"
    bf16, why = bf16_support(device)
    settings = [cfg.optimize_settings(c.prompt, c.variant) for c in cfg.cells]
    levers = sorted({(s.bf16, s.bf16_networks) for s in settings})
    # a mesh whose ray cache traces no visibility is shaded without shadows whatever optimize asks
    # (auto decides per mesh when its cache is made: taken here as optimize asks)
    shadowed = [False if cfg.stage_settings(c.mesh, "raycache").visibility == "off" else None for c in cfg.cells]
    renderers = sorted({planned_path(s, device, shade) for s, shade in zip(settings, shadowed, strict=True)})
    detail = (
        f"torch {torch.__version__} ({build}, {gpu}); this config's torch stages run on {device.type} "
        f"(device: {cfg.device}); {torch.get_num_threads()} CPU threads ({cpu_isa()}); bfloat16: {why}; training runs "
        + ("; ".join(precision_summary(a, b, device, reason=False) for a, b in levers) or "none in this config")
        + (f"; renderer: {'; '.join(renderers)}" if renderers else "")
        + (f"; C allocator: {allocator_plan([s.keep_freed_memory for s in settings])}" if settings else "")
        + (f"; float32 linear layers: {_products_plan(settings, device)}" if settings else "")
    )
    if cfg.device == "cuda" and not torch.cuda.is_available():
        return Check(
            "torch and device",
            False,
            True,
            detail,
            "device: cuda but torch sees no GPU: install a CUDA build of torch (README, 'GPU') or set device: auto",
        )

    def use() -> str:
        a = torch.randn(256, 256, device=device, requires_grad=True)
        (a @ a).square().mean().backward()
        if not torch.isfinite(a.grad).all():
            raise RuntimeError("a 256 x 256 matrix product's gradient is not finite")
        if bf16:
            with torch.autocast(device.type, dtype=torch.bfloat16):
                if (a @ a).dtype != torch.bfloat16:
                    raise RuntimeError("bfloat16 autocast did not run in bfloat16")
        return f"a matrix product and its gradient on {device.type}" + (" (and under bfloat16 autocast)" if bf16 else "")

    return tried(Check("torch and device", True, True, detail), use, "reinstall torch (bash scripts/setup.sh)")


def check_module(name: str, module: str, dist: str, what: str, fix: str, needed: bool, use: Callable[[], str]) -> Check:
    """A Python package: installed (``module`` importable), then its smallest real use ``use``."""
    found = importlib.util.find_spec(module) is not None
    version = _version(dist)
    if not found:
        return Check(name, False, needed, f"{dist} is not installed: {what}", fix)
    return tried(Check(name, True, needed, f"{dist} {version or '(version unknown)'}: {what}"), use, fix)


def check_clip(cfg, online: bool = True) -> list[Check]:
    """The weights of each real CLIP the config needs: a local file, the Hugging Face cache, or
    (``online``, and ``HF_HUB_OFFLINE`` unset) whether the model hub would give them, which the log
    says before the hub is asked; never downloaded. Offline, weights not here are missing, and the
    line says the hub was not asked."""
    specs = cfg.clip_specs()
    if not specs:
        return [Check("CLIP weights", True, False, "this config needs no real CLIP weights (image guidance or the test CLIP)")]
    out = []
    offline = "--offline" if not online else "HF_HUB_OFFLINE=1" if hub_offline() else None
    for spec in specs:
        role = "guidance" if spec.section == "optimize" else "evaluation"
        name = f"CLIP weights ({role})"
        try:
            path, weights_id, _ = resolve_weights(spec, download=False, online=online)  # checked, never fetched here
        except ClipWeightsUnavailable as exc:
            first, _, rest = str(exc).partition("\n")
            if offline:
                first += f" Not checked online ({offline})."
            out.append(Check(name, False, True, first, rest))
        else:
            where = path or "not cached here; the model hub answers, so the workflow downloads them when it starts"
            out.append(Check(name, True, True, f"{weights_id} for {spec.section}: {where}"))
    return out


def check_node(glb: Path) -> Check:
    """Node.js, model-viewer and the glTF validator; the validator run on the probe GLB."""
    node = shutil.which("node")
    name = "Node.js and the report's viewer"
    fix = f"install Node.js and npm (Debian: apt-get install nodejs npm), then rerun {SETUP} (it runs npm ci)"
    if node is None:
        what = "the report shows static previews instead of 3D viewers, and the export skips the Khronos glTF validator"
        return Check(name, False, False, f"node not found: {what}", fix)
    version = _run([node, "--version"]) or "?"
    missing = [p.name for p in (MODEL_VIEWER, GLTF_VALIDATOR) if not p.exists()]
    if missing:
        what = "no 3D viewers in the report / no glTF validation"
        return Check(
            name,
            False,
            False,
            f"node {version}, but {', '.join(missing)} not installed in node_modules: {what}",
            f"run {SETUP} (or npm ci)",
        )
    check = Check(name, True, False, f"node {version}; model-viewer and the Khronos glTF validator in node_modules")
    return tried(check, lambda: probe_node_validator(glb), f"run {SETUP} again (npm ci), or reinstall Node.js")


def target_samples(cfg, mesh: str) -> int:
    """The Mitsuba samples one target job of ``mesh`` path-traces, the relit truths included
    (:func:`stages.reference.targets.target_samples`)."""
    return sum(targets_ref.target_samples(cfg.stage_settings(mesh, "raycache"), cfg.stage_settings(mesh, "target")).values())


def check_mitsuba(cfg) -> Check:
    """Mitsuba 3: installed, the variant each target job uses (its mesh's ``target.variant``), a
    small render of the target scene in each such variant and, when targets are needed, how long
    this config's target jobs take at the rates it measured (rendering only)."""
    jobs = cfg.target_jobs()
    needed = bool(jobs)
    use = "renders this config's image targets" if needed else "the ground-truth judge of image-guided runs (not used here)"
    version = _version("mitsuba")
    fix = f"pip install -e '.[reference]' ({SETUP} installs it)"
    if version is None:
        return Check("Mitsuba 3", False, needed, f"mitsuba is not installed: it {use}", fix)
    meshes = sorted({m for m, _ in jobs}) or cfg.grid_meshes[:1]
    settings = {m: cfg.stage_settings(m, "target") for m in meshes}
    try:
        variants = {m: choose_variant(s.variant) for m, s in settings.items()}
    except ImportError as exc:
        return Check(
            "Mitsuba 3",
            False,
            needed,
            f"mitsuba {version}: {exc}",
            f"pip install {LLVM_WHEEL} (or apt-get install libllvm19), or target.variant: auto",
        )
    lib = locate_libllvm()
    names = ", ".join(sorted(set(variants.values())))
    where = f"with {lib.describe()}" if lib else "(no libLLVM 16+ found)"
    check = Check("Mitsuba 3", True, needed, f"mitsuba {version}, variant {names} {where}: {use}")

    def render() -> str:
        probes = {}
        for mesh, variant in variants.items():
            if variant not in probes:
                probes[variant] = probe_targets(settings[mesh])
        said = "; ".join(
            f"rendered a {r.width} x {r.width} target probe at {r.spp} spp in {v} ({r.samples_per_second / 1e6:.2f} M samples/s)"
            for v, r in probes.items()
        )
        if jobs:
            samples = sum(target_samples(cfg, m) for m, _ in jobs)
            seconds = sum(target_samples(cfg, m) / probes[variants[m]].samples_per_second for m, _ in jobs)
            said += (
                f"; this config's targets ({len(jobs)} job(s), {samples / 1e6:.0f} M samples) take about "
                f"{duration(seconds)} of rendering here"
            )
        if "scalar_rgb" in probes:
            said += (
                f" in the slow scalar_rgb variant (pip install {LLVM_WHEEL}, or Debian: apt-get install libllvm19, "
                "for the vectorised llvm_ad_rgb)"
            )
        return said

    return tried(check, render, f"{fix}; Mitsuba's own error is above")


def check_blender(cfg, glb: Path, work: Path) -> Check:
    """Blender: found, then an import of the probe GLB through the roundtrip stage's job script."""
    needed = bool(cfg.roundtrip_cells())
    use = "this config's roundtrip stage imports the assets into it" if needed else "the asset judge (roundtrip stage, off here)"
    fix = f"{INSTALL_HINT}; or run without it: roundtrip: {{enabled: false}} (or the overlay config/overlays/no-blender.yaml)"
    try:
        cmd = find_blender()
    except BlenderUnavailable as exc:
        return Check("Blender", False, needed, f"{exc}: {use}".split(";")[0], fix)
    check = Check("Blender", True, needed, f"{cmd[0]}: {use}")
    return tried(check, lambda: blender_ref.probe(glb, work / "blender", PROBE_GLB_FACES, PROBE_TIMEOUT_S), fix)


def check_chromium(work: Path) -> Check:
    """Chromium (the browser tests): a headless page whose script writes a marker into the DOM."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        return Check("Chromium", False, False, "not found: only for the browser tests", "apt-get install chromium")

    def use() -> str:
        page = "data:text/html,<body><script>document.body.textContent='probe-'+(6*7)</script></body>"
        args = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={work / 'chromium'}", "--dump-dom", page]
        out = subprocess.run(args, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S)
        if "probe-42" not in out.stdout:
            raise RuntimeError(
                f"headless Chromium did not run a page's script (exit {out.returncode}): {out.stderr.strip()[-300:]}"
            )
        return "ran a page's script headless"

    return tried(
        Check("Chromium", True, False, f"{exe}: only for the browser tests"), use, "apt-get install --reinstall chromium"
    )


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
    if not answer:
        return Check(
            "Slurm",
            False,
            False,
            f"plugin {plugin} and Slurm's commands, but no controller answers sinfo: {use}",
            "on a cluster, run from a login node; for a one-node test cluster: scripts/slurm-cluster.sh start",
        )
    check = Check("Slurm", True, False, f"plugin {plugin}; Slurm's commands: {use}")
    check.tried = f"sinfo answered: {answer}"
    return check


def run(configfiles: list[Path], online: bool = True) -> list[Check]:
    """Every check, for the config made of ``configfiles`` (later files update earlier ones); the
    smallest real uses run in parallel threads (most wait on a child process). ``online=False``:
    nothing asks the model hub (:func:`check_clip`)."""
    cfg = load_config_files(configfiles)
    cells = cfg.cells
    meshlab = any(cfg.decimated(m) for m in cfg.grid_meshes) or any(
        cfg.cell_stage_settings("lod", c.prompt, c.variant).enabled for c in cells
    )
    with tempfile.TemporaryDirectory(prefix="tango-doctor-") as tmp:
        work = Path(tmp)
        glb = work / "probe.glb"
        try:
            write_probe_glb(glb)
        except Exception as exc:  # noqa: BLE001 - trimesh itself broken: the GLB probes then say so
            log.warning("could not write the probe GLB: %s", exc)
        # the pieces that run a child process (Node.js, Blender, Chromium, Slurm) wait in threads;
        # the in-process ones run one after another here (extension modules imported from several
        # threads at once can deadlock)
        with ThreadPoolExecutor(max_workers=4) as pool:
            children = [
                pool.submit(job)
                for job in (
                    lambda: check_node(glb),
                    lambda: check_blender(cfg, glb, work),
                    lambda: check_chromium(work),
                    check_slurm,
                )
            ]
            here = [
                check_torch(cfg),
                check_module(
                    "Embree",
                    "embreex",
                    "embreex",
                    "ray casting (ray cache, bake)",
                    f"pip install embreex ({SETUP})",
                    True,  # the bake's atlas and the targets' truth trace with Embree whatever the cache's backend
                    probe_embree,
                ),
                check_module(
                    "pymeshlab",
                    "pymeshlab",
                    "pymeshlab",
                    "decimation, LODs",
                    f"pip install pymeshlab ({SETUP})",
                    meshlab,
                    probe_pymeshlab,
                ),
                check_module(
                    "xatlas", "xatlas", "xatlas", "the bake's texture atlas", f"pip install xatlas ({SETUP})", True, probe_xatlas
                ),
                check_module(
                    "usd-core",
                    "pxr",
                    "usd-core",
                    "USD and USDZ export",
                    f"pip install usd-core ({SETUP})",
                    True,
                    lambda: probe_usd(work),
                ),
                check_module(
                    "pygltflib",
                    "pygltflib",
                    "pygltflib",
                    "glTF export",
                    f"pip install pygltflib ({SETUP})",
                    True,
                    lambda: probe_gltf(glb),
                ),
                check_clip(cfg, online),
            ]
            node, blender, chromium, slurm = (f.result() for f in children)
        # alone: its rate (samples per second) is what the run's target jobs will see
        mitsuba = check_mitsuba(cfg)
        done = [*here, node, mitsuba, blender, chromium, slurm]
    return [c for d in done for c in (d if isinstance(d, list) else [d])]


def report(checks: list[Check], configfiles: list[Path]) -> str:
    width = max(len(c.name) for c in checks)
    lines = [f"tango-stylize doctor: what a run of {' + '.join(str(f) for f in configfiles)} needs"]
    for c in checks:
        lines.append(f"  {c.status:<8} {c.name:<{width}}  {c.detail}")
        if c.tried:
            lines.append(f"  {'':<8} {'':<{width}}  tried: {c.tried} ({c.seconds:.1f} s)")
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
        add_configfile(parser)
        parser.add_argument("--json", action="store_true", help="print the checks as JSON")
        parser.add_argument(
            "--offline",
            action="store_true",
            help=f"contact nothing: CLIP weights are looked for here only, not on the model hub ({HUB_HOST[0]})",
        )

    def body(args):
        checks = run(args.configfile, online=not args.offline)
        if args.json:
            sys.stdout.write(json.dumps([{**asdict(c), "status": c.status} for c in checks], indent=1) + "\n")
        else:
            sys.stdout.write(report(checks, args.configfile))
        result["needed_missing"] = any(not c.ok and c.needed for c in checks)

    status = stage_main("doctor", __doc__, arguments, body, argv)
    return status or int(result.get("needed_missing", False))


if __name__ == "__main__":
    raise SystemExit(main())
