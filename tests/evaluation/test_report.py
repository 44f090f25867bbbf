"""Report tables: stream names from the caller, switch columns from the generated runs; who wins
(best / tied / neither, in the metric's direction), the computed reading, columns and tables left out,
the legend of report.html."""
from __future__ import annotations

import re
import shutil

import pytest

from party.evaluation.report import (TABLE_LEGEND, TIE_NOTE, rank, reading, report, switch_names, table1, table2,
                                     table5, verdict)


def _st(m, c=0.01):
    return {"mean": m, "ci95": c}


METRICS = {k: _st(v) for k, v in dict(top1=0.5, top2=0.6, top3=0.7, fid=0.2, mm_dist=3.1, diversity=9.0,
                                       multimodality=2.0).items()}
RESULTS = {"ground_truth": {"holistic": METRICS, "arms": METRICS, "legs": METRICS},
           "full": {"holistic": METRICS, "arms": METRICS},
           "no_pg": {"holistic": METRICS}}
PAPER = {"full": {"pg": True, "ptg": True, "hpf": True}, "no_pg": {"pg": False, "ptg": True, "hpf": True}}
ROW = "0.500±.010 | 0.700±.010 | 0.200±.010 | 3.100±.010 |"
BEST = "**0.500±.010** | **0.700±.010** | **0.200±.010** | **3.100±.010** |"      # equal means: the first wins,
TIED = "**0.500±.010**† | **0.700±.010**† | **0.200±.010**† | **3.100±.010**† |"  # the others tie with it


def rows_of(md: str) -> list[str]:
    """The body rows of the (first) pipe table of ``md``."""
    lines = [line for line in md.splitlines() if line.startswith("|")]
    return lines[2:]


def test_paper_switches_render_as_before():
    assert table5(RESULTS, PAPER, "holistic") == (
        "### Table 5: ablation of the proposed components\n\n"
        "| Run | PG | PTG | HPF | Top 1 ↑ | Top 3 ↑ | FID ↓ | MM-Dist ↓ |\n"
        "|---|---|---|---|---|---|---|---|\n"
        f"| full | ✓ | ✓ | ✓ | {BEST}\n"
        f"| no_pg |  | ✓ | ✓ | {TIED}\n\n"
        "Best Top 1: full 0.500 (±0.010), tied within the 95% CIs with no_pg 0.500 (±0.010).\n\n"
        f"{TIE_NOTE}")


def test_switch_columns_are_what_the_runs_declare():
    switches = {"full": {"pg": True, "mask": False}, "no_pg": {"ptg": True, "pg": False}}
    assert switch_names(switches) == ["pg", "mask", "ptg"]                 # union, first-seen order
    out = table5(RESULTS, switches, "holistic").splitlines()
    assert out[2] == "| Run | PG | MASK | PTG | Top 1 ↑ | Top 3 ↑ | FID ↓ | MM-Dist ↓ |"
    assert out[3] == "|" + "|".join(["---"] * 8) + "|"
    assert out[4] == f"| full | ✓ |  |  | {BEST}"                         # undeclared switch: blank
    assert out[5] == f"| no_pg |  |  | ✓ | {TIED}"


def test_stream_names_come_from_the_caller():
    renamed = {src: {{"holistic": "body", "arms": "upper", "legs": "lower"}[k]: v for k, v in d.items()}
               for src, d in RESULTS.items()}
    t1 = table1(renamed, "body")
    assert "(body evaluator, R-Precision" in t1 and "| Real motion | 0.500±.010" in t1
    t2 = table2(renamed, ["upper", "lower"])
    assert "(Upper / Lower evaluators)" in t2
    assert [r.split(" | ")[1] for r in rows_of(t2)] == ["Upper", "Lower", "Upper"]
    assert table2(RESULTS, ["arms", "legs"]).startswith("### Table 2: part-level metrics (Arms / Legs evaluators)")
    full = report(renamed, {}, PAPER, "## H", whole_stream="body", part_streams=["upper", "lower"])
    assert full.startswith(f"## H\n\n{TABLE_LEGEND}\n\n### Table 1") and "| full | ✓ | ✓ | ✓ |" in full
    with pytest.raises(TypeError):                      # the names come from dataset.parts, never a default
        report(RESULTS, {}, PAPER, "## H", 256)


