"""Device and precision policy: where the torch stages run, and whether the levers that trade
precision or compilation time for speed (bfloat16 autocast, torch.compile) are on for a device.

Each decision returns what runs and why, for the metadata, the plan and the doctor; ``auto``
decides from what the machine has (native bfloat16, a C++ compiler), measured at run time.
torch is imported inside the functions that need it, so that the workflow's DAG (which imports
the settings) stays free of it.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import StageInputError
from .safefiles import RECORD_LIMIT, atomic_path, read_bytes

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

#: the bfloat16 levers' settings (``optimize.bf16``, ``optimize.bf16_networks``): ``auto`` turns
#: the lever on where the device has native bfloat16 (:func:`bf16_support`), ``on`` asks for it
#: everywhere (float32 with a warning where it is not native), ``off`` keeps float32
BF16_CHOICES = ("auto", "on", "off")


def resolve_device(name: str = "auto") -> torch.device:
    """``torch.device`` of ``name``; ``"auto"`` is CUDA when available, else the CPU.

    torch is imported here, when a torch stage asks, so that this module (and the workflow's
    DAG, which imports the settings) stays free of it.
    """
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def set_torch_threads(threads: int) -> None:
    """torch's CPU threads for this process (a stage's ``--threads``)."""
    import torch

    torch.set_num_threads(threads)


def bf16_support(device: torch.device) -> tuple[bool, str]:
    """Whether bfloat16 autocast runs natively on ``device``, and why: on a GPU that has it (Ampere
    and later; emulated bfloat16 on older GPUs is slower than float32); on a CPU when
    oneDNN has bfloat16 kernels for it (AVX-512 BF16 or AMX, as on this project's machines), where
    bfloat16 matrix products run several times faster than float32 ones (benchmarks/training/optimize.py);
    elsewhere emulated bfloat16 would be slower than float32, so it is not used."""
    import torch

    if device.type == "cuda":
        if torch.cuda.is_bf16_supported(including_emulation=False):
            return True, "CUDA with native bfloat16"
        return False, "this GPU has no native bfloat16 (before Ampere)"
    if device.type == "cpu":
        if torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported():
            return True, "CPU with native bfloat16 (oneDNN: AVX-512 BF16 / AMX)"
        return False, "this CPU has no native bfloat16 (no AVX-512 BF16 or AMX for oneDNN)"
    return False, f"no bfloat16 autocast on {device.type}"


def lever_choice(setting: str | bool, what: str) -> str:
    """A lever's setting as one of :data:`BF16_CHOICES` (YAML booleans mean on and off); a bad
    value is refused naming the lever ``what``."""
    choice = ("on" if setting else "off") if isinstance(setting, bool) else setting
    if choice not in BF16_CHOICES:
        raise ValueError(f"{what} must be one of {', '.join(BF16_CHOICES)}, got {setting!r}")
    return choice


def bf16_choice(setting: str | bool, device: torch.device, what: str) -> tuple[bool, str]:
    """Whether a bfloat16 lever (``setting``: one of :data:`BF16_CHOICES`; YAML booleans mean on
    and off) runs on ``device``, and what runs, for the metadata, the plan and the doctor:
    ``"bfloat16 autocast (<why>)"``, ``"float32"`` (off), ``"float32 (<why not>)"``; under auto
    the reason starts ``auto:``. ``on`` where bfloat16 is not native logs a warning naming
    ``what`` (the lever) and runs float32; ``auto`` there is float32 by design, without one."""
    choice = lever_choice(setting, what)
    if choice == "off":
        return False, "float32"
    supported, why = bf16_support(device)
    why = f"auto: {why}" if choice == "auto" else why
    if choice == "on" and not supported:
        log.warning("%s asked for, but %s: float32 runs instead", what, why)
    return supported, f"bfloat16 autocast ({why})" if supported else f"float32 ({why})"


#: ``compile_shading: auto`` compiles the renderer for runs of at least this many iterations on a
#: machine where it has not been compiled before: the first compilation took 75-85 s on this
#: project's 2-core CPU (an empty inductor cache) and saves 0.045 s per step at the ``fast``
#: preset's 17,000 points and 16 lobes, 0.14 s at the paper's 25,000 points and 32 lobes
#: (docs/measurements/speed.md, ``benchmarks/training/fast_step.py``): it pays from about 1,000 steps
COMPILE_MIN_ITERATIONS = 1000
#: ... and for runs of at least this many where the same renderer has been compiled before on this
#: machine (inductor's and AOTAutograd's caches warm: 3 s, repaid after about 70 ``fast`` steps)
COMPILE_MIN_ITERATIONS_WARM = 100
#: ... and on CUDA (Triton), warm or not, for runs of at least this many: on an H200 the paper step's
#: first compilation took 82 s and the compiled renderer's step 0.065 s against the eager one's 0.127 s
#: (``python -m benchmarks.training.gpu --levers "float32,compiled renderer"``, docs/measurements/speed.md): repaid
#: after 82 / 0.062 = about 1,310 steps, rounded up to 1,400 for one run's spread (the paper's 1,500
#: compile); a compilation read from a warm cache has not been timed on CUDA, so it counts as cold
COMPILE_MIN_ITERATIONS_CUDA = 1400


def cpp_compiler() -> str | None:
    """The C++ compiler torch.compile's CPU backend (inductor) would call, as it searches: ``$CXX``,
    else ``g++`` (``clang++`` on macOS) on the PATH; or None."""
    import os
    import shutil
    import sys

    name = os.environ.get("CXX") or ("clang++" if sys.platform == "darwin" else "g++")
    return shutil.which(name)


def python_headers() -> str | None:
    """``Python.h`` of this interpreter, which inductor's CPU kernels include; or None (Debian:
    the python3-dev package)."""
    import sysconfig
    from pathlib import Path

    header = Path(sysconfig.get_paths()["include"]) / "Python.h"
    return str(header) if header.is_file() else None


#: the environment under which torch uses no more than AVX2 on a CPU that has more: its own kernels
#: and inductor's code (``ATEN_CPU_CAPABILITY``), oneDNN's (``ONEDNN_MAX_CPU_ISA``: no AVX-512, so
#: no native bfloat16) and MKL's, which computes torch's float32 matrix products
#: (``MKL_ENABLE_INSTRUCTIONS``; on an AMD CPU MKL takes its AVX2 code in any case); the
#: benchmarks' stand-in for an AVX2-only CPU, read when torch loads (a new process). The clock,
#: caches and memory stay this CPU's.
AVX2_ONLY_ENV = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"}

#: the prefix of the inductor cache's folder for one CPU (:func:`use_inductor_cache`)
CPU_FOLDER_PREFIX = "cpu-"


@functools.cache
def _cpu_features_digest() -> str:
    """8 hex digits of this CPU's feature flags (Linux: ``/proc/cpuinfo``'s first ``flags`` or
    ``Features`` line; elsewhere the processor's name): what ``-march=native`` compiles for."""
    import hashlib
    import platform

    flags = platform.processor()
    try:
        info = read_bytes("/proc/cpuinfo", RECORD_LIMIT).decode("utf-8", "replace").splitlines()
        flags = next((line for line in info if line.split(":")[0].strip() in ("flags", "Features")), flags)
    except (OSError, StageInputError):
        pass
    return hashlib.sha256(flags.encode()).hexdigest()[:8]


