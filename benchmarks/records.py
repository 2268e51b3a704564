"""The measured figures the documentation quotes, one record each, and the pages made from them.

A record (``benchmarks/figures/records/<id>.json``) holds one figure: ``what`` was measured, its ``value``
as the pages print it (and, for the headline table only, a ``detail``), the ``date``, the
``commit``, the ``machine``, the ``command`` that measured it and the measurements ``page`` that
tells the whole story. A benchmark that measures a quoted figure writes its record with
:func:`write_record` (the date, commit and machine filled in here); the pages never restate one:

* ``docs/measurements/index.md``'s headline table, between ``<!-- headline:start -->`` and
  ``<!-- headline:end -->``, is generated from every record;
* any page quotes a record's value as ``<!--fig:ID-->value<!--/fig-->`` (invisible in the page),
  and the text between the marks is the record's ``value``.

    python -m benchmarks.records --write   # regenerate the table and every quoted value
    python -m benchmarks.records --check   # exit 1 naming what is out of date (the docs tests run it)

Standard library only: the documentation's tests read the records without torch.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RECORDS = REPO / "benchmarks" / "figures" / "records"
HEADLINE_PAGE = REPO / "docs" / "measurements" / "index.md"
START, END = "<!-- headline:start -->", "<!-- headline:end -->"
#: a quoted figure in a page: ``<!--fig:ID-->value<!--/fig-->``
QUOTE = re.compile(r"<!--fig:([\w.-]+)-->(.*?)<!--/fig-->", re.S)
#: the pages that may quote records
PAGES = [REPO / "README.md", REPO / "config" / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
FIELDS = ("id", "what", "value", "date", "commit", "machine", "command", "page")


def machine() -> str:
    """This machine in words: its CPU model and count, memory, and its GPU where torch sees one."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = ""
    try:
        pages = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        memory = f", {pages / 2**30:.0f} GB"
    except (ValueError, OSError, AttributeError):
        pass
    return f"{model}, {os.cpu_count()} CPUs{memory}"


def disk_bytes(path: Path) -> int:
    """The blocks the files under ``path`` take (links not followed, each inode counted once)."""
    seen, total = set(), 0
    for root, _, files in os.walk(path):
        for name in files:
            st = os.lstat(os.path.join(root, name))
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                total += st.st_blocks * 512
    return total


def commit() -> str:
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def write_record(rid: str, what: str, value: str, command: str, page: str, detail: str = "", when: str | None = None) -> Path:
    """Write (or replace) the record ``rid`` with this machine, the checkout's commit and today's
    date (UTC, or ``when``); returns its path. Run ``python -m benchmarks.records --write`` after."""
    if not re.fullmatch(r"[\w.-]+", rid):
        raise ValueError(f"a record id is letters, digits, '_', '.' and '-': {rid!r}")
    record = {
        "id": rid,
        "what": what,
        "value": value,
        "detail": detail,
        "date": when or datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
        "commit": commit(),
        "machine": machine(),
        "command": command,
        "page": page,
    }
    path = RECORDS / f"{rid}.json"
    if path.is_file():  # a record measured again keeps its place in the headline table
        order = json.loads(path.read_text(encoding="utf-8")).get("order")
        if order is not None:
            record["order"] = order
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def load_records(folder: Path = RECORDS) -> dict[str, dict]:
    """Every record by id, in the table's order (each record's ``order``, then its id)."""
    out = {}
    for path in Path(folder).glob("*.json"):
        record = json.loads(path.read_text(encoding="utf-8"))
        missing = [k for k in FIELDS if not record.get(k)]
        if missing or record["id"] != path.stem:
            raise SystemExit(f"{path}: a record needs {', '.join(FIELDS)} and its file named after its id (missing: {missing})")
        out[record["id"]] = record
    return dict(sorted(out.items(), key=lambda kv: (kv[1].get("order", 1000), kv[0])))


def page_title(link: str) -> str:
    """The title (first heading) of the page a record's ``page`` links, relative to the headline page."""
    target = (HEADLINE_PAGE.parent / link.split("#")[0]).resolve()
    for line in target.read_text(encoding="utf-8").splitlines():
        if line.startswith("# "):
            return line[2:].strip()
    raise SystemExit(f"{target}: no title (a first '# ' heading) for the headline table's link")


def cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def headline_table(records: dict[str, dict]) -> str:
    """The headline table's markdown (between the marks)."""
    rows = ["| figure | value | date | commit | machine | command | details |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in records.values():
        value = r["value"] + (f" {r['detail']}" if r.get("detail") else "")
        link = f"[{page_title(r['page'])}]({r['page']})"
        parts = (cell(r["what"]), cell(value), r["date"], r["commit"], cell(r["machine"]), cell(r["command"]), link)
        rows.append("| " + " | ".join(parts) + " |")
    return "\n".join(rows)


def rendered(text: str, records: dict[str, dict], page: Path) -> tuple[str, list[str]]:
    """``text`` with every quoted figure set to its record's value, and the problems (unknown ids)."""
    problems = []

    def fill(m: re.Match) -> str:
        rid = m.group(1)
        if rid not in records:
            problems.append(f"{page}: quotes {rid!r}, which no record in benchmarks/figures/records/ holds")
            return m.group(0)
        return f"<!--fig:{rid}-->{records[rid]['value']}<!--/fig-->"

    out = QUOTE.sub(fill, text)
    if page == HEADLINE_PAGE:
        if START not in out or END not in out:
            problems.append(f"{page}: no {START} ... {END} marks for the headline table")
        else:
            head, rest = out.split(START, 1)
            out = head + START + "\n" + headline_table(records) + "\n" + END + rest.split(END, 1)[1]
    return out, problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", action="store_true", help="regenerate the headline table and every quoted figure")
    group.add_argument("--check", action="store_true", help="exit 1 when a page is out of date or quotes no record")
    parser.add_argument("--records", type=Path, default=RECORDS, help="the records' folder (default: the project's)")
    parser.add_argument("--page", type=Path, action="append", help="only these pages (repeatable; default: every page)")
    args = parser.parse_args(argv)
    records = load_records(args.records)
    stale, problems = [], []
    for page in args.page or PAGES:
        text = page.read_text(encoding="utf-8")
        new, found = rendered(text, records, page)
        problems += found
        if new != text:
            stale.append(str(page))
            if args.write:
                page.write_text(new, encoding="utf-8")
    for line in problems:
        sys.stderr.write(line + "\n")
    if args.check and stale:
        sys.stderr.write(f"out of date (python -m benchmarks.records --write): {', '.join(stale)}\n")
    return 1 if problems or (args.check and stale) else 0


if __name__ == "__main__":
    raise SystemExit(main())