def test_large_batch_r_precision_only_when_measured():
    assert "B = 256" not in table1(RESULTS, "holistic")
    measured = {**RESULTS, "full": {"holistic": {**METRICS, "top1_b256": _st(0.1)}}}
    out = table1(measured, "holistic", 256)
    assert "### R-Precision with B = 256 candidates" in out
    b256 = out[out.index("### R-Precision with B"):]
    assert rows_of(b256) == ["| full | 0.100±.010 |"]                   # measured for Top 1 alone
    assert "Columns left out, no row has a value: Top 2, Top 3." in b256


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


# --- who wins -----------------------------------------------------------------------------------

def _m(**kw):
    return {k: _st(*v) if isinstance(v, tuple) else _st(v) for k, v in kw.items()}


# Real motion and the reconstruction beat every method but are references: never marked. Top 1: party
# and holistic overlap (gap .01 <= .01 + .01), random is beyond. FID / MM-Dist: lower wins. Diversity:
# closest to Real motion's 9.0 wins (holistic, 0.5 away; party 1.0 away beyond the CIs). No row has a
# MultiModality.
WINS = {"ground_truth": {"holistic": _m(top1=0.60, top2=0.7, top3=0.8, fid=(0.0, 0.0), mm_dist=2.9,
                                        diversity=(9.0, 0.1))},
        "recon_holistic": {"holistic": _m(top1=0.59, fid=(0.05, 0.01))},
        "party": {"holistic": _m(top1=0.45, top2=0.6, top3=0.7, fid=(0.30, 0.02), mm_dist=3.2, diversity=(8.0, 0.1))},
        "holistic": {"holistic": _m(top1=0.44, top2=0.5, top3=0.6, fid=(0.90, 0.02), mm_dist=3.6,
                                    diversity=(9.5, 0.1))},
        "random": {"holistic": _m(top1=0.03, top2=0.06, top3=0.09, fid=(9.0, 0.1), mm_dist=8.0,
                                  diversity=(4.0, 0.1))}}


def cells(md: str) -> dict[str, dict[str, str]]:
    """{row name (+ ' / ' + part for part tables): {column header: cell}} of the first table of ``md``."""
    lines = [line for line in md.splitlines() if line.startswith("|")]
    def split(line: str) -> list[str]:
        return [c.strip() for c in line.strip().strip("|").split("|")]
    head = split(lines[0])
    group = 1 if head[1] in ("Part", "Evaluator") else None
    return {r[0] + (f" / {r[group]}" if group else ""): dict(zip(head, r)) for r in map(split, lines[2:])}


def test_best_is_marked_in_the_direction_of_each_metric():
    t = cells(table1(WINS, "holistic"))
    assert t["party"]["Top 1 ↑"] == "**0.450±.010**"                      # higher is better
    assert t["Real motion"]["Top 1 ↑"] == "0.600±.010"                     # references are never ranked
    assert t["VQ-VAE reconstruction (holistic)"]["Top 1 ↑"] == "0.590±.010"
    assert t["VQ-VAE reconstruction (holistic)"]["FID ↓"] == "0.050±.010"
    assert t["party"]["FID ↓"] == "**0.300±.020**"                         # lower is better
    assert t["random"]["FID ↓"] == "9.000±.100" and t["holistic"]["FID ↓"] == "0.900±.020"
    assert t["party"]["MM-Dist ↓"] == "**3.200±.010**"
    assert t["holistic"]["Diversity →"] == "**9.500±.100**"                # closest to Real motion's 9.0
    assert t["party"]["Diversity →"] == "8.000±.100" and t["random"]["Diversity →"] == "4.000±.100"


def test_a_tie_within_the_cis_is_marked_as_a_tie_and_a_gap_beyond_them_is_not():
    md = table1(WINS, "holistic")
    t = cells(md)
    assert t["holistic"]["Top 1 ↑"] == "**0.440±.010**†"                   # |.45 - .44| <= .01 + .01
    assert t["random"]["Top 1 ↑"] == "0.030±.010"
    assert t["holistic"]["Top 2 ↑"] == "0.500±.010"                        # .6 vs .5: beyond the CIs
    assert TIE_NOTE in md
    no_tie = {**WINS, "holistic": {"holistic": {**WINS["holistic"]["holistic"], "top1": _st(0.40)}}}
    md = table1(no_tie, "holistic")
    assert cells(md)["holistic"]["Top 1 ↑"] == "0.400±.010" and "†" not in md and TIE_NOTE not in md


