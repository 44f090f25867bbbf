"""Markdown tables laid out like the paper's Tables 1, 2, 3, 4, 5 and S3-S5, a physical
plausibility table (``physics_table``; the paper reports none) and TextIM's interaction metrics
on the interactive subset (``interaction_table``).

The stream names come from the caller (``dataset.parts.streams``, see ``PartLayout``): Table 1
reads the whole-body stream's evaluator (``whole_stream``), Table 2 the part streams'
(``part_streams``). Table 5's switch columns are those the generated runs declare.

Every table says who wins: in each column whose header carries a direction (↑ higher is better,
↓ lower, → closest to real motion) the best method is **bold** and the methods whose 95% CI
overlaps the best's are **bold**† (tied); reference rows (real motion, VQ-VAE reconstructions)
are never ranked. Part-level tables rank within each part (each part has its own evaluator). A
one-line reading under the table is computed from the same numbers (``reading``). A column no row
has a value for is left out, with a note saying why; Table 5 needs at least two runs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

SOURCE_LABELS = {"ground_truth": "Real motion"}

#: kinds of rows: the method rows are ranked, the others are references
METHOD, REAL, REFERENCE = "method", "real", "reference"
#: header suffix -> what is better
DIRECTIONS = {"↑": "higher", "↓": "lower", "→": "target"}
TIE_MARK = "†"
TIE_NOTE = f"{TIE_MARK} tied with the best within the 95% CIs (the two intervals overlap)."
TABLE_LEGEND = ("↑ higher is better, ↓ lower is better, → closest to Real motion is better. **Bold**: the best "
                "method in its column (within each part where the table has a row per part; Real motion and "
                f"VQ-VAE reconstructions are references and never ranked); **bold**{TIE_MARK}: tied with the "
                "best within the 95% CIs.")
#: why a column can be empty for every row (by header without its arrow)
EMPTY_REASONS = {
    "MultiModality": ("it needs at least `eval.multimodality.times` generations per caption: set "
                      "`generator.generate.repeats` to at least that and rerun `party generate`"),
}


def label(source: str) -> str:
    if source in SOURCE_LABELS:
        return SOURCE_LABELS[source]
    if source.startswith("recon_"):
        return f"VQ-VAE reconstruction ({source[6:]})"
    return source


def row_kind(source: str) -> str:
    """``REAL`` for the ground truth, ``REFERENCE`` for a tokenizer reconstruction, else ``METHOD``."""
    if source == "ground_truth":
        return REAL
    return REFERENCE if source.startswith("recon_") else METHOD


def fmt(stat: Mapping | None, digits: int = 3) -> str:
    """{'mean', 'ci95'} -> '0.511±.003' (paper style); missing or not finite (e.g. foot skating of
    a motion set that never touches the floor) -> '-'."""
    if not _finite(stat):
        return "-"
    ci = f"{stat.get('ci95', 0.0):.{digits}f}"
    return f"{stat['mean']:.{digits}f}±{ci[1:] if ci.startswith('0.') else ci}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows])


def direction(header: str) -> str | None:
    """'higher' / 'lower' / 'target' (closest to real motion) from the header's arrow; None: not ranked."""
    return DIRECTIONS.get(header.rstrip()[-1:]) if header.strip() else None


def metric_name(header: str) -> str:
    """The header without its arrow."""
    h = header.rstrip()
    return h[:-1].rstrip() if h[-1:] in DIRECTIONS else h


def _finite(stat: Mapping | None) -> bool:
    m = stat.get("mean") if stat else None
    return m is not None and bool(np.isfinite(m))


def rank(stats: Sequence[Mapping | None], better: str, target: float | None = None) -> tuple[int | None, list[int]]:
    """(index of the best entry, indices of the entries tied with it) among ``stats`` ({'mean',
    'ci95'}; None or a missing / non-finite mean: not ranked). ``better``: 'higher', 'lower' or
    'target' (closest to ``target``). Tied: the 95% CIs overlap (the gap between the two means, or
    between their distances to ``target``, is at most the sum of the two half-widths). On equal
    means the first entry is the best."""
    if better not in DIRECTIONS.values():
        raise ValueError(f"rank: better must be one of {sorted(DIRECTIONS.values())}, got {better!r}")
    vals = [(i, float(s["mean"]), float(s.get("ci95") or 0.0)) for i, s in enumerate(stats) if _finite(s)]
    if not vals or (better == "target" and target is None):
        return None, []
    best, m_best, c_best = min(vals, key=lambda v: score(v[1], better, target))
    return best, [i for i, m, c in vals
                  if i != best and score(m, better, target) - score(m_best, better, target) <= c + c_best]