def cpu_isa() -> str:
    """This CPU as the code inductor generates for it depends on it, e.g. ``x86_64-avx512-1a2b3c4d``:
    the architecture, the vector instruction set torch's kernels use (``avx512``, ``avx2``,
    ``default``...; ``ATEN_CPU_CAPABILITY`` lowers it, and inductor's vectors follow) and a digest
    of the CPU's feature flags (inductor compiles with ``-march=native``)."""
    import platform

    import torch

    capability = torch.backends.cpu.get_cpu_capability().lower().replace(" ", "-")
    return f"{platform.machine().lower() or 'cpu'}-{capability}-{_cpu_features_digest()}"


def use_inductor_cache() -> None:
    """Point inductor's disk cache at this CPU's folder (``cpu-`` and :func:`cpu_isa`) under
    ``TORCHINDUCTOR_CACHE_DIR`` where it is set, else under ``$XDG_CACHE_HOME/torchinductor`` (the
    project's ``.cache/`` once ``.venv/bin/activate`` is sourced), else under inductor's default
    in the temporary folder. Inductor's cache does not tell CPUs apart: with torch 2.13, code
    generated for AVX-512 and read back under AVX2 gave wrong values, the reverse a corrupted
    heap, and either under no vectors a compile error (``tests/core/test_compile_auto.py``); a
    project folder shared by the nodes of a cluster is where that happens. Calling it again, in
    this process or a child (under another instruction set), names the folder anew; the variable
    set to inductor's default (importing inductor sets it so) counts as not set."""
    import os

    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    folder = Path(os.environ.get("TORCHINDUCTOR_CACHE_DIR") or default_cache_dir())
    if folder.name.startswith(CPU_FOLDER_PREFIX):
        folder = folder.parent
    # inductor sets the variable to its default where it finds none: that default is no one's choice
    if folder == Path(default_cache_dir()) and os.environ.get("XDG_CACHE_HOME"):
        folder = Path(os.environ["XDG_CACHE_HOME"]) / "torchinductor"
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(folder / f"{CPU_FOLDER_PREFIX}{cpu_isa()}")


