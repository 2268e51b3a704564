"""html_report: one static, self-contained HTML page over every grid cell.

Tables (the summary, split so that numbers from real CLIP weights, from the tiny test-only CLIP and
from image targets never share a table), the speed/accuracy table, plots (loss curves, Pareto
front, ablation bars), image grids (variants x prompts per mesh; original vs decimated), and for
each cell an interactive 3D viewer of its GLB (Google's <model-viewer>, bundled from the npm
package into the page: no CDN, no network). Images and models are embedded as data URIs, so the
single file opens anywhere, including from disk.

Without Node.js's packages (``node_modules/@google/model-viewer``, installed by ``npm ci`` in
``scripts/setup.sh`` when npm exists) the page is still written, with each cell's static preview
image in place of the 3D viewer, a warning in the log and a notice at the top of the page.

Every cell shows the guidance and weights that made it; when any cell was made with the test-only
random CLIP or fitted to image targets, a banner at the top of the page says so first.
"""

from __future__ import annotations

import base64
import html
import json
import logging
from pathlib import Path

import pandas as pd

from .core.cli import stage_main
from .core.provenance import atomic_path
from .results.cells import parse_cells

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
MODEL_VIEWER = REPO / "node_modules" / "@google" / "model-viewer" / "dist" / "model-viewer-umd.min.js"

CSS = """
body{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:22px} h2{font-size:18px;margin-top:32px;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:12px;margin:8px 0}
td,th{border:1px solid #ccc;padding:3px 6px;text-align:right} th{background:#f3f3f3}
td:first-child,th:first-child{text-align:left}
.cells{display:flex;flex-wrap:wrap;gap:16px}
.cell{border:1px solid #ddd;padding:8px;width:420px}
model-viewer{width:400px;height:320px;background:#eee}
img{max-width:100%} .note{color:#a00;font-weight:bold}
.banner{border:2px solid #a00;padding:8px;background:#fff4f4}
"""


def data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def table(frame: pd.DataFrame) -> str:
    return frame.to_html(index=False, float_format=lambda x: f"{x:.4g}", na_rep="", border=0, escape=True)