def score(mean: float, better: str, target: float | None = None) -> float:
    """``mean`` as a number where lower is better: ``better`` 'higher', 'lower' or 'target'
    (the distance to ``target``)."""
    return -mean if better == "higher" else mean if better == "lower" else abs(mean - float(target))


def _value(stat: Mapping, digits: int) -> str:
    return f"{stat['mean']:.{digits}f} (±{float(stat.get('ci95') or 0.0):.{digits}f})"


def _names(items: Sequence[str], most: int = 4) -> str:
    if len(items) > most:
        return ", ".join(items[:most - 1]) + f" and {len(items) - most + 1} more"
    return ", ".join(items[:-1]) + (" and " if len(items) > 1 else "") + items[-1]


def verdict(names: Sequence[str], stats: Sequence[Mapping | None], better: str, target: float | None = None,
            digits: int = 3) -> str:
    """Who wins among ``names`` (their ``stats``), in words: the best with its mean and CI, who is tied
    with it within the 95% CIs and who it is ahead of beyond them; '' when nobody is scored."""
    best, ties = rank(stats, better, target)
    if best is None:
        return ""
    scored = [i for i, s in enumerate(stats) if _finite(s)]
    text = f"{names[best]} {_value(stats[best], digits)}"
    if better == "target":
        text += f", closest to Real motion ({float(target):.{digits}f})"
    if len(scored) == 1:
        return text + ", the only method scored"
    ahead = [names[i] for i in scored if i != best and i not in ties]
    if ties:
        text += ", tied within the 95% CIs with " + _names([f"{names[i]} {_value(stats[i], digits)}" for i in ties])
    if ahead:
        text += ("; " if ties else ", ") + "ahead of " + _names(ahead) + " beyond the 95% CIs"
    return text


def reading(metric: str, names: Sequence[str], stats: Sequence[Mapping | None], better: str,
            target: float | None = None, digits: int = 3) -> str:
    """One sentence computed from the numbers, e.g. 'Best Top 1: party 0.430 (±0.010), ahead of
    holistic beyond the 95% CIs.'; '' when nobody is scored."""
    v = verdict(names, stats, better, target, digits)
    return f"Best {metric}: {v}." if v else ""


@dataclass(frozen=True)
class Num:
    """A table cell holding a statistic ({'mean', 'ci95'} or None), printed with ``fmt``."""
    stat: Mapping | None
    digits: int = 3

    def __str__(self) -> str:
        return fmt(self.stat, self.digits)


@dataclass
class Row:
    cells: list                     # str or Num, one per column; the first names the row
    kind: str = METHOD              # METHOD rows are ranked; REAL gives the target of a → column
    marks: dict = field(default_factory=dict)


