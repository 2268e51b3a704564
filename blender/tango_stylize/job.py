"""The workflow run behind the add-on, without Blender: the command line of ``python -m stages.quick``
in the project's environment, the background process with its log, its progress and its one-line
error, and the asset a finished run leaves. Nothing here imports ``bpy``, so the project's tests
read it as plain Python."""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

#: Snakemake's progress line
PROGRESS = re.compile(r"(\d+) of (\d+) steps \((\d+(?:\.\d+)?)%\) done")
#: a stage's or the quick command's one-line failure (``... ERROR stages.bake: bake failed: WHAT``)
FAILED = re.compile(r"\bERROR \S+: (?:\S+ failed: )?(.+)$")
#: what a run's name may hold (the quick command's experiment name)
NAME = re.compile(r"[^a-z0-9]+")


@dataclass(frozen=True)
class Request:
    """One stylisation: the project's ``python``, the ``workdir`` its configs and results go to, the
    exported ``mesh``, the ``prompt``, the optimisation ``preset``, the procedural ``material`` an
    image-guided run recovers instead of asking CLIP (empty: CLIP), the tiny ``test_clip``, the
    run's ``name``, the bake's ``uv`` layout and config ``overlays`` laid over the written config."""

    python: str
    workdir: Path
    mesh: Path
    prompt: str
    preset: str
    name: str
    material: str = ""
    test_clip: bool = False
    uv: str = "keep"
    overlays: tuple[str, ...] = ()

    def command(self, dry_run: bool = False) -> list[str]:
        """``python -m stages.quick`` for this request (``--force``: a new run of the same name
        replaces its config; the mesh and the prompt after ``--``, so that a prompt may start
        with a hyphen)."""
        cmd = [self.python, "-m", "stages.quick", "--preset", self.preset, "--name", self.name, "--uv", self.uv, "--force"]
        cmd += ["--image-guided", self.material] if self.material else []
        cmd += ["--test-clip"] if self.test_clip else []
        for overlay in self.overlays:
            cmd += ["--overlay", overlay]
        return cmd + (["--dry-run"] if dry_run else []) + ["--", str(self.mesh), self.prompt]

    def results(self) -> Path:
        """The run's experiment folder."""
        return Path(self.workdir) / "results" / self.name


def run_name(*words: str, settings: tuple[str, ...] = ()) -> str:
    """An experiment name from ``words`` (the file's and the objects' names): lower-case letters,
    digits and hyphens; with ``settings`` (the prompt, material, preset) a short digest of them
    after it, so that another prompt is another experiment and the same one is the same."""
    name = NAME.sub("-", "-".join(words).lower()).strip("-")[:60] or "blender"
    if settings:
        name += "-" + hashlib.sha256("\0".join(settings).encode()).hexdigest()[:8]
    return name


def environment(python: str) -> dict:
    """The environment a run gets: the project's interpreter first on ``PATH`` (the workflow's own
    ``python -m`` then finds it), and none of Blender's Python variables."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    env["PATH"] = f"{Path(python).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def choices(python: str, timeout: float = 120.0) -> dict:
    """The presets, materials and layouts the project offers (``python -m stages.config.choices``).

    Raises:
        RuntimeError: the project's Python cannot say (one line: why)."""
    try:
        proc = subprocess.run(
            [python, "-m", "stages.config.choices"], capture_output=True, text=True, timeout=timeout, env=environment(python)
        )
    except (OSError, subprocess.SubprocessError) as exc:
        raise RuntimeError(f"the project's Python {python} could not be run: {exc}") from None
    if proc.returncode != 0:
        raise RuntimeError(f"{python} -m stages.config.choices failed: {last_line(proc.stderr)}")
    return json.loads(proc.stdout)


def plan(request: Request, timeout: float = 600.0) -> subprocess.CompletedProcess:
    """The workflow's plan for ``request`` (``--dry-run``: the config written, nothing run).

    Raises:
        RuntimeError: the project's Python could not be run or did not finish (one line)."""
    Path(request.workdir).mkdir(parents=True, exist_ok=True)
    env = {**environment(request.python), "TANGO_PLAN_CALIBRATE": "0"}
    try:
        return subprocess.run(
            request.command(dry_run=True), cwd=request.workdir, capture_output=True, text=True, timeout=timeout, env=env
        )
    except (OSError, subprocess.SubprocessError) as exc:
        raise RuntimeError(f"the plan could not be made: {str(exc).splitlines()[0]}") from None


#: the plan's refusal of a UV map the bake cannot keep (``bake.uv: keep, but ...``)
REFUSED_LAYOUT = "bake.uv: keep, but"


def last_line(text: str) -> str:
    """The line of a run's output that says what went wrong: the last stage failure, else the last
    line with text."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for line in reversed(lines):
        m = FAILED.search(line)
        if m:
            return m.group(1)
    return lines[-1] if lines else "no output"


@dataclass
class Job:
    """A background run of ``command`` in ``workdir``, its output in ``log``; :meth:`poll` reads its
    progress, :meth:`cancel` stops it and every process it started."""

    command: list[str]
    workdir: Path
    log: Path
    env: dict = field(default_factory=dict)
    process: subprocess.Popen | None = None
    started: float = 0.0

    def start(self) -> Job:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log, "w", encoding="utf-8") as out:
            posix = os.name == "posix"
            self.process = subprocess.Popen(
                self.command,
                cwd=self.workdir,
                stdout=out,
                stderr=subprocess.STDOUT,
                env=self.env or None,
                start_new_session=posix,
            )
        self.started = time.monotonic()
        return self

    def poll(self) -> int | None:
        """The exit code, or None while it runs."""
        return None if self.process is None else self.process.poll()

    def wait(self, timeout: float | None = None) -> int:
        return self.process.wait(timeout)

    def output(self) -> str:
        try:
            return self.log.read_text(encoding="utf-8", errors="replace")
        except OSError:
            return ""

    def progress(self) -> tuple[float, str]:
        """The share of the workflow's steps done (0 before the first) and the last line said."""
        text = self.output()
        done = PROGRESS.findall(text)
        share = float(done[-1][2]) / 100.0 if done else 0.0
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        return share, (lines[-1][:200] if lines else "starting")

    def cancel(self, grace: float = 10.0) -> None:
        """Stop the run and the processes it started (its session), SIGTERM then SIGKILL."""
        if self.process is None or self.process.poll() is not None:
            return
        if os.name == "posix":
            os.killpg(self.process.pid, signal.SIGTERM)
        else:
            self.process.terminate()
        try:
            self.process.wait(grace)
        except subprocess.TimeoutExpired:
            if os.name == "posix":
                os.killpg(self.process.pid, signal.SIGKILL)
            else:
                self.process.kill()
            self.process.wait()


@dataclass(frozen=True)
class Result:
    """What a finished run left: its cell's ``export`` folder (``model.glb``, ``light.hdr``, the
    textures) and the bake's record of the UV layout (``uv``)."""

    export: Path
    uv: dict

    @property
    def glb(self) -> Path:
        return self.export / "model.glb"


def result_of(request: Request) -> Result:
    """The one cell a finished run of ``request`` exported.

    Raises:
        RuntimeError: none, or several (one line: what was found)."""
    found = sorted(request.results().glob("*/*/*/export/model.glb"))
    if len(found) != 1:
        raise RuntimeError(f"{len(found)} exported cells in {request.results()}, expected one")
    export = found[0].parent
    bake = export.parent / "bake" / "meta.json"
    uv = json.loads(bake.read_text(encoding="utf-8")).get("stats", {}).get("uv", {}) if bake.is_file() else {}
    return Result(export, uv)
