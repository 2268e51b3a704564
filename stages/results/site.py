"""The HTML report: a folder that scales, or one self-contained page for small grids.

**Folder** (the default): ``index.html`` holds the summary (sortable and filterable in the page,
no CDN, no network), a thumbnail and a link per cell, and the figures (``figures/*.png``, loaded
lazily). Each cell has its own page, ``cells/<mesh>/<prompt>/<variant>/index.html``, with its
renders, material maps, loss curve, metrics, relighting and material-editing figures, and its 3D
viewer, which loads when it scrolls into view. Every asset a page shows lies beside it and is
referenced by a relative path, so the folder can be zipped, served or opened from disk; a cell
page loads only its own assets. A browser opening a page from disk may not fetch files, so the
viewer then reads the cell's model and light from ``assets.js`` (the same bytes as base64, loaded
by a script tag); over HTTP it fetches ``model.glb`` and ``light.hdr`` themselves.

**Single file** (``report.single_file: true``): one ``index.html`` with every image and model
inlined as data URIs: the same table, figures and cell sections on one page.

The 3D viewer is Google's <model-viewer> from the npm package (``node_modules``), copied into the
folder (or inlined). It lights the model with the cell's learned environment (``light.hdr``), with a
toggle to a neutral studio light. Without the package the pages show each cell's static preview
and say why.

Every page shows the guidance and weights that made its cells; when any cell was made with the
test-only random CLIP or fitted to image targets, a banner at the top says so first.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import os
import re
import zipfile
from collections.abc import Callable
from pathlib import Path

import pandas as pd
from jinja2 import Environment, FileSystemLoader, StrictUndefined
from markupsafe import Markup

from ..config.guidance_modes import GUIDANCE_MODES
from ..config.layout import EXPORT_FILES, RENDER_KINDS, VIEWER_FILE
from ..config.records import Column
from ..config.sections import UV_LAYOUT_WORDS
from ..core.errors import StageInputError
from ..core.provenance import atomic_path
from ..core.safefiles import (
    DATA_LIMIT,
    copy_file,
    inside,
    place,
    plain_file,
    read_bytes,
    read_json,
    read_text,
    remove_tree,
    replace,
)
from .figures import SPEED_ACCURACY_TITLE
from .spreadsheet import read_spreadsheet_csv
from .summary import quality_of, summary_columns

log = logging.getLogger(__name__)

#: the summary columns the index table shows (:func:`~stages.results.summary.summary_columns`,
#: headed by their headings), with ``quality``, the cell's quality figure (:func:`quality_of`)
INDEX_COLUMNS = (
    "prompt_text",
    "quality",
    "seconds_optimize",
    "iterations",
    "faces_after",
    "bake_psnr_db",
    "uv_layout",
    "relit_psnr_db",
    "weights",
)
#: a cell's files the pages show: (folder, file, name in the cell's page folder)
CELL_FILES = (
    *(("optimize/renders", f"{kind}.png", f"render_{kind}.png") for kind in (*RENDER_KINDS, "target", "light")),
    ("optimize", "loss.png", "loss.png"),
    ("export", VIEWER_FILE, VIEWER_FILE),  # the export format the viewer reads (config.layout)
    ("export", EXPORT_FILES["usdz"], EXPORT_FILES["usdz"]),
    ("export", "light.hdr", "light.hdr"),
    ("export", "preview.png", "preview.png"),
    ("relight", "relit.png", "relit.png"),
    ("relight", "material_edit.png", "material_edit.png"),
    ("relight", "light_fit.png", "light_fit.png"),
    ("relight", "ground_truth.png", "relit_truth.png"),
    ("metrics", "views.png", "metric_views.png"),
    ("metrics", "targets.png", "metric_targets.png"),
    ("roundtrip", "compare.png", "roundtrip_compare.png"),
)
#: the pages' style sheet, scripts and templates (read when a report is written)
WEB = Path(__file__).resolve().parent / "web"
TEMPLATES = WEB / "templates"
#: a texture map's name as the export writes it (``textures/<name>.png``); other files found there are not shown
TEXTURE_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")
MIME = {".png": "image/png", ".glb": "model/gltf-binary", ".hdr": "image/vnd.radiance"}


#: the texture set a cell page offers, zipped (``textures/<map>.png`` inside)
TEXTURES_ZIP = "textures.zip"
#: the run's asset pack, beside the report's index (the pack stage's output)
PACK = "asset_pack.zip"
#: what a cell offers to download: (name in the cell's page folder, label, what it is)
DOWNLOADS = (
    (VIEWER_FILE, "GLB", "glTF 2.0 binary: the mesh, its PBR textures and the learned lights"),
    (EXPORT_FILES["usdz"], "USDZ", "USD package: the mesh, its UsdPreviewSurface textures and the learned light"),
    (TEXTURES_ZIP, "textures", "the baked texture set as PNG files, zipped"),
)


# ---- shared pieces ---------------------------------------------------------------------------
def templates(model_viewer: Path | None = None) -> Environment:
    """The report's templates, with every value escaped unless Python marked it safe (:class:`Markup`:
    only the style sheet, our scripts and pandas' escaped tables), and ``page_policy(style,
    inline_scripts)`` for each page's Content-Security-Policy (:func:`page_policy`, allowing the
    style sheets of the ``model_viewer`` script the pages use)."""
    env = Environment(loader=FileSystemLoader(TEMPLATES), autoescape=True, undefined=StrictUndefined, keep_trailing_newline=False)
    styles = viewer_styles(model_viewer) if model_viewer is not None and plain_file(model_viewer) else []
    env.globals["page_policy"] = lambda style, scripts: page_policy(style, scripts, styles)
    return env


#: the one style attribute the pages hold: pandas' on a table's header row
TABLE_HEADER_STYLE = "text-align: right;"


def page_policy(style: str, inline_scripts: list[str], viewer_styles: list[str] = ()) -> str:
    """A page's Content-Security-Policy: it loads only its own files (``'self'``: the report's
    folder) and runs only the style sheet and scripts it holds inline, each allowed by its SHA-256
    (with the viewer's own style sheets, ``viewer_styles``, and pandas' table header style); the
    viewer may compile its WebAssembly decoder (``'wasm-unsafe-eval'``, no JavaScript ``eval``) and
    read images and models from ``data:`` URIs (the one-file form) and ``blob:`` URLs (a model
    read from ``assets.js``, the textures inside a GLB). No plug-ins, no ``<base>``, no form
    submits."""

    def digest(text: str) -> str:
        return "'sha256-" + base64.b64encode(hashlib.sha256(str(text).encode("utf-8")).digest()).decode("ascii") + "'"

    scripts = " ".join(dict.fromkeys(["'self'", "'wasm-unsafe-eval'", *(digest(code) for code in inline_scripts)]))
    styles = " ".join(
        dict.fromkeys(["'self'", digest(style), *map(digest, viewer_styles), "'unsafe-hashes'", digest(TABLE_HEADER_STYLE)])
    )
    return (
        f"default-src 'self'; script-src {scripts}; style-src {styles}; img-src 'self' data: blob:; "
        "connect-src 'self' data: blob:; object-src 'none'; base-uri 'none'; form-action 'none'"
    )


def viewer_styles(model_viewer: Path) -> list[str]:
    """The style sheets model-viewer writes into its shadow DOM as ``<style>`` elements: the
    constant ``<style>...</style>`` blocks of its script (no ``${...}`` in them)."""
    text = read_text(model_viewer, DATA_LIMIT)
    return [body for body in re.findall(r"<style>(.*?)</style>", text, re.S) if "${" not in body]


def data_uri(path: Path, mime: str | None = None) -> str:
    mime = mime or MIME.get(Path(path).suffix.lower(), "application/octet-stream")
    return f"data:{mime};base64," + base64.b64encode(read_bytes(path, DATA_LIMIT)).decode("ascii")


def table(frame: pd.DataFrame) -> Markup:
    """A data frame as an HTML table, its values escaped by pandas."""
    return Markup(frame.to_html(index=False, float_format=lambda x: f"{x:.4g}", na_rep="", border=0, escape=True))


def _flag(frame: pd.DataFrame, column: str) -> pd.Series:
    """A yes/no column of the summary (missing or empty: no)."""
    if column not in frame:
        return pd.Series(False, index=frame.index)
    return frame[column].apply(lambda x: bool(x) if x is not None and x == x else False)


def group_rows(frame: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """Split rows so that each guidance mode's (real weights), and test-only numbers, never share
    a table (a guidance no mode of this version labels, from an older tree: a table of its own)."""
    test = _flag(frame, "test_only_weights") | _flag(frame, "eval_test_only")
    guidance = frame["guidance"].astype(str) if "guidance" in frame else pd.Series("", index=frame.index)
    groups = [(mode.table, frame[(guidance == mode.label) & ~test]) for mode in GUIDANCE_MODES.values()]
    known = guidance.isin([mode.label for mode in GUIDANCE_MODES.values()])
    groups += [
        ("Other guidance (not a mode of this version)", frame[~known & ~test]),
        ("TEST ONLY: tiny random CLIP (not real stylisations; never compare with the above)", frame[test]),
    ]
    return [(t, f) for t, f in groups if len(f)]


def origin_banner(frame: pd.DataFrame) -> list[str]:
    """A page's first lines when any of its cells is not a real CLIP stylisation (test-only
    weights, or a guidance mode with a :attr:`~stages.config.guidance_modes.GuidanceMode.banner`)."""
    out = []
    n = len(frame)
    test_only = _flag(frame, "test_only_weights")
    test = int(test_only.sum())
    if test:
        out.append(
            f"TEST ONLY: {test} of {n} cells were made with a tiny CLIP with random weights "
            "(a test model). Their renders and assets are not real stylisations of their prompts."
        )
    guidance = frame["guidance"].astype(str) if "guidance" in frame else pd.Series("", index=frame.index)
    for mode in GUIDANCE_MODES.values():
        count = int(((guidance == mode.label) & ~test_only).sum())
        if mode.banner and count:
            out.append(mode.banner.format(n=count, total=n))
    if "decimation_target_reached" in frame:
        short = frame[frame["decimation_target_reached"].astype(str).str.lower() == "false"].drop_duplicates("mesh")
        for _, r in short.iterrows():
            out.append(
                f"DECIMATION SHORT OF TARGET: mesh {r['mesh']} has "
                f"{int(r['faces_after'])} faces for a target of {int(r['decimation_target'])}: "
                f"{r['decimation_shortfall']}. Its robustness comparison is not at the intended level."
            )
    return out


def _figure(row, column: str) -> float | None:
    if column not in row or not len(row) or _missing(row[column].iloc[0]):
        return None
    return float(row[column].iloc[0])


def _missing(value) -> bool:
    return value is None or (isinstance(value, float) and value != value)


def _entries(row, column: str) -> list | None:
    """A summary column that lists one entry per environment or level (None where it has none)."""
    if column not in row or not len(row):
        return None
    value = row[column].iloc[0]
    return list(value) if isinstance(value, list) and value else None


def fidelity_lines(row) -> list[str]:
    """The cell's UV layout, recovery (image targets, held-out views) and Blender round-trip figures."""
    lines = []
    if "uv_layout" in row and isinstance(row["uv_layout"].iloc[0], str):
        kind = UV_LAYOUT_WORDS.get(row["uv_layout"].iloc[0], row["uv_layout"].iloc[0])
        why = row["uv_why"].iloc[0] if "uv_why" in row and isinstance(row["uv_why"].iloc[0], str) else ""
        lines.append(f"UV layout: {kind}" + (f" ({why})" if why else ""))
    psnr, ssim = _figure(row, "target_psnr_db"), _figure(row, "target_ssim")
    if psnr is not None:
        renderer = str(row["target_renderer"].iloc[0]) if "target_renderer" in row else "?"
        text = f"recovery on {renderer} targets (held-out views, object pixels): {psnr:.2f} dB"
        text += f", SSIM {ssim:.3f}" if ssim is not None else ""
        albedo, rough = _figure(row, "target_albedo_rmse"), _figure(row, "target_roughness_mae")
        scaled = _figure(row, "target_albedo_rmse_scaled")
        if albedo is not None:
            text += f"; albedo RMSE {albedo:.3f}" + (f" ({scaled:.3f} after its scale)" if scaled is not None else "")
        if rough is not None:
            text += f", roughness MAE {rough:.3f}"
        lines.append(text)
    glb, usdz = _figure(row, "roundtrip_glb_psnr_db"), _figure(row, "roundtrip_usdz_psnr_db")
    if glb is not None or usdz is not None:
        parts = [f"{name} {value:.2f} dB" for name, value in (("GLB", glb), ("USDZ", usdz)) if value is not None]
        diffuse = _figure(row, "roundtrip_glb_diffuse_psnr_db")
        text = "Blender round trip (Cycles vs our render, object pixels): " + ", ".join(parts)
        text += f"; GLB diffuse alone {diffuse:.2f} dB" if diffuse is not None else ""
        problems = _figure(row, "roundtrip_problems")
        if problems:
            text += f"; {int(problems)} import problem(s), see roundtrip/meta.json"
        lines.append(text)
    faces = _entries(row, "lod_faces")
    if faces is not None:
        levels = zip(faces, _entries(row, "lod_glb_bytes"), _entries(row, "lod_fidelity_psnr_db"), strict=True)
        parts = [f"lod{k} {int(f):,} faces, {int(b) / 1e6:.2f} MB GLB, {q:.2f} dB" for k, (f, b, q) in enumerate(levels)]
        lines.append("levels of detail (baked render vs the full neural render, object pixels): " + "; ".join(parts))
    return lines