def ranked_table(title: str, header: Sequence[str], rows: Sequence[Row], *, group: int | None = None,
                 ranked: bool = True, notes: Sequence[str] = ()) -> str:
    """``### title``, the table and what it says: the best / tied cells marked in every ranked column
    (within each value of column ``group`` when given), a reading of the first ranked column,
    the tie footnote, a note per column left out because no row has a value, then ``notes``."""
    header, rows = list(header), list(rows)
    keep = list(range(len(header)))
    if rows:
        keep = [j for j in keep if j == 0 or j == group or any(str(r.cells[j]).strip() != "-" for r in rows)]
    dropped = [header[j] for j in range(len(header)) if j not in keep]
    groups: dict[str, list[Row]] = {}
    for r in rows:
        groups.setdefault(str(r.cells[group]) if group is not None else "", []).append(r)
    readings, tied = [], False
    for j in keep:
        better = direction(header[j]) if ranked else None
        if better is None or not any(isinstance(r.cells[j], Num) for r in rows):
            continue
        clauses = []
        for g, members in groups.items():
            cands = [r for r in members if r.kind == METHOD]
            real = [r.cells[j].stat for r in members if r.kind == REAL and isinstance(r.cells[j], Num)
                    and _finite(r.cells[j].stat)]
            target = float(real[0]["mean"]) if real else None
            stats = [r.cells[j].stat if isinstance(r.cells[j], Num) else None for r in cands]
            if len(cands) >= 2:
                best, ties = rank(stats, better, target)
                if best is not None:
                    cands[best].marks[j] = "best"
                    for i in ties:
                        cands[i].marks[j] = "tie"
                    tied |= bool(ties)
            if not readings:
                digits = next((r.cells[j].digits for r in cands if isinstance(r.cells[j], Num)), 3)
                v = verdict([str(r.cells[0]) for r in cands], stats, better, target, digits)
                if v:
                    clauses.append(f"{g}: {v}" if group is not None else v)
        if clauses and not readings:
            by = f" by {header[group].lower()} — " if group is not None else ": "
            readings.append(f"Best {metric_name(header[j])}{by}" + "; ".join(clauses) + ".")

    def cell(r: Row, j: int) -> str:
        s = str(r.cells[j])
        mark = r.marks.get(j)
        return f"**{s}**" if mark == "best" else f"**{s}**{TIE_MARK}" if mark == "tie" else s

    out = [f"### {title}", _table([header[j] for j in keep], [[cell(r, j) for j in keep] for r in rows])]
    out += readings + ([TIE_NOTE] if tied else [])
    if dropped:
        items = [metric_name(h) + (f" ({EMPTY_REASONS[metric_name(h)]})" if metric_name(h) in EMPTY_REASONS else "")
                 for h in dropped]
        sep = "; " if any(metric_name(h) in EMPTY_REASONS for h in dropped) else ", "
        out.append(f"Column{'s' if len(items) > 1 else ''} left out, no row has a value: " + sep.join(items) + ".")
    return "\n\n".join(out + [n for n in notes if n])


def table1(results: Mapping, whole_stream: str, large: int = 256) -> str:
    rows, rows_b = [], []
    for src, d in results.items():
        h = d.get(whole_stream)
        if not h:
            continue
        rows.append(Row([label(src)] + [Num(h.get(k)) for k in ("top1", "top2", "top3", "fid", "mm_dist",
                                                                "diversity", "multimodality")], row_kind(src)))
        if f"top1_b{large}" in h:
            rows_b.append(Row([label(src)] + [Num(h.get(f"top{k}_b{large}")) for k in (1, 2, 3)], row_kind(src)))
    out = ranked_table(f"Table 1: standard metrics ({whole_stream} evaluator, R-Precision with 32 candidates)",
                       ["Method", "Top 1 ↑", "Top 2 ↑", "Top 3 ↑", "FID ↓", "MM-Dist ↓", "Diversity →",
                        "MultiModality ↑"], rows)
    if rows_b:
        out += "\n\n" + ranked_table(f"R-Precision with B = {large} candidates (HumanTOMATO protocol)",
                                     ["Method", "Top 1 ↑", "Top 2 ↑", "Top 3 ↑"], rows_b)
    return out


def retriever_table(results: Mapping, name: str, large: int = 256) -> str:
    """R-Precision at 32 and ``large`` candidates and the matching score of every source under
    another text-motion model (``eval.retrievers.<name>``; HumanTOMATO's TMA: TMA-R-Precision and
    TMA-Matching)."""
    rows = []
    for src, d in results.items():
        h = d.get(name)
        if h:
            rows.append(Row([label(src)] + [Num(h.get(k)) for k in ("top1", "top2", "top3", f"top1_b{large}",
                                                                    f"top2_b{large}", f"top3_b{large}", "mm_dist")],
                            row_kind(src)))
    if not rows:
        return ""
    return ranked_table(f"Retrieval by {name} (eval.retrievers.{name}): R-Precision with 32 and {large} candidates, "
                        "matching score", ["Method", "Top 1 ↑", "Top 2 ↑", "Top 3 ↑", f"Top 1 (B={large}) ↑",
                                           f"Top 2 (B={large}) ↑", f"Top 3 (B={large}) ↑", "Matching ↓"], rows)


def table2(results: Mapping, part_streams: Sequence[str]) -> str:
    rows = []
    for src, d in results.items():
        for part in part_streams:
            if part in d:
                p = d[part]
                rows.append(Row([label(src), part.capitalize()] + [Num(p.get(k)) for k in ("top1", "top3", "fid",
                                                                                           "mm_dist")], row_kind(src)))
    names = " / ".join(p.capitalize() for p in part_streams)
    return ranked_table(f"Table 2: part-level metrics ({names} evaluators)",
                        ["Method", "Part", "R-Precision Top 1 ↑", "R-Precision Top 3 ↑", "FID ↓", "MM-Dist ↓"],
                        rows, group=1)


