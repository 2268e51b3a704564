"""The report's figures, each comparing like with like (:mod:`stages.results.compare`).

Every function writes its PNG files under ``out_dir`` and returns figure entries for
``figures.json``: ``{"file", "title", "caption"}`` for a drawn figure, or ``{"title",
"skipped"}`` with the reason when there is nothing to compare (the page says why instead of
drawing an empty or misleading plot). Small multiples are split over files of at most
``panels`` panels.
"""

from __future__ import annotations

import io
import logging
import math
from pathlib import Path

import numpy as np

from ..core.provenance import atomic_path
from .compare import Group, trade_off
from .spreadsheet import read_csv

log = logging.getLogger(__name__)

#: a colour per sweep factor (cycled)
PALETTE = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")


#: the speed/accuracy figure's title (the report's index shows it in its speed/accuracy section)
SPEED_ACCURACY_TITLE = "Speed / accuracy per mesh x prompt"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    plt = _pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())


def _chunks(items: list, size: int) -> list[list]:
    return [items[i : i + size] for i in range(0, len(items), size)] or [[]]


def _panel_grid(n: int, width: float = 3.2, height: float = 2.6, max_columns: int = 4):
    plt = _pyplot()
    cols = min(n, max_columns)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, height * rows), dpi=100, squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat[:n])


def _chunk_entry(fig, out_dir: Path, stem: str, k: int, total: int, title: str, caption: str) -> dict:
    """Lay out and write the ``k``-th of ``total`` files of a small-multiple figure
    (``stem.png``, or ``stem_<k+1>.png`` when split) and return its figures.json entry."""
    fig.tight_layout()
    name = f"{stem}.png" if total == 1 else f"{stem}_{k + 1}.png"
    _save(fig, out_dir / name)
    return {"file": name, "title": title + (f" ({k + 1} of {total})" if total > 1 else ""), "caption": caption}