def relit_lines(row) -> list[str]:
    """One line per light the cell was relit under and graded against Mitsuba's render of the true
    material (held-out views, object pixels): the raw figure, the figure after one scale per
    channel (with the scale), and the true material's own figure in our renderer (the ceiling)."""
    ours = _entries(row, "relit_psnr_db")
    if ours is None:
        return []

    def per_environment(column: str, missing=None) -> list:
        entries = _entries(row, column)  # (a figure not every environment has cannot be told apart)
        return entries if entries is not None and len(entries) == len(ours) else [missing] * len(ours)

    envs = per_environment("relit_environments", "?")
    ceilings, scaled = per_environment("relit_ceiling_psnr_db"), per_environment("relit_psnr_scaled_db")
    factors = per_environment("relit_scale")
    return [
        f"under {env}: {q:.2f} dB raw"
        + (f"; {a:.2f} dB after one scale per channel" if a is not None else "")
        + (f" (x {', '.join(f'{x:.2f}' for x in f)})" if f is not None else "")
        + (f"; the true material in our renderer (the ceiling): {c:.2f} dB" if c is not None else "")
        for env, q, a, f, c in zip(envs, ours, scaled, factors, ceilings, strict=True)
    ]


def cell_key(cell: tuple[str, str, str]) -> str:
    return "/".join(cell)


