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
the same test. ``render`` lays them out as markdown (``party results``' Sweeps section, ``scripts/seed_table.py``).
Rows are the ``row`` dicts ``party.sweep.run_grid`` stores in ``status.json`` (strings or numbers);
``side`` (the named-side rate of ``scripts/check_generator.py``) is a metric column when present.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

#: a metric column's base name -> (label, direction); a column is ``<name>`` or ``<stream>_<name>``
DIRECTIONS = {"top1": ("Top 1", "higher"), "top2": ("Top 2", "higher"), "top3": ("Top 3", "higher"),
              "fid": ("FID", "lower"), "mm_dist": ("MM-Dist", "lower"), "diversity": ("Diversity", "target"),
              "tc": ("TC", "higher"), "sc": ("SC", "higher"), "side": ("named side", "higher")}
ARROWS = {"higher": "↑", "lower": "↓", "target": "→"}
SIDE = "side"


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
    "stats": {column: {"mean", "min", "max", "spread", "ci", "n"}}}``, in first-seen order (``ci``
    None for a column without ``_ci95``)."""
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
        out.append({"labels": g["labels"], "seeds": g["seeds"], "stats": stats})
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
    head = [*keys, "seeds", *[column_metric(c)[1] for c in columns]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g in groups:
        ctx, name = tuple(g["labels"].get(a, "") for a in within), _name(g, within)
        cells = [*g["labels"].values(), ", ".join(g["seeds"])]
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
