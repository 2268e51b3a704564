# Config validation, wildcard constraints and input/param helpers -- nothing else.
# The logic lives in stages/config/ (no torch: building the DAG imports only that layer and core).
import json
import os
import shlex
import sys
from pathlib import Path

from stages.config.code import code_digest
from stages.config.layout import EXPORT_FILES, LOD_FILES, OPTIMIZE_FILES, TEXTURES
from stages.config.sections import MATERIALS
from stages.config.workflow import MESH_WORK, RULE_THREADS, read_yaml, workflow_config
from stages.core.errors import ConfigError

DEFAULT_CONFIGFILE = "config/config.yaml"

# A --configfile on the command line replaces the default experiment instead of being merged
# into it (Snakemake's configfile directive would merge the two grids).
if not workflow.overwrite_configfiles:
    # the default file through the project's bounded reader before Snakemake's own reads it: a
    # template is refused before Snakemake evaluates it, and a file nested too deep for Snakemake's
    # reader is one line (a --configfile is read by Snakemake before this file runs)
    try:
        read_yaml(Path(DEFAULT_CONFIGFILE))
    except ConfigError as exc:
        raise WorkflowError(f"invalid configuration: {exc}") from None

    configfile: DEFAULT_CONFIGFILE


_configfiles = list(map(str, workflow.overwrite_configfiles)) or [DEFAULT_CONFIGFILE]
try:
    # each file again through the project's bounded reader before anything walks the values
    # Snakemake built (an alias bomb, a duplicate key, a YTE template, which Snakemake has already
    # evaluated: refused unless TANGO_ALLOW_YTE=1 was set when the run started), then the checks
    # `python -m stages.config --check` makes, by the same code
    CFG, EXPERIMENT = workflow_config(_configfiles, loaded=config)
except ConfigError as exc:
    raise WorkflowError(f"invalid configuration: {exc}") from None

# The experiment's cells and report live in results/<experiment>/; mesh-level work (normalize,
# decimate, raycache, target) in results/meshes/<mesh>/<key>/<stage>/, keyed by a digest of
# the settings that shape it (CFG.mesh_work_keys), so experiments share it when they agree.
RESULTS = f"results/{EXPERIMENT}"
MESHES = f"results/{MESH_WORK}"
MESH_WORK_DIR = f"{MESHES}/{{mesh}}/{{key}}"
# where the torch stages run, and the gpu resource each of their jobs asks for (1 on a GPU):
# profiles/default allows one such job at a time unless --resources gpu=N says otherwise
DEVICE = CFG.device
GPU_JOBS = CFG.gpu_jobs()
# all jobs share one environment (the project installed from the repository root)
CONDA_ENV = "../envs/tango.yaml"
ID_REGEX = "[A-Za-z0-9][A-Za-z0-9_.-]*"


wildcard_constraints:
    key="[0-9a-f]{12}",
    material="|".join(MATERIALS),
    mesh=ID_REGEX,
    prompt=ID_REGEX,
    variant=ID_REGEX,


for _mesh in CFG.grid_meshes:
    if "path" in CFG.meshes[_mesh] and CFG.mesh_file(_mesh) is None:
        logger.warning(
            f"mesh {_mesh!r}: file {CFG.meshes[_mesh]['path']!r} not found; "
            "its jobs will fail (other meshes still run with --keep-going)"
        )


def mesh_work(mesh, stage):
    """The folder of the mesh's ``stage`` output (normalize, decimate, raycache, target) under
    this experiment's settings: results/meshes/<mesh>/<key>/<stage>."""
    return f"{MESHES}/{mesh}/{CFG.mesh_work_keys(mesh)[stage]}/{stage}"


def mesh_work_input(stage, name):
    """Input function: the file ``name`` of the job's mesh's ``stage`` output."""

    def path(wildcards):
        return f"{mesh_work(wildcards.mesh, stage)}/{name}"

    path.__name__ = f"{stage}_{name.replace('.', '_')}"
    return path