def table3(results: Mapping) -> str:
    rows = [Row([label(s), Num(d["coherence"].get("tc"), 2), Num(d["coherence"].get("sc"), 2)], row_kind(s))
            for s, d in results.items() if "coherence" in d]
    return ranked_table("Table 3: coherence-level metrics",
                        ["Method", "Temporal Coherence (TC) ↑", "Spatial Coherence (SC) ↑"], rows)


#: (metric of ``results[source]['physics']``, header, scale from the stored unit, digits)
PHYSICS_COLUMNS = (("skate", "Foot skating (m/s) ↓", 1.0, 3), ("skate_ratio", "Skating ratio ↓", 1.0, 3),
                   ("float", "Floating (mm) ↓", 1e3, 1), ("penetrate", "Penetration (mm) ↓", 1e3, 1),
                   ("jitter", "Jitter (m/s³) ↓", 1.0, 1))
PHYSICS_NOTE = ("Lower is better in every column; Real motion is the reference (kinematic data is not free of "
                "these artefacts either). Foot skating: mean horizontal speed of the foot joints in contact "
                "(below `eval.physics.contact_height` in two adjacent frames; PhysDiff's Skate as a speed), the "
                "primary skating number; skating ratio: share of frames with a foot sliding (GMD); floating: "
                "height of the lowest joint above `eval.physics.float_tol`, frames in free flight left out; "
                "penetration: depth of the lowest joint below the floor (PhysDiff); jitter: mean jerk of every "
                "joint (TransPose). docs/evaluation.md.")


def _scaled(stat: Mapping | None, scale: float) -> Mapping | None:
    if not stat or stat.get("mean") is None:
        return stat
    return {**stat, "mean": stat["mean"] * scale, "ci95": float(stat.get("ci95") or 0.0) * scale}


def physics_table(results: Mapping) -> str:
    """Physical plausibility of every source (``results[source]['physics']``): reconstructions and
    real motion as references, the generated runs ranked (lower is better in every column)."""
    rows = [Row([label(s)] + [Num(_scaled(d["physics"].get(k), scale), digits)
                              for k, _, scale, digits in PHYSICS_COLUMNS], row_kind(s))
            for s, d in results.items() if "physics" in d]
    if not rows:
        return ""
    return ranked_table("Physical plausibility", ["Method"] + [h for _, h, _, _ in PHYSICS_COLUMNS], rows,
                        notes=[PHYSICS_NOTE])


INTERACTION = "interaction"      # party.evaluation.interaction.BLOCK (not imported: this module stays torch-free)
#: (metric of ``results[source]['interaction']``, header)
INTERACTION_COLUMNS = (("top1", "R@1 ↑"), ("top2", "R@2 ↑"), ("top3", "R@3 ↑"), ("mm_dist", "MM-Dist ↓"),
                       ("mpjpe", "MPJPE ↓"), ("mpvpe", "MPVPE ↓"), ("hand_jpe", "HandJPE ↓"),
                       ("foot_jpe", "FootJPE ↓"), ("side_acc_arms", "Side acc. arms ↑"),
                       ("side_acc_legs", "Side acc. legs ↑"),
                       ("boundary_speed", "Boundary speed →"), ("seam_bone", "Seam bone error ↓"))
INTERACTION_NOTE = ("TextIM's metrics (not the ParTY paper's). R@k (`eval.batch_size` candidates) and MM-Dist: the "
                    "whole-body evaluator with the caption's interaction instruction as the text (the full caption "
                    "where it has none). MPJPE (every joint), HandJPE (wrists), FootJPE (feet) and MPVPE (velocity "
                    "error) against the ground truth of the same clip: global joints, no alignment, over the frames "
                    "both have; Real motion and reconstructions are compared with the crop they come from (Real motion "
                    "scores 0). Side accuracy (not in the TextIM paper): of the captions whose interaction names "
                    "one side, the share whose named wrist (arms) or foot (legs) travels farther, root-relative. "
                    "Boundary speed (not in the paper): the root-relative speed of the collars, shoulders and hips "
                    "over the ground truth's (1: as fast; a seam between overwritten and generated channels raises "
                    "it). Seam bone error (not in the paper): the relative length error of the bones that join two "
                    "parts (spine3 to the collars, pelvis to the hips; 0: the body holds together there, however "
                    "much it moves). docs/evaluation.md.")