def _compile_marker(kind: str, device: torch.device, sources: str) -> Path:
    """The file that says a program of ``kind`` built from ``sources`` (a digest of its code and
    data, the caller's), with this torch and Python, has been compiled into this machine's
    inductor cache (:func:`use_inductor_cache`)."""
    import hashlib
    import sys

    import torch
    from torch._inductor.runtime.cache_dir_utils import cache_dir

    use_inductor_cache()
    parts = (torch.__version__, sys.version, device.type, kind, sources)
    digest = hashlib.sha256("\0".join(parts).encode())
    return Path(cache_dir()) / "stages-renderer" / digest.hexdigest()[:24]


def compiled_before(kind: str, device: torch.device, sources: str) -> bool:
    """Whether a program of ``kind`` (what its graph depends on beyond its code, in the caller's
    words) built from ``sources`` (a digest of that code, the caller's) has been compiled on this
    machine before: its compilation is then read
    from inductor's and AOTAutograd's caches (3 s against 75-86 s for the renderer). The caches
    may have been emptied since; the next compilation then pays in full, once."""
    import torch

    try:
        return _compile_marker(kind, torch.device(device), sources).is_file()
    except OSError as exc:  # a cache folder that cannot be made: as if never compiled
        log.debug("no inductor cache to look in: %s", exc)
        return False


def mark_compiled(kind: str, device: torch.device, sources: str) -> None:
    """Leave :func:`compiled_before`'s mark after a successful compilation (written whole or not
    at all; a cache that cannot be written only means the next run decides as if it were cold)."""
    try:
        marker = _compile_marker(kind, device, sources)
        with atomic_path(marker) as part:
            part.write_text(f"{kind}\n")
    except (OSError, StageInputError) as exc:
        log.debug("could not mark the compiled renderer in the inductor cache: %s", exc)


def compile_support(device: torch.device) -> tuple[bool, str]:
    """Whether torch.compile can build the renderer for ``device``, and why: on a CPU it needs a
    C++ compiler (:func:`cpp_compiler`) and the Python headers (:func:`python_headers`); on a GPU,
    Triton; on either, a platform and Python that torch.compile supports (dynamo's own check:
    it has refused Windows and new Pythons in some releases). (What can still fail, the caller
    finds by compiling once, and then runs eager.)"""
    import torch._dynamo

    if not torch._dynamo.is_dynamo_supported():
        return False, "torch.compile does not support this platform or Python"
    if device.type == "cpu":
        cxx = cpp_compiler()
        if not cxx:
            return False, "no C++ compiler ($CXX, else g++) for inductor"
        if not python_headers():
            return False, "no Python headers (Python.h; Debian: python3-dev) for inductor"
        return True, f"C++ compiler {cxx}"
    if device.type == "cuda":
        from torch.utils._triton import has_triton

        return (True, "Triton for CUDA") if has_triton() else (False, "no Triton for inductor on CUDA")
    return False, f"no inductor backend for {device.type}"