def cell_files(results: Path, cell: tuple[str, str, str]) -> dict[str, Path]:
    """The cell's files that exist, by their name in the cell's page folder (see CELL_FILES),
    plus its texture maps (``texture_<map>.png``) from the export."""
    results = Path(results)
    cdir = results.joinpath(*cell)
    # only plain files, reached without a symbolic link, and only texture names the export writes
    found = {name: cdir / folder / f for folder, f, name in CELL_FILES if plain_file(cdir / folder / f, results)}
    for tex in sorted((cdir / "export" / "textures").glob("*.png")):
        if TEXTURE_NAME.fullmatch(tex.stem) and plain_file(tex, results):
            found[f"texture_{tex.stem}.png"] = tex
    return found


def _shown(value, column: Column | None) -> str:
    """A summary value as a page shows it: a float to 4 significant digits, a list as the
    summary's CSV writes it (its column's :meth:`~stages.config.records.Column.text`)."""
    if isinstance(value, list):
        return str(column.text(value) if column is not None else "/".join(map(str, value)))
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _cell_value(row: pd.Series, name: str) -> dict:
    """One index cell: the text shown (and a ``small`` note after it), its sort value (a list's:
    its first entry's), and whether it is text (left-aligned)."""
    text = name in ("prompt_text", "weights")
    if name == "quality":
        q, quality = quality_of(row)
        return (
            {"shown": "", "small": "", "sort": "", "text": text}
            if q is None
            else {"shown": f"{q:.4g}", "small": quality, "sort": f"{q:.9g}", "text": text}
        )
    value = row.get(name)
    if _missing(value) or (isinstance(value, list) and not value):
        return {"shown": "", "small": "", "sort": "", "text": text}
    first = value[0] if isinstance(value, list) else value
    sort = f"{first:.9g}" if isinstance(first, float) else str(first)
    return {"shown": _shown(value, _columns().get(name)), "small": "", "sort": sort, "text": text}