def interaction_table(results: Mapping, description: str = "") -> str:
    """TextIM's interaction metrics of every source (``results[source]['interaction']``) on the
    interactive subset, ``description`` its title; '' when no source has them."""
    rows = [Row([label(s)] + [Num(d[INTERACTION].get(k)) for k, _ in INTERACTION_COLUMNS], row_kind(s))
            for s, d in results.items() if d.get(INTERACTION)]
    if not rows:
        return ""
    return ranked_table(f"Interaction metrics on `{INTERACTION}`" + (f": {description}" if description else ""),
                        ["Method"] + [h for _, h in INTERACTION_COLUMNS], rows, notes=[INTERACTION_NOTE])


def table4(results: Mapping, efficiency: Mapping) -> str:
    rows = []
    for src, d in results.items():
        if not src.startswith("recon_"):
            continue
        stream = src[6:]
        e = efficiency.get("tokenizers", {}).get(stream, {})
        params = e.get("params")
        ait = e.get("ait_ms")
        rows.append(Row([stream, e.get("window", "-"), f"{params / 1e6:.2f}M" if params else "-",
                         str(e.get("steps") or "-"), Num(d.get(stream, {}).get("fid")),
                         Num(d.get("reconstruction", {}).get("mpjpe_mm"), 1), f"{ait:.1f} ms" if ait else "-"],
                        REFERENCE))
    header = ["Stream", "Window", "# Params", "Steps", "FID ↓", "MPJPE (mm) ↓", "AIT (encode+decode)"]
    note = ("Not ranked: each row is a different stream, its FID from that stream's evaluator and its MPJPE "
            "over that stream's joints." if len(rows) > 1 else "")
    return ranked_table("Table 4: tokenizer reconstruction (FID with the stream's evaluator; MPJPE in mm, "
                        "root-aligned per frame; Steps: the steps trained, from model.pt)", header, rows,
                        ranked=False, notes=[note])


def switch_names(switches: Mapping[str, Mapping]) -> list[str]:
    """Every switch the runs declare (``{run: {switch: bool}}``), in first-seen order."""
    return list(dict.fromkeys(k for sw in switches.values() for k in sw))


def table5(results: Mapping, switches: Mapping[str, Mapping], whole_stream: str) -> str:
    """The ablation: a row per run that declares switches. Shown from two such runs on (one run is no
    ablation): with fewer, a one-line note saying so instead."""
    names = switch_names(switches)
    rows = []
    for src, sw in switches.items():
        h = results.get(src, {}).get(whole_stream)
        if h:
            rows.append(Row([src] + ["✓" if sw.get(k) else "" for k in names]
                            + [Num(h.get(k)) for k in ("top1", "top3", "fid", "mm_dist")]))
    if len(rows) < 2:
        runs = f" ({', '.join(str(r.cells[0]) for r in rows)})" if rows else ""
        return (f"Table 5 (ablation of the proposed components) not shown: {len(rows)} scored run{runs} declares "
                "switches; an ablation needs at least 2.")
    return ranked_table("Table 5: ablation of the proposed components",
                        ["Run", *(k.upper() for k in names), "Top 1 ↑", "Top 3 ↑", "FID ↓", "MM-Dist ↓"], rows)


def efficiency_table(efficiency: Mapping) -> str:
    """Parameters, average inference time and the steps each model was trained (``steps_trained``
    of its export; "-" for models exported without it and for trivial baselines)."""
    def row(model: str, e: Mapping, steps_key: str) -> Row:
        steps = e.get(steps_key)
        return Row([model, f"{e['params'] / 1e6:.2f}M" if e.get("params") else "-",
                    f"{e['ait_ms']:.1f} ms" if e.get("ait_ms") else "-", str(steps) if steps is not None else "-"])
    rows = [Row([f"evaluator ({s})", f"{p / 1e6:.2f}M", "-", "-"]) for s, p in efficiency.get("evaluators", {}).items()]
    rows += [row(f"tokenizer ({s})", e, "steps") for s, e in efficiency.get("tokenizers", {}).items()]
    rows += [row(f"generator ({s})", e, "steps_trained") for s, e in efficiency.get("generated", {}).items()]
    return ranked_table("Efficiency: parameters, average inference time per sample and steps trained",
                        ["Model", "# Params", "AIT", "Steps"], rows, ranked=False)