def compile_choice(setting: str | bool, device: torch.device, iterations: int, warm: bool = False) -> tuple[bool, str]:
    """Whether the renderer is compiled for a run of ``iterations`` steps on ``device``
    (``optimize.compile_shading``: one of :data:`BF16_CHOICES`; booleans mean on and off), and what
    runs, for the metadata and the plan: ``"torch.compile (<why>)"``, ``"eager"`` (off) or
    ``"eager (<why not>)"``. ``warm``: the same renderer has been compiled on this machine before
    (:func:`compiled_before`), so its compilation is read from the caches.
    ``auto`` compiles on a CPU with a C++ compiler for runs of at least
    :data:`COMPILE_MIN_ITERATIONS` steps, or :data:`COMPILE_MIN_ITERATIONS_WARM` when ``warm``, and
    on CUDA with Triton for runs of at least :data:`COMPILE_MIN_ITERATIONS_CUDA` (warm or not),
    where the compilation has been measured to pay; on other devices it stays eager (not measured
    there); ``on`` compiles wherever a backend is found and otherwise warns and runs eager."""
    choice = lever_choice(setting, "compile_shading")
    if choice == "off":
        return False, "eager"
    supported, why = compile_support(device)
    if choice == "on":
        if not supported:
            log.warning("compile_shading asked for, but %s: the renderer runs eager", why)
        return supported, f"torch.compile ({why})" if supported else f"eager ({why})"
    if device.type not in ("cpu", "cuda"):
        return False, f"eager (auto: compiling the renderer on {device.type} has not been measured to pay)"
    if device.type == "cuda":  # a warm cache's compilation has not been timed there
        needed = COMPILE_MIN_ITERATIONS_CUDA
    else:
        needed = COMPILE_MIN_ITERATIONS_WARM if warm else COMPILE_MIN_ITERATIONS
    cache = "compiled before on this machine" if warm else "not compiled on this machine before"
    if iterations < needed:
        return False, f"eager (auto: {iterations} iterations, fewer than the {needed} that repay a compilation; {cache})"
    if not supported:
        return False, f"eager (auto: {why})"
    return True, f"torch.compile (auto: {iterations} iterations; {cache}; {why})"


def compile_networks_choice(setting: str | bool, device: torch.device, renderer: bool, bf16_networks: bool) -> tuple[bool, str]:
    """Whether the SVBRDF and normal networks are compiled into the renderer's graph while training
    (``optimize.compile_networks``: one of :data:`BF16_CHOICES`; booleans mean on and off), and
    why, for the metadata: only where the renderer itself is compiled (``renderer``,
    :func:`compile_choice`). ``auto`` keeps them out: on a CPU one graph was measured no faster
    per paper step, in bfloat16 (``bf16_networks``) or float32, and its compilation was not read
    back from inductor's cache (docs/measurements/speed.md); on CUDA, where a step is bound by
    kernel launches and one graph launches fewer, ``auto`` puts them in: on an H200 a paper step
    took 0.040 s with one graph against 0.051 s with the renderer alone compiled (2.68x and 2.27x
    the eager step of the same run; a compilation of 90 s either way), so wherever the renderer's
    compilation pays, one graph pays more. ``on`` puts them in wherever the renderer is compiled
    and otherwise warns."""
    choice = lever_choice(setting, "compile_networks")
    if choice == "off":
        return False, "compile_networks: off"
    if not renderer:
        if choice == "on":
            log.warning("compile_networks asked for, but the renderer is not compiled (compile_shading): the networks run eager")
        return False, "compile_networks: the renderer is not compiled"
    if choice == "on":
        return True, "compile_networks: on"
    if device.type == "cuda":
        return True, "compile_networks auto: on CUDA one graph launches fewer kernels (measured faster)"
    if device.type != "cpu":
        return False, f"compile_networks auto: one graph has not been measured on {device.type}"
    precision = "bfloat16" if bf16_networks else "float32"
    return False, f"compile_networks auto: on a CPU one graph was measured no faster ({precision} networks here)"


