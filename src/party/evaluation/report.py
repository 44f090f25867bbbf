"""Markdown tables laid out like the paper's Tables 1, 2, 3, 4, 5 and S3-S5.

The stream names come from the caller (``dataset.parts.streams``, see ``PartLayout``): Table 1
reads the whole-body stream's evaluator (``whole_stream``), Table 2 the part streams'
(``part_streams``). Table 5's switch columns are those the generated runs declare.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

SOURCE_LABELS = {"ground_truth": "Real motion"}


def label(source: str) -> str:
    if source in SOURCE_LABELS:
        return SOURCE_LABELS[source]
    if source.startswith("recon_"):
        return f"VQ-VAE reconstruction ({source[6:]})"
    return source


def fmt(stat: Mapping | None, digits: int = 3) -> str:
    """{'mean', 'ci95'} -> '0.511±.003' (paper style); missing -> '-'."""
    if not stat or stat.get("mean") is None:
        return "-"
    ci = f"{stat.get('ci95', 0.0):.{digits}f}"
    return f"{stat['mean']:.{digits}f}±{ci[1:] if ci.startswith('0.') else ci}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows])


def table1(results: Mapping, whole_stream: str, large: int = 256) -> str:
    rows, rows_b = [], []
    for src, d in results.items():
        h = d.get(whole_stream)
        if not h:
            continue
        rows.append([label(src)] + [fmt(h.get(k)) for k in ("top1", "top2", "top3", "fid", "mm_dist", "diversity",
                                                             "multimodality")])
        if f"top1_b{large}" in h:
            rows_b.append([label(src)] + [fmt(h.get(f"top{k}_b{large}")) for k in (1, 2, 3)])
    out = f"### Table 1: standard metrics ({whole_stream} evaluator, R-Precision with 32 candidates)\n\n" + _table(
        ["Method", "Top 1 ↑", "Top 2 ↑", "Top 3 ↑", "FID ↓", "MM-Dist ↓", "Diversity →", "MultiModality ↑"], rows)
    if rows_b:
        out += f"\n\n### R-Precision with B = {large} candidates (HumanTOMATO protocol)\n\n" + _table(
            ["Method", "Top 1 ↑", "Top 2 ↑", "Top 3 ↑"], rows_b)
    return out


def table2(results: Mapping, part_streams: Sequence[str]) -> str:
    rows = []
    for src, d in results.items():
        for part in part_streams:
            if part in d:
                p = d[part]
                rows.append([label(src), part.capitalize()]
                            + [fmt(p.get(k)) for k in ("top1", "top3", "fid", "mm_dist")])
    names = " / ".join(p.capitalize() for p in part_streams)
    return f"### Table 2: part-level metrics ({names} evaluators)\n\n" + _table(
        ["Method", "Part", "R-Precision Top 1 ↑", "R-Precision Top 3 ↑", "FID ↓", "MM-Dist ↓"], rows)


def table3(results: Mapping) -> str:
    rows = [[label(s), fmt(d["coherence"].get("tc"), 2), fmt(d["coherence"].get("sc"), 2)]
            for s, d in results.items() if "coherence" in d]
    return "### Table 3: coherence-level metrics\n\n" + _table(["Method", "Temporal Coherence (TC) ↑",
                                                                  "Spatial Coherence (SC) ↑"], rows)


def table4(results: Mapping, efficiency: Mapping) -> str:
    rows = []
    for src, d in results.items():
        if not src.startswith("recon_"):
            continue
        stream = src[6:]
        e = efficiency.get("tokenizers", {}).get(stream, {})
        fid = d.get(stream, {}).get("fid")
        params = e.get("params")
        ait = e.get("ait_ms")
        rows.append([stream, e.get("window", "-"), f"{params / 1e6:.2f}M" if params else "-",
                     str(e.get("steps") or "-"), fmt(fid), fmt(d.get("reconstruction", {}).get("mpjpe_mm"), 1),
                     f"{ait:.1f} ms" if ait else "-"])
    header = ["Stream", "Window", "# Params", "Steps", "FID ↓", "MPJPE (mm) ↓", "AIT (encode+decode)"]
    return ("### Table 4: tokenizer reconstruction (FID with the stream's evaluator; MPJPE in mm, root-aligned "
            "per frame; Steps: the steps trained, from model.pt)\n\n" + _table(header, rows))


def switch_names(switches: Mapping[str, Mapping]) -> list[str]:
    """Every switch the runs declare (``{run: {switch: bool}}``), in first-seen order."""
    return list(dict.fromkeys(k for sw in switches.values() for k in sw))


def table5(results: Mapping, switches: Mapping[str, Mapping], whole_stream: str) -> str:
    names = switch_names(switches)
    rows = []
    for src, sw in switches.items():
        h = results.get(src, {}).get(whole_stream)
        if h:
            rows.append([src] + ["✓" if sw.get(k) else "" for k in names]
                        + [fmt(h.get(k)) for k in ("top1", "top3", "fid", "mm_dist")])
    return "### Table 5: ablation of the proposed components\n\n" + _table(
        ["Run", *(k.upper() for k in names), "Top 1 ↑", "Top 3 ↑", "FID ↓", "MM-Dist ↓"], rows)


def efficiency_table(efficiency: Mapping) -> str:
    """Parameters, average inference time and the steps each model was trained (``steps_trained``
    of its export; "-" for models exported without it and for trivial baselines)."""
    def row(model: str, e: Mapping, steps_key: str) -> list[str]:
        steps = e.get(steps_key)
        return [model, f"{e['params'] / 1e6:.2f}M" if e.get("params") else "-",
                f"{e['ait_ms']:.1f} ms" if e.get("ait_ms") else "-", str(steps) if steps is not None else "-"]
    rows = [[f"evaluator ({s})", f"{p / 1e6:.2f}M", "-", "-"] for s, p in efficiency.get("evaluators", {}).items()]
    rows += [row(f"tokenizer ({s})", e, "steps") for s, e in efficiency.get("tokenizers", {}).items()]
    rows += [row(f"generator ({s})", e, "steps_trained") for s, e in efficiency.get("generated", {}).items()]
    return "### Efficiency: parameters, average inference time per sample and steps trained\n\n" + _table(
        ["Model", "# Params", "AIT", "Steps"], rows)


def subset_table(results: Mapping, subset: str, streams: Sequence[str], description: str) -> str:
    """Retrieval metrics on one subset of the clips (``results[source][subset][stream]``), every stream."""
    rows = []
    for src, d in results.items():
        for s in streams:
            p = d.get(subset, {}).get(s)
            if p:
                rows.append([label(src), s.capitalize()] + [fmt(p.get(k)) for k in ("top1", "top3", "fid", "mm_dist")])
    if not rows:
        return ""
    return f"### Subset `{subset}`: {description}\n\n" + _table(
        ["Method", "Evaluator", "R-Precision Top 1 ↑", "R-Precision Top 3 ↑", "FID ↓", "MM-Dist ↓"], rows)


def report(results: Mapping, efficiency: Mapping, switches: Mapping, header: str = "", large: int = 256, *,
           whole_stream: str, part_streams: Sequence[str], subsets: Mapping[str, str] | None = None) -> str:
    """All tables. ``whole_stream`` / ``part_streams``: ``PartLayout.whole_stream`` /
    ``.part_streams`` of ``dataset.parts``; ``subsets`` {name: description} of ``run_protocol``'s subsets."""
    parts = [header, table1(results, whole_stream, large), table2(results, part_streams), table3(results)]
    if any(s.startswith("recon_") for s in results):
        parts.append(table4(results, efficiency))
    if switches:
        parts.append(table5(results, switches, whole_stream))
    for name, description in (subsets or {}).items():
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
    """{source: {stream | coherence | reconstruction: {metric: mean}, <subset>: {...}}}: the means
    of ``results`` rounded to ``digits`` significant digits, one file per source for DVC
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