def _columns() -> dict[str, Column]:
    """The summary's columns by name (:func:`~stages.results.summary.summary_columns`)."""
    return {c.name: c for c in summary_columns()}


def index_headings() -> list[str]:
    """The index table's headings: each of :data:`INDEX_COLUMNS`' own, with its unit."""
    found = _columns()
    return [found[name].title() if name in found else name for name in INDEX_COLUMNS]


def index_tables(frame: pd.DataFrame, link: Callable[[tuple], str], thumb: Callable[[tuple], str | None]) -> list[dict]:
    """The filterable, sortable cell tables (one per origin kind: they never share a table)."""
    tables = []
    for title, sub in group_rows(frame):
        rows = []
        for _, r in sub.iterrows():
            cell = (str(r["mesh"]), str(r["prompt"]), str(r["variant"]))
            text = " ".join([*cell, str(r.get("prompt_text", "")), str(r.get("origin", ""))]).lower()
            values = [_cell_value(r, name) for name in INDEX_COLUMNS]
            rows.append(
                {"cell": cell, "key": cell_key(cell), "text": text, "link": link(cell), "thumb": thumb(cell), "shown": values}
            )
        tables.append({"title": title, "note": title.startswith("TEST ONLY"), "rows": rows})
    return tables


def filter_options(frame: pd.DataFrame) -> list[tuple[str, list[str]]]:
    """The index's filters: each id column's values, in the order they first appear."""
    return [(key, list(dict.fromkeys(frame[key].astype(str)))) for key in ("mesh", "prompt", "variant")]


def figure_entries(report_dir: Path, url: Callable[[Path], str]) -> list[dict]:
    """The figures listed in figures.json: each drawn one's source, or the reason it is not drawn."""
    entries = []
    for e in _figures_record(report_dir).get("figures", []):
        figure = _figure_file(report_dir, e)
        entries.append(
            {
                "title": str(e.get("title", "")),
                "src": None if figure is None else url(figure),
                "caption": str(e.get("caption", "")),
                "skipped": str(e.get("skipped", "the figure file is missing")),
            }
        )
    return entries


def _figures_record(report_dir: Path) -> dict:
    """The report's ``figures.json`` (none: ``{}``), read as data; a record that is not the
    mapping the report stage writes is shown as empty, with a warning."""
    fj = Path(report_dir) / "figures.json"
    if not fj.exists() and not fj.is_symlink():
        return {}
    data = read_json(fj, remedy="Rerun the report stage.")
    if not isinstance(data, dict) or not all(isinstance(data.get(k, []), list) for k in ("figures", "groups")):
        log.warning("%s: not the record the report stage writes; no figures shown", fj)
        return {}
    return {k: [e for e in data.get(k, []) if isinstance(e, dict)] for k in ("figures", "groups")}


def _figure_file(report_dir: Path, entry: dict) -> Path | None:
    """The figure a ``figures.json`` entry names: a plain file inside the report folder, reached
    without a link; an entry naming anything else (an absolute path, ``..``, a link, a FIFO) is
    logged and shown as not drawn (a received report folder is data)."""
    if "file" not in entry:
        return None
    try:
        return inside(report_dir, entry["file"])
    except StageInputError as exc:
        log.warning("figure not shown: %s", exc)
        return None


def _mean_std(mean, std, digits: int) -> str:
    if _missing(mean):
        return ""
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if not _missing(std) and std > 0 else "")


