"""Training noise: a grid's finished points grouped over its seed axis.

A grid whose spec declares ``seeds: {axis: seed, within: [guidance]}`` trains every other setting
with several seeds. ``summarize`` groups its rows by every axis but the seed axis and gives, per
group and metric column, the mean over the seeds, their range (min, max; the *seed spread* is
max - min) and the mean 95% half-width of the evaluation (``<column>_ci95``: the CI over the
protocol's replications, which covers the evaluation's sampling only).

``compare`` ranks the groups that share their labels on the ``within`` axes (``gen_methods``: the
methods at one guidance scale) on each metric with a direction, and says whether the best is
ahead of the second **beyond the training noise**: the two groups' seed ranges do not overlap
(every seed of the best beats every seed of the second) *and* the gap between their means exceeds
the sum of their evaluation CIs. With three seeds that is a strict test; a lead inside it is a lead
that another set of seeds could reverse.

``against`` sets one group (ParTY) beside each other group of its context, metric by metric, with
the same test. ``render`` lays them out as markdown (``party results``' Sweeps section, ``scripts/seed_table.py``),
with the optimizer steps each group's models actually trained (the rows' ``steps``).

A grid that also declares ``curve: <axis>`` (one of ``within``: ``gen_budget``'s training budget)
is drawn by ``curve_png``: one panel per metric, the metric against the steps trained, one line
per group of the other axes (mean over seeds) with a band for the seed range; ``party gen_ablation``
and ``scripts/seed_table.py`` put it in the grid's ``report.html`` (``grid_report``).
Rows are the ``row`` dicts ``party.sweep.run_grid`` stores in ``status.json`` (strings or numbers);
``side`` (the named-side rate of ``scripts/check_generator.py``) is a metric column when present.
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

#: a metric column's base name -> (label, direction); a column is ``<name>`` or ``<stream>_<name>``
DIRECTIONS = {"top1": ("Top 1", "higher"), "top2": ("Top 2", "higher"), "top3": ("Top 3", "higher"),
              "fid": ("FID", "lower"), "mm_dist": ("MM-Dist", "lower"), "diversity": ("Diversity", "target"),
              "tc": ("TC", "higher"), "sc": ("SC", "higher"), "side": ("named side", "higher")}
ARROWS = {"higher": "↑", "lower": "↓", "target": "→"}
SIDE = "side"
#: the row column with the optimizer steps a point's model trained (``party gen_ablation``)
STEPS = "steps"


def _float(v) -> float | None:
    if v is None or v == "":
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if x == x else None


def column_metric(column: str) -> tuple[str, str, str | None]:
    """(base metric, header, direction or None) of a metric column such as ``arms_top1``."""
    base = next((k for k in sorted(DIRECTIONS, key=len, reverse=True)
                 if column == k or column.endswith("_" + k)), None)
    if base is None:
        return column, column, None
    label, direction = DIRECTIONS[base]
    stream = column[: -len(base) - 1] if column != base else ""
    stream = "" if stream in ("", "coherence") else stream.capitalize() + " "
    return base, f"{stream}{label} {ARROWS[direction]}", direction


def metric_columns(rows: Sequence[Mapping]) -> list[str]:
    """The columns that hold a metric: those with a ``_ci95`` twin, in row order, then ``side``."""
    cols = list(dict.fromkeys(k for r in rows for k in r))
    out = [c for c in cols if f"{c}_ci95" in cols]
    return out + ([SIDE] if SIDE in cols else [])


def summarize(rows: Sequence[Mapping], axes: Sequence[str], seed_axis: str,
              columns: Sequence[str] | None = None) -> list[dict]:
    """Groups of ``rows`` over ``seed_axis``: ``{"labels": {axis: label}, "seeds": [label],
    "steps": [distinct steps trained], "stats": {column: {"mean", "min", "max", "spread", "ci",
    "n"}}}``, in first-seen order (``ci`` None for a column without ``_ci95``)."""
    if seed_axis not in axes:
        raise ValueError(f"seed axis {seed_axis!r} is not an axis of the grid ({', '.join(axes)})")
    keys = [a for a in axes if a != seed_axis]
    columns = list(columns) if columns is not None else metric_columns(rows)
    groups: dict[tuple, dict] = {}
    for r in rows:
        g = groups.setdefault(tuple(str(r.get(k)) for k in keys),
                              {"labels": {k: str(r.get(k)) for k in keys}, "seeds": [], "rows": []})
        g["seeds"].append(str(r.get(seed_axis)))
        g["rows"].append(r)
    out = []
    for g in groups.values():
        stats = {}
        for c in columns:
            v = [x for r in g["rows"] if (x := _float(r.get(c))) is not None]
            ci = [x for r in g["rows"] if (x := _float(r.get(f"{c}_ci95"))) is not None]
            if v:
                stats[c] = {"mean": sum(v) / len(v), "min": min(v), "max": max(v), "spread": max(v) - min(v),
                            "ci": sum(ci) / len(ci) if ci else None, "n": len(v)}
        steps = sorted({int(x) for r in g["rows"] if (x := _float(r.get(STEPS))) is not None})
        out.append({"labels": g["labels"], "seeds": g["seeds"], "steps": steps, "stats": stats})
    return out


def _name(g: Mapping, within: Sequence[str]) -> str:
    return "-".join(lab for a, lab in g["labels"].items() if a not in within) or "all"


def _contexts(groups: Sequence[Mapping], within: Sequence[str]) -> dict[tuple, list[Mapping]]:
    """The groups by their labels on ``within``, in first-seen order."""
    out: dict[tuple, list[Mapping]] = {}
    for g in groups:
        out.setdefault(tuple(g["labels"].get(a, "") for a in within), []).append(g)
    return out


def compare(groups: Sequence[Mapping], columns: Sequence[str], within: Sequence[str] = ()) -> list[dict]:
    """Per context (the labels on ``within``) and ranked column: ``{"context", "column", "header",
    "ranking": [(group, mean, min, max, ci)], "best", "second", "beyond"}``; ``beyond`` needs at
    least two seeds in both groups, non-overlapping seed ranges and a gap above both CIs."""
    out = []
    for ctx, gs in _contexts(groups, within).items():
        for c in columns:
            _, header, direction = column_metric(c)
            if direction not in ("higher", "lower"):
                continue
            have = [(_name(g, within), g["stats"][c]) for g in gs if c in g["stats"]]
            if len(have) < 2:
                continue
            sign = -1.0 if direction == "higher" else 1.0
            have.sort(key=lambda t: (sign * t[1]["mean"], t[0]))
            (b, sb), (s, ss) = have[0], have[1]
            beyond = _apart(sb, ss, direction)
            out.append({"context": dict(zip(within, ctx)), "column": c, "header": header,
                        "ranking": [(n, st["mean"], st["min"], st["max"], st["ci"]) for n, st in have],
                        "best": b, "second": s, "beyond": beyond})
    return out


def _apart(a: Mapping, b: Mapping, direction: str) -> bool:
    """``a`` beats ``b`` beyond the training noise (see the module docstring)."""
    ranges = a["min"] > b["max"] if direction == "higher" else a["max"] < b["min"]
    return ranges and abs(a["mean"] - b["mean"]) > (a["ci"] or 0.0) + (b["ci"] or 0.0) and min(a["n"], b["n"]) >= 2


def against(groups: Sequence[Mapping], focus: str, columns: Sequence[str], within: Sequence[str] = ()) -> list[dict]:
    """The group named ``focus`` against every other group of its context: ``{"context", "other",
    "cells": {column: (difference, verdict)}}``, the difference signed so that > 0 favours ``focus``,
    verdict ``"ahead"`` / ``"behind"`` beyond the training noise, else ``"within"``."""
    out = []
    for ctx, gs in _contexts(groups, within).items():
        mine = next((g for g in gs if _name(g, within) == focus), None)
        if mine is None:
            continue
        for g in gs:
            if g is mine:
                continue
            cells = {}
            for c in columns:
                direction = column_metric(c)[2]
                if direction not in ("higher", "lower") or c not in mine["stats"] or c not in g["stats"]:
                    continue
                a, b = mine["stats"][c], g["stats"][c]
                diff = (a["mean"] - b["mean"]) * (1.0 if direction == "higher" else -1.0)
                verdict = "ahead" if _apart(a, b, direction) else "behind" if _apart(b, a, direction) else "within"
                cells[c] = (diff, verdict)
            out.append({"context": dict(zip(within, ctx)), "other": _name(g, within), "cells": cells})
    return out


MARKS = {"ahead": " ✓", "behind": " ✗", "within": ""}


def _diff(d: float, verdict: str) -> str:
    return (f"{d:+.3f}" if round(d, 3) != 0 else "0.000") + MARKS[verdict]


def _cell(st: Mapping | None) -> str:
    if st is None:
        return "–"
    ci = "" if st["ci"] is None else f" ±{st['ci']:.3f}"
    if st["n"] < 2:
        return f"{st['mean']:.3f}{ci} (1 seed)"
    return f"{st['mean']:.3f} [{st['min']:.3f}, {st['max']:.3f}]{ci}"


def render(groups: Sequence[Mapping], within: Sequence[str] = (), columns: Sequence[str] | None = None,
           focus: Sequence[str] = ()) -> list[str]:
    """Markdown lines: the table (mean [seed min, max] ±evaluation CI per cell; **bold** the best
    of its context when beyond the training noise), one sentence per ranked column and context, and
    per ``focus`` group a table of its differences to every other group of its context."""
    if not groups:
        return ["No finished point."]
    have = list(dict.fromkeys(c for g in groups for c in g["stats"]))
    columns = [c for c in columns if c in have] if columns is not None else have
    comps = compare(groups, columns, within)
    bold = {(tuple(c["context"].values()), c["best"], c["column"]) for c in comps if c["beyond"]}
    keys = list(groups[0]["labels"])
    steps = any(g.get("steps") for g in groups)
    head = [*keys, "seeds", *(["steps trained"] if steps else []), *[column_metric(c)[1] for c in columns]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g in groups:
        ctx, name = tuple(g["labels"].get(a, "") for a in within), _name(g, within)
        cells = [*g["labels"].values(), ", ".join(g["seeds"])]
        if steps:       # a group whose seeds trained different budgets shows each (a point served short)
            cells.append(", ".join(f"{n:,}" for n in g.get("steps") or []) or "–")
        for c in columns:
            cell = _cell(g["stats"].get(c))
            cells.append(f"**{cell}**" if (ctx, name, c) in bold else cell)
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Cells: mean over the seeds [lowest, highest seed] ±mean evaluation 95% CI. **Bold**: best of "
              + ("its " + " / ".join(within) if within else "the grid")
              + " beyond the training noise (its seed range does not overlap the second's and the gap "
              "exceeds both CIs).", ""]
    for c in comps:
        where = ", ".join(f"{a} {lab}" for a, lab in c["context"].items())
        order = " > ".join(f"{n} {m:.3f}" for n, m, *_ in c["ranking"]) if column_metric(c["column"])[2] == "higher" \
            else " < ".join(f"{n} {m:.3f}" for n, m, *_ in c["ranking"])
        verdict = "beyond the training noise" if c["beyond"] else "within the training noise"
        lines.append(f"- {c['header']}" + (f" ({where})" if where else "") + f": {order}; {c['best']} over "
                     f"{c['second']} {verdict}.")
    for f in focus:
        rows = against(groups, f, columns, within)
        if not rows:
            continue
        cols = [c for c in columns if any(c in r["cells"] for r in rows)]
        lines += ["", f"{f} against each other group (difference of the means, > 0 favours {f}; ✓ ahead / ✗ "
                  "behind beyond the training noise):", "",
                  "| " + " | ".join([*within, "against", *(column_metric(c)[1] for c in cols)]) + " |",
                  "|" + "---|" * (len(within) + 1 + len(cols))]
        for r in rows:
            cells = [_diff(*r["cells"][c]) if c in r["cells"] else "–" for c in cols]
            lines.append("| " + " | ".join([*r["context"].values(), r["other"], *cells]) + " |")
    return lines + [""]


def grid_lines(rows: Sequence[Mapping], axes: Sequence[str], declared: Mapping) -> list[str]:
    """``render`` of a grid's rows as its spec's ``seeds:`` entry (``declared``: axis, within, and
    optionally columns and focus) lays them out."""
    groups = summarize(rows, axes, declared["axis"])
    return render(groups, declared.get("within", []), declared.get("columns"), declared.get("focus", []))


def curves(groups: Sequence[Mapping], axis: str, columns: Sequence[str] | None = None) -> dict[str, dict[str, list]]:
    """``{column: {line: [(x, label, mean, min, max)]}}``: per metric column, one line per group of
    the axes other than ``axis`` (their labels joined), its points along ``axis`` in order of x. x
    is the mean of the steps the group's models trained, or the label's position on the axis when
    no row records its steps."""
    order = list(dict.fromkeys(g["labels"][axis] for g in groups if axis in g["labels"]))
    have = list(dict.fromkeys(c for g in groups for c in g["stats"]))
    out: dict[str, dict[str, list]] = {}
    for c in (columns if columns is not None else have):
        lines: dict[str, list] = {}
        for g in groups:
            if axis not in g["labels"] or c not in g["stats"]:
                continue
            st, lab = g["stats"][c], g["labels"][axis]
            x = sum(g["steps"]) / len(g["steps"]) if g.get("steps") else float(order.index(lab) + 1)
            name = "-".join(v for a, v in g["labels"].items() if a != axis) or "all"
            lines.setdefault(name, []).append((x, lab, st["mean"], st["min"], st["max"]))
        if lines:
            out[c] = {n: sorted(pts) for n, pts in lines.items()}
    return out


def curve_png(groups: Sequence[Mapping], axis: str, columns: Sequence[str] | None = None) -> bytes | None:
    """PNG: one panel per metric column against the steps trained (log scale), a line per group with
    a band over the seed range; None when no column has two points on one line."""
    data = {c: lines for c, lines in curves(groups, axis, columns).items() if any(len(p) > 1 for p in lines.values())}
    if not data:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from party.render import PLAIN_TEXT, figure_png

    names = list(dict.fromkeys(n for lines in data.values() for n in lines))
    steps = any(g.get("steps") for g in groups)
    cols = min(4, len(data))
    rows = (len(data) + cols - 1) // cols
    fig, axs = plt.subplots(rows, cols, figsize=(3.8 * cols, 3.0 * rows), squeeze=False)
    for ax, (c, lines) in zip(axs.flat, data.items()):
        for n, pts in lines.items():
            colour = f"C{names.index(n) % 10}"
            xs = [p[0] for p in pts]
            ax.plot(xs, [p[2] for p in pts], marker="o", ms=3, color=colour, label=n)
            ax.fill_between(xs, [p[3] for p in pts], [p[4] for p in pts], color=colour, alpha=0.18, lw=0)
        if steps:
            ax.set_xscale("log")
        ticks = sorted({(p[0], p[1]) for pts in lines.values() for p in pts})
        ax.set_xticks([t[0] for t in ticks], [f"{t[1]}\n{t[0]:,.0f}" if steps else t[1] for t in ticks], fontsize=7)
        ax.minorticks_off()
        ax.set_title(column_metric(c)[1], fontsize=9, **PLAIN_TEXT)
        ax.tick_params(axis="y", labelsize=7)
    for ax in list(axs.flat)[len(data):]:
        ax.axis("off")
    axs.flat[0].legend(fontsize=7, loc="best")
    fig.supxlabel(f"{axis}: steps trained" if steps else axis, fontsize=8)
    fig.tight_layout()
    return figure_png(fig, dpi=80)


def grid_report(rows: Sequence[Mapping], axes: Sequence[str], declared: Mapping, title: str) -> str:
    """The grid's ``report.html``: its seed table (``grid_lines``) and, with ``curve`` declared,
    the metrics against the training budget (``curve_png``)."""
    from party.evaluation.html import report_html

    png = None
    if declared.get("curve"):
        png = curve_png(summarize(rows, axes, declared["axis"]), declared["curve"], declared.get("columns"))
    md = "\n".join([f"## Mean over training seeds (axis `{declared['axis']}`)", "", *grid_lines(rows, axes, declared)])
    return report_html(md, png, [], title, charts_title=f"Metrics against {declared.get('curve')}: the mean over "
                       "training seeds, the band from the lowest to the highest seed", legend=False)


def finished_rows(grid: str | Path, points: Mapping) -> list[dict]:
    """The ``row`` of every done point of a grid's ``status.json`` ``points``, each with its named-side
    rate where ``scripts/seed_table.py --side`` cached one (``<grid>/side/<point>.json``)."""
    rows = []
    for label, e in points.items():
        if not isinstance(e, Mapping) or e.get("status") != "done" or not isinstance(e.get("row"), Mapping):
            continue
        row = dict(e["row"])
        side = Path(grid) / "side" / f"{label}.json"
        if side.is_file():
            try:
                row[SIDE] = float(next(iter(json.loads(side.read_text()).values()))["mean"])
            except (ValueError, TypeError, KeyError, StopIteration) as err:
                raise ValueError(f"{side}: not a named-side check of scripts/check_generator.py "
                                 f"({type(err).__name__}: {err}); delete it to recompute") from None
        rows.append(row)
    return rows


def write_grid_report(grid: str | Path, spec: Mapping, points: Mapping) -> Path | None:
    """``<grid>/report.html`` (``grid_report``) for a spec with a ``seeds:`` entry and a finished
    point; None (nothing written) otherwise."""
    from party.io import write_text

    rows = finished_rows(grid, points)
    if not spec.get("seeds") or not rows:
        return None
    title = f"party sweep {spec.get('name', Path(grid).name)}" + (f": {spec['description']}" if spec.get("description") else "")
    path = Path(grid) / "report.html"
    write_text(path, grid_report(rows, list(spec["axes"]), spec["seeds"], title))
    return path