def group_rows(frame: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """Split rows so that real, test-only and image-guided numbers never share a table."""

    def flag(column: str) -> pd.Series:
        if column not in frame:
            return pd.Series(False, index=frame.index)
        return frame[column].apply(lambda x: bool(x) if x is not None and x == x else False)

    test = flag("test_only_weights") | flag("eval_test_only")
    image = frame["guidance"].astype(str).str.startswith("image")
    groups = [
        ("CLIP-guided with real weights", frame[~test & ~image]),
        ("Image-guided (procedural targets; verification, no CLIP)", frame[image & ~test]),
        ("TEST ONLY: tiny random CLIP (not real stylisations; never compare with the above)", frame[test]),
    ]
    return [(t, f) for t, f in groups if len(f)]


def origin_banner(frame: pd.DataFrame) -> str:
    """The page's first lines when any cell is not a real CLIP stylisation."""
    out = []
    n = len(frame)
    test = int(frame["test_only_weights"].astype(bool).sum()) if "test_only_weights" in frame else 0
    image = int((frame["image_guided"].astype(bool) & ~frame["test_only_weights"].astype(bool)).sum()) if n else 0
    if test:
        out.append(
            f"<p class='banner note'>TEST ONLY: {test} of {n} cells were made with a tiny CLIP with random weights "
            "(a test model). Their renders and assets are not real stylisations of their prompts.</p>"
        )
    if image:
        out.append(
            f"<p class='banner note'>IMAGE-GUIDED: {image} of {n} cells were fitted to renders of procedural target "
            "materials (a verification run without CLIP), not stylised from their prompts.</p>"
        )
    if "decimation_target_reached" in frame:
        short = frame[frame["decimation_target_reached"].astype(str).str.lower() == "false"].drop_duplicates("mesh")
        for _, r in short.iterrows():
            out.append(
                f"<p class='banner note'>DECIMATION SHORT OF TARGET: mesh {html.escape(str(r['mesh']))} has "
                f"{int(r['faces_after'])} faces for a target of {int(r['decimation_target'])}: "
                f"{html.escape(str(r['decimation_shortfall']))}. Its robustness comparison is not at the intended level.</p>"
            )
    return "".join(out)


def _figure(row, column: str) -> float | None:
    if column not in row or not len(row) or pd.isna(row[column].iloc[0]):
        return None
    return float(row[column].iloc[0])


def fidelity_lines(row) -> str:
    """The cell's recovery (image targets, held-out views) and Blender round-trip figures."""
    lines = []
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
    if "lod_faces" in row and isinstance(row["lod_faces"].iloc[0], str):
        levels = zip(
            row["lod_faces"].iloc[0].split("/"),
            str(row["lod_glb_bytes"].iloc[0]).split("/"),
            str(row["lod_fidelity_psnr_db"].iloc[0]).split("/"),
            strict=True,
        )
        parts = [f"lod{k} {int(f):,} faces, {int(b) / 1e6:.2f} MB GLB, {q} dB" for k, (f, b, q) in enumerate(levels)]
        lines.append("levels of detail (baked render vs the full neural render, object pixels): " + "; ".join(parts))
    return "".join(f"<br><small class='fidelity'>{html.escape(t)}</small>" for t in lines)


def run(results: Path, report_dir: Path, cells: list[tuple[str, str, str]], out: Path, model_viewer: Path | None = None) -> int:
    """Write the page; returns the number of 3D viewers in it (0 when model-viewer is missing)."""
    model_viewer = MODEL_VIEWER if model_viewer is None else Path(model_viewer)
    viewer = model_viewer.is_file()
    frame = pd.read_csv(report_dir / "summary.csv")
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>tango-stylize report</title><style>{CSS}</style>"]
    if viewer:
        parts.append(f"<script>{model_viewer.read_text()}</script>")
    else:
        log.warning(
            "%s not found: the report shows static previews instead of 3D viewers. Install Node.js and run "
            "'npm ci' in the repository (scripts/setup.sh does when npm is available), then rerun the report.",
            model_viewer,
        )
    parts.append("</head><body>")
    parts.append(f"<h1>tango-stylize report: {len(cells)} grid cells</h1>")
    parts.append(origin_banner(frame))
    if not viewer:
        parts.append(
            "<p class='banner' id='no-viewer'>3D viewers are off: model-viewer (an npm package) was not installed "
            "when this page was made, so each asset shows its static preview. Install Node.js, run 'npm ci' and "
            "rerun the report to get them.</p>"
        )
    parts.append("<h2>Summary</h2>")
    for title, sub in group_rows(frame):
        cls = " class='note'" if title.startswith("TEST ONLY") else ""
        parts.append(f"<h3{cls}>{html.escape(title)}</h3>")
        parts.append(table(sub))
    sa = report_dir / "speed_accuracy.csv"
    if sa.is_file() and sa.stat().st_size > 1:
        try:
            sa_frame = pd.read_csv(sa)
        except pd.errors.EmptyDataError:
            sa_frame = pd.DataFrame()
        if len(sa_frame):
            parts.append("<h2>Speed / accuracy</h2>")
            parts.append(table(sa_frame))
    parts.append("<h2>Figures</h2>")
    figures = ["overview.png", "pareto.png", "ablation_bars.png", "loss_curves.png"]
    fj = report_dir / "figures.json"
    if fj.is_file():
        figures += json.loads(fj.read_text()).get("grids", [])
    for name in figures:
        if (report_dir / name).is_file():
            parts.append(
                f"<h3>{html.escape(name)}</h3><img alt='{html.escape(name)}' src='{data_uri(report_dir / name, 'image/png')}'>"
            )
    parts.append("<h2>Assets</h2><div class='cells'>")
    models = 0
    for mesh, prompt, variant in cells:
        cdir = results / mesh / prompt / variant
        glb = cdir / "export" / "model.glb"
        row = frame[(frame["mesh"] == mesh) & (frame["prompt"] == prompt) & (frame["variant"] == variant)]
        label = html.escape(f"{mesh} / {prompt} / {variant}")
        text = html.escape(str(row["prompt_text"].iloc[0])) if len(row) else ""
        origin = str(row["origin"].iloc[0]) if len(row) else ""
        cls = " class='note'" if origin.startswith(("TEST ONLY", "IMAGE-GUIDED")) else ""
        parts.append(f"<div class='cell'><b>{label}</b><br>{text}<br><small{cls}>{html.escape(origin)}</small><br>")
        preview = cdir / "export" / "preview.png"
        if not viewer and preview.is_file():
            parts.append(f"<img class='preview' alt='{label}' src='{data_uri(preview, 'image/png')}'>")
        elif glb.is_file():
            parts.append(
                f"<model-viewer src='{data_uri(glb, 'model/gltf-binary')}' alt='{label}' camera-controls "
                "loading='eager' reveal='auto' shadow-intensity='0.5' exposure='1' interaction-prompt='none'></model-viewer>"
            )
            models += 1
        parts.append(fidelity_lines(row))
        compare = cdir / "roundtrip" / "compare.png"
        if compare.is_file():
            parts.append(
                "<br><small>Blender round trip, front view: ours | Cycles per format | 4 x |difference|</small>"
                f"<img src='{data_uri(compare, 'image/png')}'>"
            )
        edit = cdir / "relight" / "material_edit.png"
        if edit.is_file():
            parts.append(
                f"<br><small>material editing (rows: roughness x, columns: specular x)</small>"
                f"<img src='{data_uri(edit, 'image/png')}'>"
            )
        parts.append("</div>")
    parts.append("</div></body></html>")
    with atomic_path(out) as tmp:
        tmp.write_text("".join(parts))
    log.info("wrote %s (%d viewers, %.1f MB)", out, models, out.stat().st_size / 1e6)
    return models


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--results", type=Path, default=Path("results"))
        parser.add_argument("--report-dir", type=Path, default=Path("results/report"))
        parser.add_argument("--out", type=Path, required=True)
        parser.add_argument("--cells", nargs="+", required=True)

    def body(args):
        run(args.results, args.report_dir, parse_cells(args.cells), args.out)

    return stage_main("html_report", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