def speed_accuracy_table(report_dir: Path) -> dict | None:
    """The speed/accuracy table as a reader takes it (None where the report has none): per mesh x
    prompt and configuration, what it changes, its seeds, the optimisation's wall time and peak
    memory, its quality (mean ± standard deviation over seeds) and whether it is on the Pareto front
    (and the knee); the CSV keeps every column."""
    sa = Path(report_dir) / "speed_accuracy.csv"
    frame = read_spreadsheet_csv(sa) if sa.exists() or sa.is_symlink() else pd.DataFrame()
    if not len(frame):
        return None

    def text(r, key, default=""):
        value = r.get(key, default)
        return default if _missing(value) else str(value)

    def yes(r, key):
        return str(r.get(key, "")).strip().lower() in ("true", "1", "yes")

    rows = []
    for _, r in frame.iterrows():
        front = "yes, the knee" if yes(r, "knee") else "yes" if yes(r, "pareto") else ""
        change = "the reference" if yes(r, "reference") else text(r, "factor") or "the seed"
        rows.append(
            {
                "mesh x prompt": text(r, "group"),
                "configuration": text(r, "configuration") + (" (ablation)" if yes(r, "ablation") else ""),
                "changes": change,
                "seeds": text(r, "seeds"),
                "optimisation (s)": _mean_std(r.get("seconds"), r.get("seconds_std"), 1),
                "peak memory (MB)": "" if _missing(r.get("peak_mb")) else f"{float(r['peak_mb']):,.0f}",
                "quality": _mean_std(r.get("quality"), r.get("quality_std"), 2),
                "quality measure": text(r, "quality_name"),
                "Pareto front": front,
            }
        )
    shown = pd.DataFrame(rows)
    return {"rows": len(shown), "table": table(shown)}


def _groups(report_dir: Path) -> list[dict]:
    return _figures_record(report_dir).get("groups", [])


def comparison_text(cell: tuple[str, str, str], groups: list[dict]) -> str:
    """What the report compares the cell with: its group's reference, what its configuration
    changes against it, its seed replicates; "" when it is in no comparison (no quality figure)."""
    mesh, prompt, variant = cell
    for g in groups:
        if g["mesh"] != mesh or g["prompt"] != prompt:
            continue
        if variant in g.get("duplicates", {}):
            return f"the same settings as {g['duplicates'][variant]}, seed included: left out of the comparisons"
        conf = next((c for c, vs in g["configurations"].items() if variant in vs), None)
        if conf is None:
            continue  # another group of this mesh x prompt (another quality measure or kind of weights)
        ref = g.get("reference")
        if ref is None:
            text = "no reference variant in this mesh x prompt to compare with"
        elif conf == ref:
            text = "the reference variant"
        else:
            text = f"changes against the reference ({ref}): {g['factors'].get(conf) or 'nothing but the seed'}"
            text += " (an ablation)" if conf in g.get("ablations", []) else ""
        replicates = g["configurations"][conf]
        if len(replicates) > 1:
            text += f"; seed replicates: {', '.join(replicates)}"
        return text
    return ""


def cell_anchor(cell: tuple[str, str, str]) -> str:
    """The element id of a cell's section (``/`` cannot occur in an id part, so ids never collide)."""
    return "cell-" + cell_key(cell)


#: a cell's figures after its maps, renders and metrics: (file in the cell's folder, title)
CELL_FIGURES = (
    ("relit.png", "Relighting (evaluation views under a new environment)"),
    ("light_fit.png", "The new environment and its SG fit"),
    (
        "relit_truth.png",
        "Relit against the truth (held-out views; per light: our relit render | Mitsuba's render of the true material"
        " | 4 x |difference|)",
    ),
    ("material_edit.png", "Material editing (rows: roughness x, columns: specular x)"),
    ("metric_views.png", "Metric views"),
    ("metric_targets.png", "Metric targets"),
    ("roundtrip_compare.png", "Blender round trip, front view: ours | Cycles per format | 4 x |difference|"),
)


def cell_context(
    cell: tuple[str, str, str],
    row: pd.DataFrame,
    files: dict[str, Path],
    url: Callable[[str], str],
    viewer: dict,
    comparison: str,
    downloads: list[dict] = (),
) -> dict:
    """What a cell's section shows: heading, origin, what it is compared with (``comparison``), 3D
    ``viewer``, its ``downloads`` (:func:`downloads`), fidelity figures, material maps, renders, loss
    curve, every summary field and the relighting (its figures printed under it) and
    material-editing figures. ``url(name)``: how the page refers to the cell's file."""
    r = row.iloc[0] if len(row) else None
    origin = "" if r is None else str(r.get("origin", ""))

    def shown(items):
        return [{"src": url(name), "label": label} for name, label in items]

    return {
        "anchor": cell_anchor(cell),
        "key": cell_key(cell),
        "row": r is not None,
        "prompt_text": "" if r is None else str(r.get("prompt_text", "")),
        "origin": origin,
        "origin_is_note": r is not None and any(_flag(row, k).iloc[0] for k in ("test_only_weights", "image_guided")),
        "comparison": comparison,
        "viewer": viewer,
        "fidelity": fidelity_lines(row) if r is not None else [],
        "maps": shown((n, n.removeprefix("texture_").removesuffix(".png")) for n in files if n.startswith("texture_")),
        "renders": shown((n, n.removeprefix("render_").removesuffix(".png")) for n in files if n.startswith("render_")),
        "loss": url("loss.png") if "loss.png" in files else None,
        "fields": [] if r is None else _fields(r),
        "figures": _cell_figures(files, url, relit_lines(row) if r is not None else []),
        "downloads": downloads,
    }