def test_rank_directions_ties_and_what_is_not_ranked():
    a, b = _st(0.50), _st(0.47)
    assert rank([a, b, None, _st(float("nan"))], "higher") == (0, [])    # gap .03 > .01 + .01
    assert rank([a, b], "lower") == (1, [])
    assert rank([_st(0.50, 0.02), _st(0.47, 0.02)], "higher") == (0, [1])
    assert rank([_st(8.0, 0.1), _st(9.5, 0.1), _st(10.2, 0.1)], "target", 9.0) == (1, [])
    assert rank([_st(8.9, 0.1), _st(9.05, 0.1)], "target", 9.0) == (1, [0])   # .1 - .05 <= .2
    assert rank([a, b], "target") == (None, []) and rank([None], "higher") == (None, [])
    with pytest.raises(ValueError, match="better"):
        rank([a], "bigger")


def test_the_reading_is_computed_from_the_numbers():
    assert (reading("Top 1", ["party", "holistic", "random"], [_st(0.45), _st(0.44), _st(0.03)], "higher")
            == "Best Top 1: party 0.450 (±0.010), tied within the 95% CIs with holistic 0.440 (±0.010); "
               "ahead of random beyond the 95% CIs.")
    assert (reading("FID", ["party", "holistic"], [_st(0.9, 0.02), _st(0.3, 0.02)], "lower")
            == "Best FID: holistic 0.300 (±0.020), ahead of party beyond the 95% CIs.")
    assert (reading("TC", ["party"], [_st(0.431, 0.012)], "higher", digits=2)
            == "Best TC: party 0.43 (±0.01), the only method scored.")
    assert reading("Top 1", ["party"], [None], "higher") == ""
    assert (reading("Diversity", ["a", "b"], [_st(8.0, 0.1), _st(9.5, 0.1)], "target", 9.0)
            == "Best Diversity: b 9.500 (±0.100), closest to Real motion (9.000), ahead of a beyond the 95% CIs.")
    many = verdict([f"r{i}" for i in range(7)], [_st(0.9 - i / 10) for i in range(7)], "higher")
    assert many.endswith("ahead of r1, r2, r3 and 3 more beyond the 95% CIs")
    md = table1(WINS, "holistic")
    assert ("\n\nBest Top 1: party 0.450 (±0.010), tied within the 95% CIs with holistic 0.440 (±0.010); "
            "ahead of random beyond the 95% CIs.\n\n") in md                # under the table, from its rows


def test_part_tables_rank_and_read_within_each_part():
    res = {"ground_truth": {"arms": _m(top1=0.9), "legs": _m(top1=0.9)},
           "party": {"arms": _m(top1=0.50), "legs": _m(top1=0.20)},
           "holistic": {"arms": _m(top1=0.30), "legs": _m(top1=0.25)}}
    md = table2(res, ["arms", "legs"])
    t = cells(md)
    assert t["party / Arms"]["R-Precision Top 1 ↑"] == "**0.500±.010**"
    assert t["holistic / Legs"]["R-Precision Top 1 ↑"] == "**0.250±.010**"   # below party's Arms: own part
    assert t["party / Legs"]["R-Precision Top 1 ↑"] == "0.200±.010"
    assert ("Best R-Precision Top 1 by part — Arms: party 0.500 (±0.010), ahead of holistic beyond the 95% CIs; "
            "Legs: holistic 0.250 (±0.010), ahead of party beyond the 95% CIs.") in md
    assert "Columns left out, no row has a value: R-Precision Top 3, FID, MM-Dist." in md


def test_a_column_without_any_value_is_left_out_with_a_note():
    md = table1(WINS, "holistic")
    head = next(line for line in md.splitlines() if line.startswith("| Method"))
    assert "MultiModality" not in head and "Diversity →" in head
    assert all(row.count("|") == head.count("|") for row in rows_of(md))
    note = [line for line in md.splitlines() if line.startswith("Column left out")]
    assert note == [("Column left out, no row has a value: MultiModality (it needs at least "
                     "`eval.multimodality.times` generations per caption: set `generator.generate.repeats` to at "
                     "least that and rerun `party generate`).")]
    with_mm = {**WINS, "party": {"holistic": {**WINS["party"]["holistic"], "multimodality": _st(2.0)}}}
    md = table1(with_mm, "holistic")
    assert "MultiModality ↑" in md and "left out" not in md               # one value keeps the column