def speed_accuracy_figures(out_dir: Path, groups: list[Group], panels: int) -> list[dict]:
    """Per mesh x prompt: optimisation wall time against quality for each configuration (mean
    over its seeds, bars = one standard deviation), the group's Pareto front and its knee; the
    configurations of one sweep factor are joined to the reference by a line of their colour.
    Never across meshes or prompts."""
    title = SPEED_ACCURACY_TITLE
    tradeoffs = [(g, trade_off(g)) for g in groups]
    drawn = [(g, t) for g, t in tradeoffs if len(t) >= 2]
    if not drawn:
        why = (
            "no cells with both a quality figure and a wall time"
            if not any(tradeoffs)
            else "every mesh x prompt has a single configuration (variants that differ only by seed count as one): "
            "there is no trade to draw"
        )
        return [{"title": title, "skipped": why}]
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    entries = []
    chunks = _chunks(drawn, panels)
    for k, chunk in enumerate(chunks):
        fig, axes = _panel_grid(len(chunk))
        for ax, (g, points) in zip(axes, chunk, strict=True):
            colours: dict[str, str] = {}
            ref = next((p for p in points if p["reference"]), None)
            for p in points:
                if p["factor"] and p["factor"] not in colours:
                    colours[p["factor"]] = PALETTE[len(colours) % len(PALETTE)]
            for factor, colour in colours.items():
                line = sorted([p for p in points if p["factor"] == factor] + ([ref] if ref else []), key=lambda p: p["seconds"])
                ax.plot([p["seconds"] for p in line], [p["quality"] for p in line], c=colour, lw=0.8, alpha=0.6)
            for p in points:
                colour = "k" if p["reference"] else colours.get(p["factor"], "tab:gray")
                ax.errorbar(
                    p["seconds"],
                    p["quality"],
                    xerr=p["seconds_std"] or None,
                    yerr=p["quality_std"] or None,
                    fmt="o",
                    ms=4,
                    c=colour,
                    mfc=colour if p["pareto"] else "white",
                    zorder=3,
                )
                label = p["configuration"] + (f" x{p['seeds']}" if p["seeds"] > 1 else "")
                ax.annotate(label, (p["seconds"], p["quality"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
            front = sorted((p for p in points if p["pareto"]), key=lambda p: p["seconds"])
            ax.plot([p["seconds"] for p in front], [p["quality"] for p in front], c="tab:red", lw=1, ls="--", zorder=2)
            for p in points:
                if p["knee"]:
                    ax.scatter(p["seconds"], p["quality"], s=120, facecolors="none", edgecolors="tab:red", zorder=4)
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(ScalarFormatter())
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_title(panel_title(g.label + (" (TEST-ONLY weights)" if g.test_only else "")), fontsize=8)
            ax.set_xlabel("optimisation wall time (s, log)", fontsize=7)
            ax.set_ylabel(g.quality_name, fontsize=6)
            ax.tick_params(labelsize=6)
            ax.grid(alpha=0.3)
        caption = (
            "Each panel is one mesh x prompt. Points: configurations (filled: on the Pareto front, dashed red; ringed: "
            "the knee); black: the reference variant; a colour per sweep factor, joined to the reference; bars: one "
            "standard deviation over seeds (xN = N seeds)."
        )
        entries.append(_chunk_entry(fig, out_dir, "speed_accuracy", k, len(chunks), title, caption))
    skipped = len(tradeoffs) - len(drawn)
    if skipped:
        entries[-1]["caption"] += f" {skipped} mesh x prompt group(s) with a single configuration are not drawn."
    return entries


def ablation_figures(out_dir: Path, groups: list[Group], panels: int) -> list[dict]:
    """Ablation bars: per mesh x prompt, the reference and each ablation (mean over seeds,
    bars = one standard deviation); then, over every mesh x prompt that has them, each
    ablation's change against the reference (mean and standard deviation over the groups)."""
    title = "Ablations"
    with_ablations = [g for g in groups if g.reference is not None and g.ablations]
    if not with_ablations:
        return [
            {
                "title": title,
                "skipped": "no ablation variants in this experiment: no variant differs from the reference only by "
                "switching components off (name them with report.ablations)",
            }
        ]
    entries = []
    chunks = _chunks(with_ablations, panels)
    for k, chunk in enumerate(chunks):
        fig, axes = _panel_grid(len(chunk))
        for ax, g in zip(axes, chunk, strict=True):
            stats = g.stats("quality")
            names = [g.reference] + g.ablations
            means = [stats[c][0] for c in names]
            stds = [stats[c][1] for c in names]
            ax.bar(range(len(names)), means, yerr=stds, color=["k"] + ["tab:blue"] * len(g.ablations), capsize=3)
            ax.set_xticks(range(len(names)), [f"{c}\n(n={stats[c][2]})" for c in names], fontsize=6, rotation=30)
            low = min(m - s for m, s in zip(means, stds, strict=True))
            high = max(m + s for m, s in zip(means, stds, strict=True))
            pad = 0.1 * max(high - low, 1e-6)
            ax.set_ylim(low - pad, high + pad)
            ax.set_title(panel_title(g.label + (" (TEST-ONLY weights)" if g.test_only else "")), fontsize=8)
            ax.set_ylabel(g.quality_name, fontsize=6)
            ax.tick_params(axis="y", labelsize=6)
        caption = (
            "Black: the reference variant; blue: variants that switch a component off. Bars: mean over seeds, whiskers "
            "one standard deviation (n = seeds). The y axis is zoomed to the bars."
        )
        entries.append(_chunk_entry(fig, out_dir, "ablations", k, len(chunks), title + " per mesh x prompt", caption))
    # averaged: change against the reference, per quality measure and weights kind
    kinds: dict[tuple[str, bool], dict[str, list[float]]] = {}
    for g in with_ablations:
        stats = g.stats("quality")
        for c in g.ablations:
            kinds.setdefault((g.quality_name, g.test_only), {}).setdefault(c, []).append(stats[c][0] - stats[g.reference][0])
    fig, axes = _panel_grid(len(kinds), width=4.5, height=3.0, max_columns=2)
    for ax, ((qname, test_only), deltas) in zip(axes, kinds.items(), strict=True):
        names = list(deltas)
        means = [float(np.mean(deltas[c])) for c in names]
        stds = [float(np.std(deltas[c], ddof=1)) if len(deltas[c]) > 1 else 0.0 for c in names]
        ax.bar(range(len(names)), means, yerr=stds, color="tab:blue", capsize=3)
        ax.axhline(0, c="k", lw=0.8)
        ax.set_xticks(range(len(names)), [f"{c}\n({len(deltas[c])} groups)" for c in names], fontsize=6, rotation=30)
        ax.set_ylabel(f"change vs reference\n{qname}", fontsize=6)
        ax.tick_params(axis="y", labelsize=6)
        ax.set_title("mean over mesh x prompt" + (" (TEST-ONLY weights)" if test_only else ""), fontsize=8)
    fig.tight_layout()
    _save(fig, out_dir / "ablations_mean.png")
    entries.append(
        {
            "file": "ablations_mean.png",
            "title": "Ablations averaged over mesh x prompt",
            "caption": "Each ablation's change in quality against the reference of the same mesh x prompt, averaged over "
            "the groups that have both; whiskers: one standard deviation over the groups.",
        }
    )
    return entries


def loss_figures(
    out_dir: Path, results: Path, cells: list[tuple[str, str, str]], panels: int, kinds: dict | None = None
) -> list[dict]:
    """Loss curves as small multiples: one panel per mesh x prompt and kind of run (``kinds``:
    cell -> e.g. "CLIP" or "image-guided, TEST ONLY": losses of different guidance or weights
    never share an axis), its variants overlaid (a legend when there are few), each panel on its
    own axes."""
    import pandas as pd

    title = "Loss curves per mesh x prompt"
    kinds = kinds or {}
    several = len(set(kinds.get(c, "") for c in cells)) > 1
    curves: dict[tuple[str, str, str], list[tuple[str, pd.DataFrame]]] = {}
    for mesh, prompt, variant in cells:
        f = Path(results) / mesh / prompt / variant / "optimize" / "loss.csv"
        if f.exists() or f.is_symlink():
            key = (mesh, prompt, kinds.get((mesh, prompt, variant), ""))
            loss = read_csv(f, "Rerun the cell's optimisation.", usecols=["iteration", "loss"], dtype=float)
            curves.setdefault(key, []).append((variant, loss))
    if not curves:
        return [{"title": title, "skipped": "no cell has a loss record (optimize/loss.csv)"}]
    entries = []
    keys = list(curves)
    chunks = _chunks(keys, panels)
    for k, chunk in enumerate(chunks):
        fig, axes = _panel_grid(len(chunk), width=3.0, height=2.2, max_columns=5)
        for ax, key in zip(axes, chunk, strict=True):
            for variant, d in curves[key]:
                ax.plot(d["iteration"], d["loss"], lw=0.7, label=variant)
            ax.set_title(panel_title(f"{key[0]} / {key[1]}" + (f" ({key[2]})" if several else "")), fontsize=8)
            ax.tick_params(labelsize=6)
            if len(curves[key]) <= 8:
                ax.legend(fontsize=5)
        fig.supxlabel("iteration", fontsize=8)
        fig.supylabel("loss", fontsize=8)
        caption = (
            "One panel per mesh x prompt with its variants; each panel has its own axes (losses of different meshes or "
            "prompts are not on one scale). Each cell's page has its own curve."
        )
        entries.append(_chunk_entry(fig, out_dir, "loss_curves", k, len(chunks), title, caption))
    return entries


#: the longest line of a panel's title (characters at 8 points across a 3-inch panel)
PANEL_TITLE_CHARS = 44


def panel_title(text: str, width: int = PANEL_TITLE_CHARS) -> str:
    """``text`` wrapped to lines of at most ``width`` characters (ids of 64 characters are split),
    so that a panel's title stays over its panel."""
    import textwrap

    return "\n".join(textwrap.wrap(text, width, break_long_words=True, break_on_hyphens=False)) or text


def robustness_figure(
    out_dir: Path,
    results: Path,
    cells: list[tuple[str, str, str]],
    decimated: dict[str, str],
    faces: dict[str, int],
    quality: dict[tuple[str, str, str], str],
    tile,
    relit: dict[tuple[str, str, str], str] | None = None,
) -> list[dict]:
    """Each mesh beside its decimated versions, finest first (face counts in the column heads), one
    row per prompt x variant run on the original and at least one decimated version, with the
    quality of each render under it (``quality``: cell -> its figure as text) and, where the cell
    was graded under another light, the relit figure beside its ceiling (``relit``: cell -> text,
    :func:`relit_text`). A level that did not run a row's cell is left blank."""
    from PIL import Image, ImageDraw

    title = "Robustness: each mesh beside its decimated versions"
    relit = relit or {}
    present = set(cells)
    meshes = list(dict.fromkeys(c[0] for c in cells))
    levels: dict[str, list[str]] = {}
    for dec, orig in decimated.items():
        if orig in meshes and dec in meshes:
            levels.setdefault(orig, []).append(dec)
    if not levels:
        return [{"title": title, "skipped": "no mesh of this experiment has a decimated version in the grid"}]
    entries = []
    size, head, label_w, under = 192, 40, 180, 30
    for orig, decs in levels.items():
        columns = [orig] + sorted(decs, key=lambda m: (-faces.get(m, 0), m))
        heads = " | ".join(f"{m} ({faces.get(m, 0):,} faces)" for m in columns)
        rows = [(p, v) for (m, p, v) in cells if m == orig and any((d, p, v) in present for d in decs)]
        if not rows:
            entries.append(
                {"title": f"{title}: {heads}", "skipped": "no prompt x variant ran on the original and a decimated version"}
            )
            continue
        canvas = Image.new("RGB", (label_w + len(columns) * size, head + (size + under) * len(rows)), "white")
        draw = ImageDraw.Draw(canvas)
        for j, m in enumerate(columns):
            draw.text((label_w + j * size + 4, 4), f"{m}\n{faces.get(m, 0):,} faces", fill="black")
        for i, (p, v) in enumerate(rows):
            y = head + i * (size + under)
            draw.text((4, y + 6), f"{p} / {v}", fill="black")
            for j, m in enumerate(columns):
                if (m, p, v) not in present:
                    continue
                canvas.paste(tile((m, p, v), size), (label_w + j * size, y))
                text = "\n".join(t for t in (quality.get((m, p, v)), relit.get((m, p, v))) if t)
                draw.text((label_w + j * size + 4, y + size + 1), text, fill="black")
        name = f"robustness_{orig}.png"
        path = out_dir / name
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            canvas.save(tmp, format="PNG")
        caption = "Front evaluation view of each cell; under each render its quality figure"
        if any(c in relit for c in present if c[0] in columns):
            caption += (
                ", and its figure under the first relighting environment beside that light's ceiling "
                "(the true material in the renderer)"
            )
        entries.append({"file": name, "title": f"{title}: {heads}", "caption": caption + "."})
    return entries


def relit_text(row: dict) -> str | None:
    """The first relighting environment's scaled figure and ceiling of a summary row, as a short
    label (``relit 24.37 | ceiling 25.26 dB``), or None where the cell was not relit."""
    scaled, ceiling = row.get("relit_psnr_scaled_db"), row.get("relit_ceiling_psnr_db")
    if not scaled or not isinstance(scaled, list):
        return None
    text = f"relit {scaled[0]:.2f}"
    if ceiling and isinstance(ceiling, list):
        text += f" | ceiling {ceiling[0]:.2f}"
    return text + " dB"


def variant_grids(out_dir: Path, cells: list[tuple[str, str, str]], tile) -> list[dict]:
    """Per mesh: rows = variants, columns = prompts (front evaluation view of each cell)."""
    from PIL import Image, ImageDraw

    entries = []
    present = set(cells)
    size, head, label_w = 192, 24, 160
    for mesh in dict.fromkeys(c[0] for c in cells):
        prompts = list(dict.fromkeys(p for m, p, _ in cells if m == mesh))
        variants = list(dict.fromkeys(v for m, _, v in cells if m == mesh))
        canvas = Image.new("RGB", (label_w + size * len(prompts), head + size * len(variants)), "white")
        draw = ImageDraw.Draw(canvas)
        for j, p in enumerate(prompts):
            draw.text((label_w + j * size + 4, 6), p, fill="black")
        for i, v in enumerate(variants):
            draw.text((4, head + i * size + 6), v, fill="black")
            for j, p in enumerate(prompts):
                if (mesh, p, v) in present:
                    canvas.paste(tile((mesh, p, v), size), (label_w + j * size, head + i * size))
        name = f"grid_{mesh}.png"
        with atomic_path(out_dir / name) as tmp:
            canvas.save(tmp, format="PNG")
        entries.append(
            {"file": name, "title": f"{mesh}: variants x prompts", "caption": "Rows: variants; columns: prompts; front view."}
        )
    return entries
