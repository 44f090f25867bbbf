"""Mean over training seeds and the seed spread of a generator grid's table (``party gen_ablation``).

    .venv/bin/python scripts/seed_table.py [--grid data/ablations/gen_methods] [--seed-axis seed]
                                           [--within guidance] [--side --samples 50]
                                           [--out <grid>/seed_table.md]

Groups the finished points of a grid (``<grid>/status.json``, so a grid still running or stopped
part-way is read as far as it got; else ``<grid>/table.csv``) by every axis but the seed axis (for
``gen_methods``: method x guidance) and prints, per group and metric, the mean over the seeds, the
lowest and highest seed and the mean evaluation CI (95% half-width over the protocol's
replications), then ranks the groups that share their ``--within`` labels (default: the spec's
``seeds:``) and says whether each lead is beyond the training noise (``party.seeds``: the seed
ranges do not overlap and the gap exceeds both CIs). ``party results`` renders the same table for
every grid with a ``seeds:`` entry. ``--side`` adds the named-side rate of
``scripts/check_generator.py`` for each point's trained model at that point's guidance scale (cached
in ``<grid>/side/<point>.json``, where ``party results`` reads it too) and rewrites the grid's
``report.html`` (``party.seeds.grid_report``: the table and, for a grid with a ``curve`` axis, the
metrics against the steps trained) with them.
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

from party import seeds
from party.sweep import load_sweep

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
    ap.add_argument("--seed-axis", default=None, help="default: the grid spec's seeds.axis, else 'seed'")
    ap.add_argument("--within", nargs="*", default=None,
                    help="compare the groups that share these axes' labels (default: the spec's seeds.within)")
    ap.add_argument("--side", action="store_true", help="add the named-side rate (scripts/check_generator.py)")
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    grid = Path(a.grid)
    table, status = grid / "table.csv", grid / "status.json"
    spec = {}
    if status.is_file():
        st = json.loads(status.read_text())
        points = st.get("points", {})
        rows = [dict(e["row"]) for e in points.values() if e.get("status") == "done" and e.get("row")]
        if st.get("sweep") and Path(st["sweep"]).is_file():
            spec = load_sweep(st["sweep"])
    elif table.is_file():
        rows = [r for r in csv.DictReader(table.open()) if r.get("status") == "done"]
    else:
        sys.exit(f"{grid}: no status.json or table.csv; run `party gen_ablation` first")
    if not rows:
        sys.exit(f"{grid}: no finished point")
    cols = list(rows[0])
    declared = spec.get("seeds") or {}
    seed_axis = a.seed_axis or declared.get("axis", "seed")
    within = a.within if a.within is not None else declared.get("within", [])
    axes = list(spec["axes"]) if spec else cols[1:cols.index("params")]
    if seed_axis not in axes:
        sys.exit(f"{grid}: no axis {seed_axis!r} (axes: {', '.join(axes)})")
    if a.side:
        for r in rows:
            r[seeds.SIDE] = side_rate(grid, r, a.samples, a.params)
    text = "\n".join([f"{grid.name}: mean over training seeds (axis `{seed_axis}`)", "",
                      *seeds.grid_lines(rows, axes, {**declared, "axis": seed_axis, "within": within})])
    print(text)
    Path(a.out or grid / "seed_table.md").write_text(text)
    if spec.get("seeds") and status.is_file():      # the grid's report.html, with the side rates cached above
        report = seeds.write_grid_report(grid, spec, json.loads(status.read_text()).get("points", {}))
        if report is not None:
            print(f"wrote {report}")


if __name__ == "__main__":
    main()
