"""Mean over training seeds and the seed spread of a generator grid's table (``party gen_ablation``).

    .venv/bin/python scripts/seed_table.py [--grid data/ablations/gen_methods] [--seed-axis seed]
                                           [--side --samples 50] [--out <grid>/seed_table.md]

Groups the finished points of a grid (``<grid>/status.json``, so a grid still running or stopped
part-way is read as far as it got; else ``<grid>/table.csv``) by every axis but the seed axis (for ``gen_methods``:
method x guidance) and prints, per group and metric, the mean over the seeds, the seed spread
(max - min) and the mean evaluation CI (95% half-width over the protocol's replications). A
difference between two groups is beyond the training noise only when it exceeds both the seed
spreads and the CIs. ``--side`` adds the named-side rate of ``scripts/check_generator.py`` for
each point's trained model at that point's guidance scale (cached in ``<grid>/side/<point>.json``).
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

METRICS = [("top1", "Top 1 ↑"), ("fid", "FID ↓"), ("arms_top1", "Arms Top 1 ↑"), ("legs_top1", "Legs Top 1 ↑"),
           ("coherence_tc", "TC ↑"), ("coherence_sc", "SC ↑")]


def _scale(home: Path, method: str) -> float | None:
    """The guidance scale the point generated with (its trained method's ``config.json``)."""
    conf = home / method / "config.json"
    if not conf.is_file():
        return None
    return float(json.loads(conf.read_text()).get("generate", {}).get("cond_scale", 1.0))


def side_rate(grid: Path, row: dict, samples: int, params: str) -> float | None:
    """Named-side rate of the point's model at its guidance scale (cached)."""
    cache = grid / "side" / f"{row['point']}.json"
    if not cache.is_file():
        home = grid / "points" / row["point"]
        methods = [p.name for p in home.iterdir() if (p / "method.json").is_file()]
        if len(methods) != 1:
            return None
        cmd = [sys.executable, str(Path(__file__).with_name("check_generator.py")), "--params", params,
               "--generators", str(home), "--methods", methods[0], "--samples", str(samples),
               "--out", str(cache)]
        scale = _scale(home, methods[0])
        if scale is not None:
            cmd += ["--cond-scale", str(scale)]
        cache.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    rep = json.loads(cache.read_text())
    return float(next(iter(rep.values()))["mean"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grid", default="data/ablations/gen_methods")
    ap.add_argument("--seed-axis", default="seed")
    ap.add_argument("--side", action="store_true", help="add the named-side rate (scripts/check_generator.py)")
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    grid = Path(a.grid)
    table, status = grid / "table.csv", grid / "status.json"
    if status.is_file():
        points = json.loads(status.read_text()).get("points", {})
        rows = [{k: ("" if v is None else str(v)) for k, v in e["row"].items()}
                for e in points.values() if e.get("status") == "done" and e.get("row")]
    elif table.is_file():
        rows = [r for r in csv.DictReader(table.open()) if r.get("status") == "done"]
    else:
        sys.exit(f"{grid}: no status.json or table.csv; run `party gen_ablation` first")
    if not rows:
        sys.exit(f"{grid}: no finished point")
    cols = list(rows[0])
    if a.seed_axis not in cols:
        sys.exit(f"{grid}: no axis {a.seed_axis!r} (columns: {', '.join(cols)})")
    axes = cols[1:cols.index("params")]
    keys = [c for c in axes if c != a.seed_axis]
    metrics = list(METRICS) + ([("side", "named side ↑")] if a.side else [])
    if a.side:
        for r in rows:
            r["side"] = side_rate(grid, r, a.samples, a.params)
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    head = [*keys, "seeds", *[lab for _, lab in metrics]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g, rs in groups.items():
        cells = [*g, str(len(rs))]
        for key, _ in metrics:
            v = np.array([float(r[key]) for r in rs if r.get(key) not in (None, "")])
            ci = [float(r[f"{key}_ci95"]) for r in rs if r.get(f"{key}_ci95") not in (None, "")]
            if not len(v):
                cells.append("–")
                continue
            cell = f"{v.mean():.3f} (spread {v.max() - v.min():.3f}"
            cell += f"; CI ±{np.mean(ci):.3f})" if ci else ")"
            cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    text = (f"{grid.name}: mean over training seeds (seed spread = max - min; CI = mean 95% half-width of the "
            f"evaluation)\n\n" + "\n".join(lines) + "\n")
    print(text)
    Path(a.out or grid / "seed_table.md").write_text(text)


if __name__ == "__main__":
    main()