def _cell_figures(files: dict, url: Callable[[str], str], relit: list[str]) -> list[dict]:
    """The cell's figures in :data:`CELL_FIGURES`' order, the relit figures under the one that
    grades them (Mitsuba's truth beside ours; without it, the relit views)."""
    graded = "relit_truth.png" if "relit_truth.png" in files else "relit.png"
    return [
        {"title": title, "src": url(name), "lines": relit if name == graded else []}
        for name, title in CELL_FIGURES
        if name in files
    ]


def _fields(r: pd.Series) -> list[dict]:
    """Every summary column of a cell that has a value (:func:`~stages.results.summary.summary_columns`,
    in order): its name, what it means and its value as text, with its unit."""
    out = []
    for c in summary_columns():
        value = r.get(c.name)
        if _missing(value) or (isinstance(value, list) and not value):
            continue
        shown = f"{value:.6g}" if isinstance(value, float) else _shown(value, c)
        out.append({"name": c.name, "description": c.description, "value": shown + (f" {c.unit}" if c.unit else "")})
    return out


def viewer_context(files: dict[str, Path], url: Callable[[str], str], have_viewer: bool, packed: str | None, label: str) -> dict:
    """A cell's 3D viewer (model-viewer, started when it scrolls into view) with its light toggle;
    without model-viewer or a model (``model`` None), the static preview and why."""
    model = url(VIEWER_FILE) if have_viewer and VIEWER_FILE in files else None
    return {
        "model": model,
        "hdr": url("light.hdr") if model and "light.hdr" in files else "",
        "packed": packed,
        "preview": url("preview.png") if "preview.png" in files else None,
        "label": label,
    }


def write_textures_zip(files: dict[str, Path], out: Path) -> Path | None:
    """The cell's texture maps (``texture_<map>.png`` of :func:`cell_files`) as ``out``, a zip of
    ``textures/<map>.png`` (stored: PNG is compressed already), written atomically; None without maps."""
    maps = sorted((n, f) for n, f in files.items() if n.startswith("texture_"))
    if not maps:
        return None
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
            for name, src in maps:
                z.writestr(f"textures/{name.removeprefix('texture_')}", read_bytes(src, DATA_LIMIT))
    return out


def _size(nbytes: int) -> str:
    return f"{nbytes / 1e6:.1f} MB" if nbytes >= 100_000 else f"{max(nbytes, 1) / 1e3:.0f} kB"


def downloads(available: dict[str, Path], href: Callable[[str], str], pack: tuple[str, Path] | None) -> list[dict]:
    """A cell's download links: each file of :data:`DOWNLOADS` it has (``available``: name -> the
    file, for its size; ``href(name)``: the link), and the run's asset ``pack`` (its link and file)."""
    out = [
        {
            "label": label,
            "href": href(name),
            "file": name,
            "size": _size(available[name].stat().st_size),
            "what": what,
        }
        for name, label, what in DOWNLOADS
        if name in available
    ]
    if pack is not None:
        link, path = pack
        what = "every cell's asset folder of this run in one zip, with an index"
        out.append({"label": "asset pack", "href": link, "file": PACK, "size": _size(path.stat().st_size), "what": what})
    return out


def run_summary(results: Path, cells: list[tuple[str, str, str]], pack: bool) -> dict:
    """The index's summary of the run: how many cells, when their jobs ran (the earliest start and
    the latest finish over every stage record of the cells: ``finished_utc`` less the job's own
    ``timings_s.total``), how much job time that was, and where the assets are."""
    import datetime

    spans, busy = [], 0.0
    for cell in cells:
        for meta in Path(results).joinpath(*cell).glob("*/meta.json"):
            try:
                m = read_json(meta)
                end = datetime.datetime.fromisoformat(str(m["finished_utc"]).replace("Z", "+00:00"))
                took = float(m["timings_s"]["total"])
            except (StageInputError, KeyError, TypeError, ValueError):
                continue  # a record without the times (an older stage, or not ours): left out
            spans.append((end - datetime.timedelta(seconds=took), end))
            busy += took
    out = {"cells": len(cells), "pack": PACK if pack else None, "experiment": Path(results).name}
    if spans:
        first, last = min(a for a, _ in spans), max(b for _, b in spans)
        out.update(
            first=first.strftime("%Y-%m-%d %H:%M UTC"),
            last=last.strftime("%Y-%m-%d %H:%M UTC"),
            wall=_duration((last - first).total_seconds()),
            busy=_duration(busy),
        )
    return out


