"""tango: one command in front of the tool's everyday commands (``python -m stages`` is the same).

Each subcommand is the module named beside it with the same arguments; ``tango <command> --help``
prints that command's own help.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from . import _version

#: the subcommands: (what it does, the module whose ``main`` runs it)
COMMANDS = {
    "demo": ("the image-guided demo (config/demo.yaml): two cells through every stage, no weights needed", None),
    "quick": ("stylise one's own mesh from a prompt, without writing YAML", "stages.quick"),
    "doctor": ("check in seconds what a run of a config needs, and how to fix each missing piece", "stages.doctor"),
    "plan": ("what a run of a config will do and about how long it will take here", "stages.plan"),
    "check": ("read a config (a received one, say) as the workflow will, without running anything", "stages.config.workflow"),
}
#: the repository root: the workflow and its configs
REPO = Path(__file__).resolve().parents[1]


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [f"usage: tango <command> [arguments]   (tango-stylize {_version()})", "", "commands:"]
    lines += [f"  {name:<{width}}  {what}" for name, (what, _) in COMMANDS.items()]
    lines += ["", "tango <command> --help: that command's arguments; tango --version: the version"]
    return "\n".join(lines) + "\n"


def demo(argv: list[str]) -> int:
    """``tango demo [--cores N] [--dry-run] [snakemake options]``: Snakemake on config/demo.yaml,
    results under the working directory's ``results/demo``."""
    import argparse
    import os
    import subprocess

    parser = argparse.ArgumentParser(prog="tango demo", description=COMMANDS["demo"][0] + ".")
    parser.add_argument("--cores", type=int, default=2, help="CPU cores Snakemake may use (default 2)")
    parser.add_argument("--dry-run", action="store_true", help="list the jobs; run nothing")
    args, rest = parser.parse_known_args(argv)
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--cores", str(args.cores)]
    cmd += ["--configfile", str(REPO / "config" / "demo.yaml"), *(["-n"] if args.dry_run else []), *rest]
    # the stages' own `python -m` find this interpreter's packages first
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run(cmd, env=env).returncode


def equivalent(argv: list[str]) -> list[str]:
    """The plain command a ``tango`` command line stands for (``tango check C`` ->
    ``python -m stages.config --check --configfile C``; ``tango demo`` -> ``snakemake --cores 2
    --configfile config/demo.yaml``), as a user would type it from the repository root."""
    name, rest = argv[0], list(argv[1:])
    if name == "demo":
        cores = rest[rest.index("--cores") + 1] if "--cores" in rest else "2"
        if "--cores" in rest:
            del rest[rest.index("--cores") : rest.index("--cores") + 2]
        rest = ["-n" if a == "--dry-run" else a for a in rest]
        return ["snakemake", "--cores", cores, "--configfile", "config/demo.yaml", *rest]
    if name == "check":
        rest = ["--check", *(["--configfile", *rest] if rest and not rest[0].startswith("-") else rest)]
    module = COMMANDS[name][1]
    return ["python", "-m", "stages.config" if module == "stages.config.workflow" else module, *rest]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        sys.stdout.write(usage())
        return 0 if argv else 2
    if argv[0] == "--version":
        sys.stdout.write(f"tango-stylize {_version()}\n")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        sys.stderr.write(f"tango: unknown command {name!r}: use one of {', '.join(COMMANDS)} (tango --help)\n")
        return 2
    if name == "demo":
        return demo(rest)
    return importlib.import_module(COMMANDS[name][1]).main(equivalent(argv)[3:])


if __name__ == "__main__":
    raise SystemExit(main())