def check_key(stage, wildcards):
    """A mesh-level job is built only under its own settings' key: a path asked for with another
    key (an old folder, a hand-typed target) is an error, not a job run under the wrong settings.
    """
    if "key" not in wildcards.keys():
        return  # a per-cell job reading a mesh stage's settings (lod: decimate)
    keys = CFG.mesh_work_keys(wildcards.mesh) if wildcards.mesh in CFG.meshes else {}
    want = keys.get(stage)
    if wildcards.key != want:
        has = (
            f"its key: {want}"
            if want
            else f"it has no {stage} work for mesh {wildcards.mesh!r}"
        )
        raise WorkflowError(
            f"{MESHES}/{wildcards.mesh}/{wildcards.key}/{stage} was keyed by other {stage} settings than "
            f"experiment {EXPERIMENT!r} has ({has}); ask for the experiment's own targets instead"
        )


def mesh_input(wildcards):
    """The mesh file when it exists; a missing file is reported by the stage itself, so that
    --keep-going still runs the rest of the grid."""
    path = CFG.mesh_file(wildcards.mesh)
    return [path] if path else []


def mesh_source(wildcards):
    return CFG.mesh_source(wildcards.mesh)


def stage_settings_json(stage):
    """Params function: the resolved settings of ``stage`` for the job's mesh, as JSON."""

    def settings(wildcards):
        check_key(stage, wildcards)
        return json.dumps(
            CFG.stage_settings(wildcards.mesh, stage).to_dict(), sort_keys=True
        )

    settings.__name__ = f"{stage}_settings_json"
    return settings


def target_envmaps(wildcards):
    """Input function of target: the environment files (not builtin:) its scenes read, the
    training light and the relit judges', so that editing one renders the targets again.
    """
    s = CFG.stage_settings(wildcards.mesh, "target")
    return [
        e
        for e in (s.environment, *s.relight_environments)
        if not e.startswith("builtin:")
    ]


def budget_raycache_json(wildcards):
    """Params function of decimate: with ``decimate.mode: budget``, the mesh's ray-cache settings
    that set the face budget (FACE_BUDGET_FIELDS) as a quoted option; else nothing, so that
    other ray-cache edits do not rerun a decimation that does not read them."""
    fields = CFG.face_budget_fields(wildcards.mesh)
    if not fields:
        return ""
    return f"--raycache-settings {shlex.quote(json.dumps(fields, sort_keys=True))}"


def traced_mesh(wildcards):
    """Input of raycache: the decimated mesh where decimation is enabled, else the normalised one."""
    stage = "decimate" if CFG.decimated(wildcards.mesh) else "normalize"
    return f"{mesh_work(wildcards.mesh, stage)}/mesh.ply"


CELL = f"{RESULTS}/{{mesh}}/{{prompt}}/{{variant}}"


def cell_dir(stage):
    """Params helper: the stage's output folder of the job's grid cell."""

    def folder(wildcards):
        return (
            f"{RESULTS}/{wildcards.mesh}/{wildcards.prompt}/{wildcards.variant}/{stage}"
        )

    folder.__name__ = f"{stage}_dir"
    return folder


def optimize_outputs():
    outs = {key: f"{CELL}/optimize/{name}" for key, name in OPTIMIZE_FILES.items()}
    outs["meta"] = f"{CELL}/optimize/meta.json"
    return outs


def prompt_text(wildcards):
    return CFG.prompt_text(wildcards.mesh, wildcards.prompt)


def optimize_settings_json(wildcards):
    settings = CFG.optimize_settings(wildcards.prompt, wildcards.variant)
    return json.dumps(settings.to_dict(), sort_keys=True)


def optimize_threads(wildcards):
    """Threads function: the cell's optimize job's CPU threads (its guidance mode's)."""
    return CFG.optimize_threads(wildcards.prompt, wildcards.variant)


def cell_targets(name):
    """Input function: the cell's Mitsuba targets (``train`` or ``metrics``), or nothing when the
    cell trains on CLIP or on SG-rendered targets."""

    def targets(wildcards):
        material = CFG.target_material(wildcards.prompt, wildcards.variant)
        if material is None:
            return {}
        return {
            "targets": f"{mesh_work(wildcards.mesh, 'target')}/{material}/{name}.npz"
        }

    targets.__name__ = f"{name}_targets"
    return targets