def compile_static_choice(setting: str | bool, device: torch.device, whole: bool) -> tuple[bool, str]:
    """Whether the one graph (networks and renderer, :func:`compile_networks_choice`) is compiled for
    a fixed number of points (``optimize.compile_static``: one of :data:`BF16_CHOICES`; booleans
    mean on and off): each step's points padded to the training pool's largest view, so that on
    CUDA torch.compile captures it as CUDA graphs (mode ``reduce-overhead``), and on a CPU it runs
    with static shapes; and why, for the metadata. Only where the networks are in the renderer's
    graph (``whole``). ``auto`` leaves it off: on a CPU static shapes were measured slower than
    free ones (a paper step 0.86 s against 0.66: the points padded to the largest view's are 1.4
    times a step's on average), and on a GPU the capture has not been measured yet; ``on`` puts it in where
    the one graph is built and otherwise warns."""
    choice = lever_choice(setting, "compile_static")
    if choice == "off":
        return False, "compile_static: off"
    if not whole:
        if choice == "on":
            log.warning("compile_static asked for, but the networks are not in the renderer's graph (compile_networks)")
        return False, "compile_static: no one graph"
    capture = "CUDA graphs" if device.type == "cuda" else "static shapes"
    if choice == "on":
        return True, f"compile_static: on, {capture}"
    if device.type != "cpu":
        return False, f"compile_static auto: CUDA graphs have not been measured on {device.type}"
    return False, "compile_static auto: on a CPU static shapes were measured slower (the padded points' arithmetic)"


def compile_plan(
    settings: tuple[str | bool, ...],
    device: torch.device,
    iterations: int,
    kinds: tuple[str, str, str],
    bf16_networks: bool,
    sources: str,
) -> tuple[bool, bool, bool, str]:
    """What training compiles, as planned before any compilation: ``settings`` are
    ``(compile_shading, compile_networks[, compile_static])`` (``compile_static`` off where left
    out), ``kinds`` those of the renderer alone, of the one graph of the networks and the renderer
    with free shapes and of that graph with static shapes (the caller's words), whose marks
    (:func:`compiled_before`, with the digest of their ``sources``) say whether the compilation would be read from the caches (the
    one graph's where the networks would be in it). Returns whether the renderer is
    compiled, whether the networks are in its graph, whether that graph has static shapes (CUDA
    graphs on CUDA), and what runs, for the metadata, the plan and the doctor
    (:func:`compile_choice`'s words, or ``"torch.compile, networks and renderer in one graph
    (<why>)"``)."""
    shading, networks, static_setting = (*settings, "off")[:3]
    wanted = compile_networks_choice(networks, device, True, bf16_networks)[0]
    static_wanted = compile_static_choice(static_setting, device, True)[0]
    kind = (kinds[2] if static_wanted else kinds[1]) if wanted else kinds[0]
    renderer, path = compile_choice(shading, device, iterations, compiled_before(kind, device, sources))
    whole, why = compile_networks_choice(networks, device, renderer, bf16_networks)
    static, static_why = compile_static_choice(static_setting, device, whole)
    if whole:
        reasons = f"{path.removeprefix('torch.compile (')[:-1]}; {why}"
        reasons += "" if static_setting in ("off", False) else f"; {static_why}"
        graph = " as CUDA graphs" if static and device.type == "cuda" else ", static shapes" if static else ""
        path = f"torch.compile, networks and renderer in one graph{graph} ({reasons})"
    return renderer, whole, static, path


def precision_summary(bf16: str | bool, bf16_networks: str | bool, device: torch.device, reason: bool = True) -> str:
    """One line for the plan and the doctor: what the two bfloat16 levers resolve to on
    ``device`` (:func:`bf16_choice`), e.g. ``CLIP bfloat16 (bf16: auto), networks bfloat16
    (bf16_networks: auto): CPU with native bfloat16 (...)``; ``reason``: with the part after the colon."""
    parts = []
    for what, name, setting in (("CLIP", "bf16", bf16), ("networks", "bf16_networks", bf16_networks)):
        on = bf16_choice(setting, device, name)[0]
        parts.append(f"{what} {'bfloat16' if on else 'float32'} ({name}: {setting})")
    return ", ".join(parts) + (f": {bf16_support(device)[1]}" if reason else "")