def _duration(seconds: float) -> str:
    minutes, s = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min" if hours else f"{minutes} min {s:02d} s" if minutes else f"{s} s"


def _page_frame(title: str, **scripts) -> dict:
    """The frame's context: the title, the style sheet (ours, inline) and the scripts."""
    return {
        "title": title,
        "style": Markup(read_text(WEB / "report.css")),
        "script_files": scripts.get("files", []),
        "deferred_files": scripts.get("deferred", []),
        "inline_head": [Markup(code) for code in scripts.get("inline", [])],
    }


def _place(src: Path, dst: Path) -> None:
    """Put the plain file ``src`` at ``dst``: a hard link where the file system allows (no copy),
    else a copy."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    place(src, dst)


def read_summary(report_dir: Path) -> pd.DataFrame:
    """The summary's rows (``summary.json``: every value as the records give it, lists as lists,
    ids as text); a file that is not a list of rows with their ids is one :class:`StageInputError`."""
    path = Path(report_dir) / "summary.json"
    rows = read_json(path, "Rerun the report stage.")
    ids = ("mesh", "prompt", "variant")
    if not isinstance(rows, list) or not all(isinstance(r, dict) and all(isinstance(r.get(k), str) for k in ids) for r in rows):
        raise StageInputError(path, "is not the list of rows the report stage writes", "Rerun the report stage.")
    return pd.DataFrame(rows, columns=list(dict.fromkeys(k for r in rows for k in r)) or list(ids))


def _row(frame: pd.DataFrame, cell: tuple[str, str, str]) -> pd.DataFrame:
    mesh, prompt, variant = cell
    return frame[(frame["mesh"] == mesh) & (frame["prompt"] == prompt) & (frame["variant"] == variant)]


# ---- the folder ------------------------------------------------------------------------------
def write_folder(
    results: Path,
    report_dir: Path,
    cells: list[tuple[str, str, str]],
    model_viewer: Path,
    thumbnail: Callable[[tuple[str, str, str]], object],
) -> dict:
    """Write ``index.html``, ``cells/`` and ``viewer/`` under ``report_dir`` (the summary and
    figures already there). ``thumbnail(cell)``: a PIL image. Returns counts and sizes."""
    report_dir, env = Path(report_dir), templates(model_viewer)
    frame = read_summary(report_dir)
    have_viewer = Path(model_viewer).is_file()
    groups = _groups(report_dir)
    staging = {name: report_dir / f".{name}.partial" for name in ("cells", "viewer")}
    for d in staging.values():
        remove_tree(d)
        d.mkdir(parents=True)
    copy_file(WEB / "cell.js", staging["viewer"] / "cell.js")
    if have_viewer:
        copy_file(model_viewer, staging["viewer"] / "model-viewer.min.js")
    viewers = 0
    for cell in cells:
        folder = staging["cells"].joinpath(*cell)
        folder.mkdir(parents=True)
        files = cell_files(results, cell)
        for name, src in files.items():
            _place(src, folder / name)
        with atomic_path(folder / "thumb.png") as tmp:
            thumbnail(cell).save(tmp, format="PNG")
        offered = {**files}
        if write_textures_zip(files, folder / TEXTURES_ZIP) is not None:
            offered[TEXTURES_ZIP] = folder / TEXTURES_ZIP
        packed = None
        if have_viewer and VIEWER_FILE in files:
            assets = {"glb": base64.b64encode(read_bytes(files[VIEWER_FILE], DATA_LIMIT)).decode("ascii")}
            if "light.hdr" in files:
                assets["hdr"] = base64.b64encode(read_bytes(files["light.hdr"], DATA_LIMIT)).decode("ascii")
            with atomic_path(folder / "assets.js") as tmp:
                tmp.write_text("window.TANGO_CELL_ASSETS = " + json.dumps(assets) + ";\n")
            packed = "assets.js"
            viewers += 1
        up = "../" * (len(cell) + 1)  # cells/<mesh>/<prompt>/<variant>/ back to the report folder
        pack = (f"{up}{PACK}", report_dir / PACK) if plain_file(report_dir / PACK, report_dir) else None
        row, label = _row(frame, cell), cell_key(cell)
        scripts = {"files": [f"{up}viewer/model-viewer.min.js"] if have_viewer else [], "deferred": [f"{up}viewer/cell.js"]}
        viewer = viewer_context(files, lambda n: n, have_viewer, packed, label)
        page = env.get_template("cell.html").render(
            **_page_frame(f"{label}: tango-stylize report", **scripts),
            up=up,
            banner=origin_banner(row),
            have_viewer=have_viewer,
            cell=cell_context(
                cell, row, files, lambda n: n, viewer, comparison_text(cell, groups), downloads(offered, lambda n: n, pack)
            ),
        )
        with atomic_path(folder / "index.html") as tmp:
            tmp.write_text(page)
    # swap the finished folders in, then the index (written last: it is the rule's marker)
    for name, d in staging.items():
        final = report_dir / name
        remove_tree(final)
        replace(d, final)

    def link(cell):
        return "cells/" + "/".join(cell) + "/index.html"

    def thumb(cell):
        return "cells/" + "/".join(cell) + "/thumb.png"

    index = _index_page(
        env,
        frame,
        report_dir,
        (link, thumb, lambda p: Path(p).relative_to(report_dir).as_posix()),
        have_viewer,
        run_summary(results, cells, plain_file(report_dir / PACK, report_dir)),
    )
    with atomic_path(report_dir / "index.html") as tmp:
        tmp.write_text(index)
    size = (report_dir / "index.html").stat().st_size
    log.info("wrote %s (%d cells, %d viewers; index %.2f MB)", report_dir / "index.html", len(cells), viewers, size / 1e6)
    return {"cells": len(cells), "viewers": viewers, "index_bytes": size}


def _index_page(
    env: Environment,
    frame: pd.DataFrame,
    report_dir: Path,
    links: tuple,
    have_viewer: bool,
    summary: dict,
    cells=(),
    head=(),
    end=(),
) -> str:
    """The index page. ``links``: how it refers to a cell's page, a cell's thumbnail and a file of
    the report folder; ``summary``: the run's (:func:`run_summary`); ``cells``: the cells' sections
    (the one-file form); ``head`` and ``end``: scripts to inline in the head and at the end."""
    link, thumb, url = links
    csvs = [n for n in ("summary.csv", "speed_accuracy.csv") if plain_file(Path(report_dir) / n, report_dir)]
    overview = Path(report_dir) / "overview.png"
    figures = figure_entries(report_dir, url)
    pareto = [f for f in figures if f["title"].startswith(SPEED_ACCURACY_TITLE)]
    return env.get_template("index.html").render(
        **_page_frame("tango-stylize report", inline=list(head)),
        n_cells=summary["cells"],
        summary=summary,
        banner=origin_banner(frame),
        have_viewer=have_viewer,
        csvs=csvs if not cells else [],
        filters=filter_options(frame),
        n_rows=len(frame),
        columns=index_headings(),
        tables=index_tables(frame, link, thumb),
        speed_accuracy=speed_accuracy_table(report_dir),
        pareto=pareto,
        figures=[f for f in figures if f not in pareto],
        overview=url(overview) if plain_file(overview, report_dir) else None,
        cells=list(cells),
        inline_end=[Markup(code) for code in (*end, read_text(WEB / "index.js"))],
    )


# ---- one file ------------------------------------------------------------------------------
def _single_file_downloads(files: dict[str, Path], folder: Path, page_dir: Path) -> dict[str, Path]:
    """What a one-file report offers a cell to download: its export's own files where they lie in
    the results (linked relative to the page, so the results folder must stay beside it) and its
    texture set zipped under the report's ``downloads/``."""
    offered = {name: files[name] for name, _, _ in DOWNLOADS if name in files}
    zipped = write_textures_zip(files, folder / TEXTURES_ZIP)
    if zipped is not None:
        offered[TEXTURES_ZIP] = zipped
    return offered


