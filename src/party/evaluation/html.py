"""``data/eval/report.html``: one self-contained page to look at an evaluation.

- a legend: the colours of the animations (``party.render``'s left / right / centre / trajectory
  colours) and what the arrows and marks of the tables mean (``report.TABLE_LEGEND``),
- the paper-layout tables of ``tables.md`` (Markdown pipe tables rendered as HTML tables, the
  best value of each column bold, ties within the 95% CIs bold†, a computed reading under each),
- bar charts with 95% CI error bars per metric for every scored source (ground truth and
  generated runs; reconstructions have their own Table 4), so an ablation grid evaluated side
  by side reads as bars,
- side-by-side stick-figure animations (GIF) of the ground truth and every generated run for a
  fixed set of test clips (``eval.report.clips``: the first clips, by id, that every run
  generated), titled with the caption; the panels wrap and shrink to the page width.

Every image is embedded as a ``data:`` URI, so the file can be mailed or logged to MLflow as one
artifact. A small script sets ``data-images-ok`` / ``data-images`` on ``<body>`` once every image
has decoded (what the browser test reads).
"""
from __future__ import annotations

import base64
import html
import re
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from party.evaluation.report import TABLE_LEGEND
from party.render import CENTER_COLOR, LEFT_COLOR, PLAIN_TEXT, RIGHT_COLOR, TRAJ_COLOR, figure_png

#: (stream, 'coherence' or 'physics', metric, label, higher is better)
CHART_METRICS = (("{whole}", "top1", "R-Precision Top 1 ({whole})", True),
                 ("{whole}", "fid", "FID ({whole})", False),
                 ("{whole}", "mm_dist", "MM-Dist ({whole})", False),
                 ("{part}", "top1", "R-Precision Top 1 ({part})", True),
                 ("coherence", "tc", "TC", True),
                 ("coherence", "sc", "SC", True),
                 ("physics", "skate", "Foot skating (m/s)", False),
                 ("physics", "float", "Floating (m)", False),
                 ("physics", "penetrate", "Penetration (m)", False),
                 ("physics", "jitter", "Jitter (m/s³)", False))