def light_map_input(wildcards):
    """Input function of optimize: the environment file of ``optimize.light: fixed`` (not
    builtin:), so that editing it trains the cell again."""
    s = CFG.optimize_settings(wildcards.prompt, wildcards.variant)
    if s.light != "fixed" or s.light_map.startswith("builtin:"):
        return {}
    return {"light_map": s.light_map}


def targets_option(wildcards, input):
    """Params function: ``--targets FILE`` when the job has Mitsuba targets, else nothing."""
    return f"--targets {input.targets}" if "targets" in input.keys() else ""


def pending_jobs():
    """The jobs this run still has to run, as ``(rule, wildcards)`` from Snakemake's DAG, or None
    when the DAG cannot be read (its API changed): the plan and the check of the judges.
    """
    try:
        return [
            (job.rule.name, dict(job.wildcards.items()))
            for job in workflow.dag.needrun_jobs()
        ]
    except Exception:
        return None


def run_cores():
    """Snakemake's ``--cores`` where the jobs run on this machine, None where an executor sends
    them elsewhere (Slurm: Snakemake has no cores to share then)."""
    try:
        return workflow.cores
    except Exception:
        return None


def print_plan():
    """Before the first job: the plan (stages/plan.py: cells, jobs to run, device, an estimate
    of the wall time here). A plan that cannot be made never stops the run."""
    from stages.plan import make_plan, plan_text

    # None: the plan counts from the results folder instead
    pending = pending_jobs()
    import logging

    # a library that logs through the root logger gives it a handler (logging's basicConfig);
    # Snakemake's own log lines would then reach the terminal twice: leave root as it was
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        calibrate = os.environ.get("TANGO_PLAN_CALIBRATE", "1") != "0"
        text = plan_text(
            make_plan(
                CFG,
                EXPERIMENT,
                calibrate=calibrate,
                pending=pending,
                cores=run_cores(),
            )
        )
    except Exception as exc:
        text = f"(no plan: {type(exc).__name__}: {exc})\n"
    finally:
        for handler in root.handlers[:]:
            if handler not in handlers:
                root.removeHandler(handler)
        root.setLevel(level)
    sys.stderr.write(text)


def check_needed_pieces():
    """Before any job runs: stop at once when real CLIP weights (for guidance or for the
    evaluation metrics) are needed but unavailable, one message per missing model, and when a
    judge the jobs still to run need (Mitsuba for target jobs, Blender for roundtrip jobs) is
    missing.
    """
    # imported here, not at the top: they import torch, which building the DAG never needs
    from stages.guidance.clip import missing_weights
    from stages.reference.judges import missing_judges

    problems = missing_weights(CFG.clip_specs())
    lead = []
    if problems:
        lead.append(
            f"{len(problems)} of the CLIP models this run needs cannot be loaded; nothing was run."
        )
    judges = missing_judges(*judges_needed())
    if judges:
        lead.append(
            f"{len(judges)} of the tools this run needs are missing; nothing was run."
        )
    if lead:
        raise WorkflowError("\n\n".join(["\n".join(lead), *problems, *judges]))


def judges_needed():
    """The ``target.variant`` of each mesh with a target job to run, and the number of roundtrip
    jobs to run (from Snakemake's DAG; the whole config when the DAG cannot be read), so that
    a run that needs no judge (``--until normalize``, a report rebuilt) is never stopped.
    """
    pending = pending_jobs()
    if pending is None:
        meshes = None
        roundtrips = len(CFG.roundtrip_cells())
    else:
        meshes = {w["mesh"] for rule, w in pending if rule == "target"}
        roundtrips = sum(rule == "roundtrip" for rule, _ in pending)
    variants = {
        CFG.stage_settings(mesh, "target").variant
        for mesh, _ in CFG.target_jobs(meshes)
    }
    return variants, roundtrips


def cell_settings_json(stage):
    """Params helper: resolved settings of a per-cell stage (bake, export, relight) as JSON."""

    def settings(wildcards):
        s = CFG.cell_stage_settings(stage, wildcards.prompt, wildcards.variant)
        return json.dumps(s.to_dict(), sort_keys=True)

    settings.__name__ = f"{stage}_settings_json"
    return settings