def test_a_one_row_ablation_is_not_shown():
    one = {"full": {"pg": True, "ptg": True}}
    t5 = table5(RESULTS, one, "holistic")
    assert "###" not in t5 and "|" not in t5
    assert t5 == ("Table 5 (ablation of the proposed components) not shown: 1 scored run (full) declares switches; "
                  "an ablation needs at least 2.")
    unscored = {"full": {"pg": True}, "ghost": {"pg": False}}              # a run without scores is no point
    assert "### Table 5" not in table5(RESULTS, unscored, "holistic")
    full = report(RESULTS, {}, one, "## H", whole_stream="holistic", part_streams=["arms", "legs"])
    assert "### Table 5" not in full and "| full | ✓" not in full and "Table 5 (ablation" in full
    assert "### Table 5" in report(RESULTS, {}, PAPER, "## H", whole_stream="holistic", part_streams=["arms"])


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


# --- report.html ---------------------------------------------------------------------------------

def _page(tables_md: str, gif: bytes = b"GIF89a"):
    from party.evaluation.html import report_html
    return report_html(tables_md, None, [("a person waves", gif)], "t")


def test_the_page_has_a_legend_and_marks_the_best():
    from party.render import CENTER_COLOR, LEFT_COLOR, RIGHT_COLOR, TRAJ_COLOR
    md = report(WINS, {}, {}, "## H", whole_stream="holistic", part_streams=["arms"])
    page = _page(md)
    legend = re.search(r"<div class='legend'>(.*?)</div>", page, re.DOTALL).group(1)
    assert re.search(f"background: {LEFT_COLOR}'></span>left arm and leg \\(red\\)", legend)
    assert re.search(f"background: {RIGHT_COLOR}'></span>right arm and leg \\(blue\\)", legend)
    assert CENTER_COLOR in legend and TRAJ_COLOR in legend
    assert "↑ higher is better, ↓ lower is better, → closest to Real motion is better" in legend
    assert page.count("↑ higher is better") == 1                          # not again above the tables
    assert "<td><strong>0.450±.010</strong></td>" in page and "<td><strong>0.440±.010</strong>†</td>" in page
    assert "**" not in page
    assert "Animations" not in report_html_without_gifs(md)               # no animations: no colour legend


def report_html_without_gifs(md):
    from party.evaluation.html import report_html
    return report_html(md, None, [], "t")


def test_animations_wrap_and_shrink_to_the_page():
    page = _page("")
    assert re.search(r"\.grid \{[^}]*flex-wrap: wrap", page)
    assert re.search(r"figure img \{[^}]*max-width: 100%", page)
    assert re.search(r"<div class='grid'>\s*<figure><img alt='a person waves'", page)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (Debian package `chromium`)")
def test_wide_animations_fit_a_1400_px_window(tmp_path):
    """Five 320 px panels (1,600 px) in a 1,400 px window: scaled down, no horizontal scrollbar."""
    import io
    import subprocess

    from PIL import Image
    buf = io.BytesIO()
    Image.new("RGB", (1600, 200), (200, 30, 30)).save(buf, format="GIF")
    probe = ("<script>window.addEventListener('load', function () { var i = document.images[0];"
             "document.body.setAttribute('data-fit', String(document.documentElement.scrollWidth <= window.innerWidth"
             " && i.getBoundingClientRect().right <= window.innerWidth)); });</script></body>")
    page = _page(report(WINS, {}, {}, "## H", whole_stream="holistic", part_streams=["arms"]), buf.getvalue())
    path = tmp_path / "report.html"
    path.write_text(page.replace("</body>", probe))
    dom = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--window-size=1400,900",
                          "--virtual-time-budget=5000", "--dump-dom", path.as_uri()],
                         capture_output=True, text=True, timeout=120, check=False).stdout
    assert 'data-fit="true"' in dom, dom[:300]