_SCRIPT = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.body.setAttribute('data-images', String(imgs.length));
  document.body.setAttribute('data-images-ok', String(ok));
});
</script>"""

_STYLE = """<style>
body { font-family: sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; }
th { background: #f0f0f0; }
td strong { color: #0b6623; }
.grid { display: flex; flex-wrap: wrap; gap: 0.5em; align-items: flex-start; }
figure { margin: 0.5em 0; max-width: 100%; }
figure img { max-width: 100%; height: auto; display: block; }
figcaption { font-size: 0.85em; max-width: 60em; }
.legend { border: 1px solid #ccc; background: #fafafa; padding: 0.4em 1em; max-width: 75em; }
.legend p { margin: 0.4em 0; }
.swatch { display: inline-block; width: 1.6em; height: 0.5em; margin: 0 0.3em 0.1em 0.6em;
          vertical-align: middle; }
</style>"""

#: (colour, what it draws) in the animations, as ``party.render`` draws them
ANIMATION_COLOURS = ((LEFT_COLOR, "left arm and leg (red)"), (RIGHT_COLOR, "right arm and leg (blue)"),
                     (CENTER_COLOR, "spine and head (grey)"), (TRAJ_COLOR, "the root's path on the ground (orange)"))


def inline(s: str) -> str:
    """One line of Markdown text, escaped: `code` and **bold**."""
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", html.escape(s))
    return re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", s)


def markdown_to_html(md: str) -> str:
    """The subset of Markdown ``tables.md`` and the seed tables use: headings, pipe tables, ``- ``
    lists, paragraphs, `code`, **bold**."""
    out, table, items = [], [], []

    def flush():
        if items:
            out.append("<ul>" + "".join(f"<li>{inline(i)}</li>" for i in items) + "</ul>")
            items.clear()
        if not table:
            return
        head, *body = [r for r in table if not re.fullmatch(r"\|?[\s\-:|]+\|?", r)]
        cells = lambda r: [c.strip() for c in r.strip().strip("|").split("|")]  # noqa: E731
        out.append("<table><thead><tr>" + "".join(f"<th>{inline(c)}</th>" for c in cells(head)) + "</tr></thead><tbody>"
                   + "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in cells(r)) + "</tr>" for r in body)
                   + "</tbody></table>")
        table.clear()

    for line in md.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        if line.startswith("- "):
            if table:
                flush()
            items.append(line[2:])
            continue
        flush()
        m = re.match(r"(#{1,6})\s+(.*)", line)
        if m:
            n = len(m.group(1))
            out.append(f"<h{n}>{inline(m.group(2))}</h{n}>")
        elif line.strip():
            out.append(f"<p>{inline(line)}</p>")
    flush()
    return "\n".join(out)


def _data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode()}"


def bar_charts(results: Mapping, whole_stream: str, part_streams: Sequence[str]) -> bytes | None:
    """PNG: one panel per metric, a bar per source (mean) with its 95% CI; None if nothing to show."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sources = [s for s in results if not s.startswith("recon_")]
    panels = []
    for stream, metric, title, higher in CHART_METRICS:
        for part in (part_streams if "{part}" in stream else [None]):
            key = stream.format(whole=whole_stream, part=part)
            vals = [(s, results[s].get(key, {}).get(metric)) for s in sources]
            vals = [(s, v) for s, v in vals if v and v.get("mean") is not None]
            if vals:
                panels.append((title.format(whole=whole_stream, part=part), higher, vals))
    if not panels:
        return None
    cols = min(4, len(panels))
    rows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.9 * rows), squeeze=False)
    for ax, (title, higher, vals) in zip(axes.flat, panels):
        names = [s for s, _ in vals]
        ax.bar(range(len(vals)), [v["mean"] for _, v in vals], yerr=[v.get("ci95", 0.0) for _, v in vals],
               capsize=3, color=["#999" if n == "ground_truth" else f"C{i}" for i, n in enumerate(names)])
        ax.set_xticks(range(len(vals)), [n.replace("ground_truth", "real") for n in names], rotation=30,
                      ha="right", fontsize=7, **PLAIN_TEXT)
        ax.set_title(f"{title} {'↑' if higher else '↓'}", fontsize=9, **PLAIN_TEXT)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.tight_layout()
    return figure_png(fig, dpi=80)


def sample_clips(ctx, generated: Sequence, split: str, n: int) -> list[dict]:
    """The first ``n`` clips of ``split`` (by id) that every generated run holds."""
    have = set.intersection(*(set(g.by_clip) for g in generated)) if generated else set()
    return [c for c in sorted(ctx.index.clips(split), key=lambda c: c["id"]) if c["id"] in have][:n]


def animations(ctx, generated: Sequence, clips: Sequence[dict], max_frames: int) -> list[tuple[str, bytes]]:
    """(caption, GIF bytes) per clip: ground truth beside every generated run."""
    from party.evaluation.protocol import motion_joints
    from party.render import render_comparison

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for c in clips:
            caption = generated[0].by_clip[c["id"]][0][0]
            feats = [ctx.store.clip_features(c)] + [g.by_clip[c["id"]][0][2] for g in generated]
            joints = motion_joints([np.asarray(f, dtype=np.float32) for f in feats], ctx.n_joints)
            path = Path(tmp) / f"{len(out)}.gif"
            render_comparison(joints, ["real"] + [g.name for g in generated], path, ctx.index.skeleton,
                              fps=ctx.index.fps, title=caption, max_frames=max_frames)
            out.append((caption, path.read_bytes()))
    return out


def legend_html(animated: bool = True) -> str:
    """What the tables' and charts' arrows and marks mean and, when ``animated``, the animations' colours."""
    swatches = "".join(f"<span class='swatch' style='background: {c}'></span>{html.escape(what)}"
                       for c, what in ANIMATION_COLOURS)
    anim = (f"<p><b>Animations</b> (real motion first, then every generated run):{swatches}.</p>"
            if animated else "")
    return f"<div class='legend'>{anim}<p><b>Tables and charts</b>: {inline(TABLE_LEGEND)}</p></div>"


def report_html(tables_md: str, charts_png: bytes | None, gifs: Sequence[tuple[str, bytes]], title: str,
                charts_title: str = "Metrics with 95% CIs", legend: bool = True) -> str:
    """The page; ``legend`` False for tables that say what their marks mean themselves (a grid's
    seed tables, whose bold is a lead beyond the training noise)."""
    parts = ["<!DOCTYPE html>", "<html><head><meta charset='utf-8'>", f"<title>{html.escape(title)}</title>",
             _STYLE, "</head><body>", f"<h1>{html.escape(title)}</h1>", legend_html(bool(gifs)) if legend else ""]
    if charts_png is not None:
        parts += [f"<h2>{html.escape(charts_title)}</h2>",
                  f"<figure><img alt='metrics' src='{_data_uri(charts_png, 'image/png')}'></figure>"]
    if gifs:
        parts += ["<h2>Samples: ground truth beside every generated run</h2>", "<div class='grid'>"]
        for cap, gif in gifs:
            parts.append(f"<figure><img alt='{html.escape(cap)}' src='{_data_uri(gif, 'image/gif')}'>"
                         f"<figcaption>{html.escape(cap)}</figcaption></figure>")
        parts.append("</div>")
    tables_md = tables_md.replace(TABLE_LEGEND + "\n", "")          # the legend above says it
    parts += ["<h2>Tables</h2>", markdown_to_html(tables_md), _SCRIPT, "</body></html>"]
    return "\n".join(parts) + "\n"


def write_report(path: str | Path, cfg, ctx, results: Mapping, tables_md: str, generated: Sequence) -> Path:
    """Build and write the report (atomic); ``cfg.eval.report`` says how many sample clips."""
    from party.io import write_text

    rc = cfg.eval.report
    charts = bar_charts(results, ctx.layout.whole_stream, ctx.layout.part_streams)
    clips = sample_clips(ctx, generated, cfg.eval.split, rc.clips) if generated and rc.clips > 0 else []
    gifs = animations(ctx, generated, clips, rc.max_frames) if clips else []
    path = Path(path)
    write_text(path, report_html(tables_md, charts, gifs, f"party evaluation: {ctx.index.dataset} / {cfg.eval.split}"))
    return path