def bake_outputs():
    outs = {k: f"{CELL}/bake/textures/{k}.png" for k in TEXTURES}
    for key, name in (
        ("exr", "light.exr"),
        ("hdr", "light.hdr"),
        ("atlas", "atlas.npz"),
    ):
        outs[key] = f"{CELL}/bake/{name}"
    outs["preview"] = f"{CELL}/bake/preview.png"
    outs["meta"] = f"{CELL}/bake/meta.json"
    return outs


def export_inputs(wildcards):
    cell = f"{RESULTS}/{wildcards.mesh}/{wildcards.prompt}/{wildcards.variant}"
    return {
        "mesh": traced_mesh(wildcards),
        "transform": f"{mesh_work(wildcards.mesh, 'normalize')}/transform.json",
        "preview": f"{cell}/bake/preview.png",
        "bake_meta": f"{cell}/bake/meta.json",
        # the input itself: a kept UV layout's asset is its own topology (bake.uv)
        "source": mesh_input(wildcards),
    }


def export_outputs():
    # every export format's files (stages.config.layout.EXPORT_FORMATS): model_glb, model_usda, ...
    outs = {
        f"model_{suffix}": f"{CELL}/export/{name}"
        for suffix, name in EXPORT_FILES.items()
    }
    outs.update({f"tex_{k}": f"{CELL}/export/textures/{k}.png" for k in TEXTURES})
    outs.update(
        exr=f"{CELL}/export/light.exr",
        hdr=f"{CELL}/export/light.hdr",
        preview=f"{CELL}/export/preview.png",
        meta=f"{CELL}/export/meta.json",
    )
    return outs


def asset_name(wildcards):
    return f"{wildcards.mesh}_{wildcards.prompt}_{wildcards.variant}"


def relight_inputs(wildcards):
    cell = f"{RESULTS}/{wildcards.mesh}/{wildcards.prompt}/{wildcards.variant}"
    inputs = {
        "field": f"{cell}/optimize/field.pt",
        "eval": f"{mesh_work(wildcards.mesh, 'raycache')}/eval.npz",
    }
    env = CFG.cell_stage_settings("relight", wildcards.prompt, wildcards.variant).envmap
    if not env.startswith("builtin:"):
        inputs["envmap"] = env
    material = CFG.target_material(wildcards.prompt, wildcards.variant)
    if material is not None:  # Mitsuba's relit ground truth grades the relighting
        target = f"{mesh_work(wildcards.mesh, 'target')}/{material}"
        inputs["truth"] = f"{target}/relit.npz"
        inputs["targets"] = f"{target}/metrics.npz"
        inputs["metrics_cache"] = f"{mesh_work(wildcards.mesh, 'raycache')}/metrics.npz"
    return inputs


def relight_truth_options(wildcards, input):
    """Params function of relight: the relit ground truth and what it needs, when the cell has it."""
    if "truth" not in input.keys():
        return ""
    return f"--truth {shlex.quote(input.truth)} --targets {shlex.quote(input.targets)} --metrics {shlex.quote(input.metrics_cache)}"


def roundtrip_inputs(wildcards):
    cell = f"{RESULTS}/{wildcards.mesh}/{wildcards.prompt}/{wildcards.variant}"
    return {
        "mesh": traced_mesh(wildcards),
        "transform": f"{mesh_work(wildcards.mesh, 'normalize')}/transform.json",
        "field": f"{cell}/optimize/field.pt",
        "eval": f"{mesh_work(wildcards.mesh, 'raycache')}/eval.npz",
        "atlas": f"{cell}/bake/atlas.npz",
        "export_meta": f"{cell}/export/meta.json",
        "source": mesh_input(wildcards),
    }


def roundtrip_metas():
    """The Blender round trip's metadata of every cell that has it enabled (section
    ``roundtrip``); nothing when it is off, so the main job never needs Blender."""
    return [
        f"{RESULTS}/{c.mesh}/{c.prompt}/{c.variant}/roundtrip/meta.json"
        for c in CFG.cells
        if CFG.cell_stage_settings("roundtrip", c.prompt, c.variant).enabled
    ]