def write_single_file(results: Path, report_dir: Path, cells: list[tuple[str, str, str]], out: Path, model_viewer: Path) -> dict:
    """One self-contained page: the index, then every cell's section with its images and model
    inlined (data URIs) and its viewer started when it scrolls into view."""
    report_dir = Path(report_dir)
    for name in ("cells", "viewer"):  # pages of an earlier folder-form report would go stale beside it
        if (report_dir / name).is_dir() and Path(out).parent == report_dir:
            log.info("removing %s: this report is one file now", report_dir / name)
            remove_tree(report_dir / name)
    frame, env = read_summary(report_dir), templates(model_viewer)
    have_viewer = Path(model_viewer).is_file()
    groups = _groups(report_dir)
    sections, viewers = [], 0
    has_pack = plain_file(report_dir / PACK, report_dir)
    for cell in cells:
        files = cell_files(results, cell)

        def url(name, files=files):
            return data_uri(files[name]) + ("#light.hdr" if name == "light.hdr" else "")

        viewer = viewer_context(files, url, have_viewer, None, cell_key(cell))
        viewers += viewer["model"] is not None
        offered = _single_file_downloads(files, report_dir / "downloads" / cell_key(cell), Path(out).parent)
        pack = (os.path.relpath(report_dir / PACK, Path(out).parent), report_dir / PACK) if has_pack else None
        listed = downloads(offered, lambda n, o=offered: os.path.relpath(o[n], Path(out).parent), pack)
        sections.append(cell_context(cell, _row(frame, cell), files, url, viewer, comparison_text(cell, groups), listed))
    page = _index_page(
        env,
        frame,
        report_dir,
        (lambda c: "#" + cell_anchor(c), lambda c: None, data_uri),
        have_viewer,
        run_summary(results, cells, has_pack),
        cells=sections,
        head=[read_text(model_viewer, DATA_LIMIT)] if have_viewer else [],
        end=[read_text(WEB / "cell.js")],
    )
    with atomic_path(Path(out)) as tmp:
        tmp.write_text(page)
    size = Path(out).stat().st_size
    log.info("wrote %s (one file, %d cells, %d viewers, %.1f MB)", out, len(cells), viewers, size / 1e6)
    return {"cells": len(cells), "viewers": viewers, "index_bytes": size}
