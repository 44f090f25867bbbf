"""Report tables: stream names from the caller, switch columns from the generated runs."""
from __future__ import annotations

import pytest

from party.evaluation.report import report, switch_names, table1, table2, table5


def _st(m, c=0.01):
    return {"mean": m, "ci95": c}


METRICS = {k: _st(v) for k, v in dict(top1=0.5, top2=0.6, top3=0.7, fid=0.2, mm_dist=3.1, diversity=9.0,
                                       multimodality=2.0).items()}
RESULTS = {"ground_truth": {"holistic": METRICS, "arms": METRICS, "legs": METRICS},
           "full": {"holistic": METRICS, "arms": METRICS},
           "no_pg": {"holistic": METRICS}}
PAPER = {"full": {"pg": True, "ptg": True, "hpf": True}, "no_pg": {"pg": False, "ptg": True, "hpf": True}}
ROW = "0.500±.010 | 0.700±.010 | 0.200±.010 | 3.100±.010 |"


def test_paper_switches_render_as_before():
    assert table5(RESULTS, PAPER, "holistic") == (
        "### Table 5: ablation of the proposed components\n\n"
        "| Run | PG | PTG | HPF | Top 1 ↑ | Top 3 ↑ | FID ↓ | MM-Dist ↓ |\n"
        "|---|---|---|---|---|---|---|---|\n"
        f"| full | ✓ | ✓ | ✓ | {ROW}\n"
        f"| no_pg |  | ✓ | ✓ | {ROW}")


def test_switch_columns_are_what_the_runs_declare():
    switches = {"full": {"pg": True, "mask": False}, "no_pg": {"ptg": True, "pg": False}}
    assert switch_names(switches) == ["pg", "mask", "ptg"]                 # union, first-seen order
    out = table5(RESULTS, switches, "holistic").splitlines()
    assert out[2] == "| Run | PG | MASK | PTG | Top 1 ↑ | Top 3 ↑ | FID ↓ | MM-Dist ↓ |"
    assert out[3] == "|" + "|".join(["---"] * 8) + "|"
    assert out[4] == f"| full | ✓ |  |  | {ROW}"                          # undeclared switch: blank
    assert out[5] == f"| no_pg |  |  | ✓ | {ROW}"


def test_stream_names_come_from_the_caller():
    renamed = {src: {{"holistic": "body", "arms": "upper", "legs": "lower"}[k]: v for k, v in d.items()}
               for src, d in RESULTS.items()}
    t1 = table1(renamed, "body")
    assert "(body evaluator, R-Precision" in t1 and "| Real motion | 0.500±.010" in t1
    t2 = table2(renamed, ["upper", "lower"])
    assert "(Upper / Lower evaluators)" in t2
    assert [r.split(" | ")[1] for r in t2.splitlines()[4:]] == ["Upper", "Lower", "Upper"]
    assert table2(RESULTS, ["arms", "legs"]).startswith("### Table 2: part-level metrics (Arms / Legs evaluators)")
    full = report(renamed, {}, PAPER, "## H", whole_stream="body", part_streams=["upper", "lower"])
    assert full.startswith("## H\n\n### Table 1") and "| full | ✓ | ✓ | ✓ |" in full
    with pytest.raises(TypeError):                      # the names come from dataset.parts, never a default
        report(RESULTS, {}, PAPER, "## H", 256)


def test_large_batch_r_precision_only_when_measured():
    assert "B = 256" not in table1(RESULTS, "holistic")
    measured = {**RESULTS, "full": {"holistic": {**METRICS, "top1_b256": _st(0.1)}}}
    out = table1(measured, "holistic", 256)
    assert "### R-Precision with B = 256 candidates" in out and "| full | 0.100±.010 | - | - |" in out


def test_subset_table_lists_every_stream_of_the_subset():
    from party.evaluation.report import subset_table
    stat = lambda v: {"mean": v, "ci95": 0.01, "n": 3}  # noqa: E731
    res = {"ground_truth": {"held_out": {"holistic": {"top1": stat(0.5), "fid": stat(0.0)},
                                         "arms": {"top1": stat(0.4)}}},
           "party": {"holistic": {"top1": stat(0.3)}, "held_out": {"arms": {"top1": stat(0.2)}}}}
    t = subset_table(res, "held_out", ["holistic", "arms", "legs"], "3 clips")
    assert t.startswith("### Subset `held_out`: 3 clips")
    rows = [line for line in t.splitlines() if line.startswith("| ") and "Method" not in line]
    assert len(rows) == 3 and rows[-1].startswith("| party | Arms | 0.200")
    assert subset_table(res, "other", ["holistic"], "x") == ""