def subset_table(results: Mapping, subset: str, streams: Sequence[str], description: str) -> str:
    """Retrieval metrics on one subset of the clips (``results[source][subset][stream]``), every stream."""
    rows = []
    for src, d in results.items():
        for s in streams:
            p = d.get(subset, {}).get(s)
            if p:
                rows.append(Row([label(src), s.capitalize()] + [Num(p.get(k)) for k in ("top1", "top3", "fid",
                                                                                        "mm_dist")], row_kind(src)))
    if not rows:
        return ""
    return ranked_table(f"Subset `{subset}`: {description}",
                        ["Method", "Evaluator", "R-Precision Top 1 ↑", "R-Precision Top 3 ↑", "FID ↓", "MM-Dist ↓"],
                        rows, group=1)


def report(results: Mapping, efficiency: Mapping, switches: Mapping, header: str = "", large: int = 256, *,
           whole_stream: str, part_streams: Sequence[str], subsets: Mapping[str, str] | None = None,
           retrievers: Sequence[str] = ()) -> str:
    """All tables, after ``header`` and the legend (``TABLE_LEGEND``). ``whole_stream`` / ``part_streams``:
    ``PartLayout.whole_stream`` / ``.part_streams`` of ``dataset.parts``; ``subsets`` {name: description}
    of ``run_protocol``'s subsets (``interaction``: the interactive subset, the title of the interaction
    table); ``retrievers``: the names of ``eval.retrievers`` (a table each)."""
    parts = [header, TABLE_LEGEND, table1(results, whole_stream, large),
             *(retriever_table(results, r, large) for r in retrievers), table2(results, part_streams),
             table3(results), physics_table(results), interaction_table(results, (subsets or {}).get(INTERACTION, ""))]
    if any(s.startswith("recon_") for s in results):
        parts.append(table4(results, efficiency))
    if switches:
        parts.append(table5(results, switches, whole_stream))
    for name, description in (subsets or {}).items():
        if name != INTERACTION:
            parts.append(subset_table(results, name, [whole_stream, *part_streams], description))
    parts.append(efficiency_table(efficiency))
    return "\n\n".join(p for p in parts if p) + "\n"


def calibration_tables(rows: list[Mapping], recommended: Mapping[str, Mapping]) -> str:
    """rows: {'table', 'params', 'metric', 'gt', 'mix', 'freeze', 'separation'} per grid point."""
    titles = {"S3": "Table S3: σ and κ (TC)", "S4": "Table S4: L and τ_max (TC)", "S5": "Table S5: β_d = β_θ (SC)"}
    out = []
    for tab, title in titles.items():
        sub = [r for r in rows if r["table"] == tab]
        if not sub:
            continue
        body = []
        for r in sub:
            name = ", ".join(f"{k}={v}" for k, v in r["params"].items())
            best = recommended.get(tab, {}).get("params") == r["params"]
            cells = [name, f"{r['gt']:.3f}", f"{r['mix']:.3f}", f"{r['freeze']:.3f}", f"{r['separation']:.3f}"]
            body.append([f"**{c}**" for c in cells] if best else cells)
        m = sub[0]["metric"].upper()
        out.append(f"### {title}\n\n" + _table(["Hyperparameters", f"{m} ground truth ↑", f"{m} mixed arms/legs ↓",
                                                 f"{m} frozen part ↓", "separation ↑"], body))
    return "\n\n".join(out) + "\n"


def dvc_metrics(results: dict, digits: int) -> dict[str, dict]:
    """{source: {stream | coherence | physics | interaction | reconstruction: {metric: mean},
    <subset>: {...}}}: the means of ``results`` rounded to ``digits`` significant digits, one file per source for DVC
    (``dvc metrics show`` reads it as one row per source, ``dvc exp show`` as columns)."""
    def lean(node):
        if isinstance(node, dict) and "mean" in node:
            m = node["mean"]
            return None if m is None or not np.isfinite(m) else float(f"{m:.{digits}g}")
        if isinstance(node, dict):
            out = {k: v for k, v in ((k, lean(v)) for k, v in node.items()) if v is not None and v != {}}
            return out
        return None
    return {source: lean(res) for source, res in results.items()}