def lod_inputs(wildcards):
    cell = f"{RESULTS}/{wildcards.mesh}/{wildcards.prompt}/{wildcards.variant}"
    return {
        "mesh": traced_mesh(wildcards),
        "transform": f"{mesh_work(wildcards.mesh, 'normalize')}/transform.json",
        "field": f"{cell}/optimize/field.pt",
        "eval": f"{mesh_work(wildcards.mesh, 'raycache')}/eval.npz",
        "atlas": f"{cell}/bake/atlas.npz",
        "export_meta": f"{cell}/export/meta.json",
        "source": mesh_input(wildcards),
    }


def lod_outputs():
    return {key: f"{CELL}/lod/{name}" for key, name in LOD_FILES.items()}


def lod_settings_json(wildcards):
    """Params function of lod: the settings it reads, one JSON object per section (the cell's
    lod, bake and export settings, the mesh's decimate settings)."""
    sections = {
        stage: CFG.cell_stage_settings(stage, wildcards.prompt, wildcards.variant)
        for stage in ("lod", "bake", "export")
    }
    sections["decimate"] = CFG.stage_settings(wildcards.mesh, "decimate")
    return json.dumps({k: s.to_dict() for k, s in sections.items()}, sort_keys=True)


def lod_metas():
    """The levels-of-detail metadata of every cell that has them enabled (section ``lod``)."""
    return [
        f"{RESULTS}/{c.mesh}/{c.prompt}/{c.variant}/lod/meta.json"
        for c in CFG.cells
        if CFG.cell_stage_settings("lod", c.prompt, c.variant).enabled
    ]


def lod_cells_option():
    """``--lod-cells`` and the cells with levels of detail (none: the flag alone)."""
    cells = [
        f"{c.mesh}/{c.prompt}/{c.variant}"
        for c in CFG.cells
        if CFG.cell_stage_settings("lod", c.prompt, c.variant).enabled
    ]
    return " ".join(["--lod-cells", *cells])


def decimation_pairs_json(wildcards):
    return json.dumps(CFG.decimation_pairs())


def mesh_work_json(wildcards):
    """Params function of report: mesh id -> stage -> the folder of its mesh-level work."""
    dirs = {}
    for mesh in CFG.grid_meshes:
        stages = ["normalize", "raycache"] + (
            ["decimate"] if CFG.decimated(mesh) else []
        )
        dirs[mesh] = {stage: mesh_work(mesh, stage) for stage in stages}
    return json.dumps(dirs, sort_keys=True)


def candidates_json(wildcards):
    return json.dumps(CFG.candidate_prompts(wildcards.mesh))


def cell_metas(rel):
    return [f"{RESULTS}/{c.mesh}/{c.prompt}/{c.variant}/{rel}" for c in CFG.cells]


def results_root(wildcards, input):
    """Params function: the results folder, from the first cell file among the inputs
    (``<results>/<mesh>/<prompt>/<variant>/<stage>/meta.json``)."""
    return str(Path(input[0]).parents[4])


def results_root_from_assets(wildcards, input):
    """Params function: the results folder, from the cells' asset metadata inputs."""
    return str(Path(input.assets[0]).parents[4])


def output_folder(wildcards, output):
    """Params function: the folder of the rule's first output."""
    return str(Path(output[0]).parent)


#: the report section (reference variant, ablations, the HTML form), validated with the config
REPORT = CFG.report_settings()
REPORT_SETTINGS_JSON = json.dumps(REPORT.to_dict(), sort_keys=True)
#: the HTML report's folders beside index.html (none when it is one self-contained file)
REPORT_SITE = (
    []
    if REPORT.single_file
    else [directory(f"{RESULTS}/report/cells"), directory(f"{RESULTS}/report/viewer")]
)


def cell_ids():
    return " ".join(f"{c.mesh}/{c.prompt}/{c.variant}" for c in CFG.cells)


def all_targets():
    return [
        f"{RESULTS}/report/summary.csv",
        f"{RESULTS}/report/overview.png",
        f"{RESULTS}/report/asset_pack.zip",
        f"{RESULTS}/report/index.html",
    ]
