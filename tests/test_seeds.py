"""party.seeds: a grid's rows over its seed axis, and which leads survive the training noise."""
import json

import pytest
import yaml

from party import cli, seeds
from party.sweep import load_sweep


def row(seed, method, guidance, top1, fid, ci=0.004, side=None):
    r = {"point": f"{seed}-{method}-{guidance}", "seed": seed, "method": method, "guidance": guidance,
         "params": 10, "top1": top1, "top1_ci95": ci, "fid": fid, "fid_ci95": 0.01, "steps": 100}
    if side is not None:
        r["side"] = side
    return r


AXES = ["seed", "method", "guidance"]


def grid_rows():
    # at g1: a beats b on Top 1 at every seed (ranges [0.30, 0.32] vs [0.25, 0.28]); FID overlaps
    # at g2: a's seeds straddle b's (0.27..0.33 vs 0.29..0.30): a leads on the mean only
    return [row("s1", "a", "g1", 0.30, 1.0), row("s2", "a", "g1", 0.32, 1.4), row("s3", "a", "g1", 0.31, 1.2),
            row("s1", "b", "g1", 0.25, 1.3), row("s2", "b", "g1", 0.28, 1.1), row("s3", "b", "g1", 0.27, 1.2),
            row("s1", "a", "g2", 0.27, 2.0), row("s2", "a", "g2", 0.33, 2.1), row("s3", "a", "g2", 0.32, 2.2),
            row("s1", "b", "g2", 0.29, 1.0), row("s2", "b", "g2", 0.30, 1.1)]


def test_summary_means_ranges_and_cis():
    groups = seeds.summarize(grid_rows(), AXES, "seed")
    assert [g["labels"] for g in groups] == [{"method": m, "guidance": g} for g in ("g1", "g2") for m in "ab"]
    a1 = groups[0]
    assert a1["seeds"] == ["s1", "s2", "s3"]
    assert a1["stats"]["top1"] == pytest.approx({"mean": 0.31, "min": 0.30, "max": 0.32, "spread": 0.02,
                                                 "ci": 0.004, "n": 3})
    assert seeds.metric_columns(grid_rows()) == ["top1", "fid"]
    with pytest.raises(ValueError, match="seed axis 'run'"):
        seeds.summarize(grid_rows(), AXES, "run")


def test_a_lead_is_beyond_the_noise_only_when_the_seed_ranges_do_not_overlap():
    comps = seeds.compare(seeds.summarize(grid_rows(), AXES, "seed"), ["top1", "fid"], within=["guidance"])
    by = {(c["context"]["guidance"], c["column"]): c for c in comps}
    assert by["g1", "top1"]["best"] == "a" and by["g1", "top1"]["beyond"]          # every a-seed above every b-seed
    assert by["g2", "top1"]["best"] == "a" and not by["g2", "top1"]["beyond"]      # a ahead on the mean only
    assert by["g2", "fid"]["best"] == "b" and by["g2", "fid"]["beyond"]            # lower is better: 1.0-1.1 vs 2.0-2.2
    assert not by["g1", "fid"]["beyond"]
    # a gap inside the evaluation CIs is not beyond, even with apart ranges
    wide = [dict(r, top1_ci95=0.05) for r in grid_rows()]
    assert not next(c for c in seeds.compare(seeds.summarize(wide, AXES, "seed"), ["top1"], ["guidance"])
                    if c["context"]["guidance"] == "g1")["beyond"]
    # one seed says nothing about the training noise
    one = [r for r in grid_rows() if r["seed"] == "s1"]
    assert not any(c["beyond"] for c in seeds.compare(seeds.summarize(one, AXES, "seed"), ["top1", "fid"], ["guidance"]))


def test_focus_against_each_other_group_and_the_markdown():
    groups = seeds.summarize(grid_rows(), AXES, "seed")
    rows = seeds.against(groups, "a", ["top1", "fid"], ["guidance"])
    assert [(r["context"]["guidance"], r["other"]) for r in rows] == [("g1", "b"), ("g2", "b")]
    assert rows[0]["cells"]["top1"] == (pytest.approx(0.0433, abs=1e-3), "ahead")
    assert rows[1]["cells"]["fid"] == (pytest.approx(-1.05, abs=1e-3), "behind")  # > 0 favours a: FID is lower-better
    assert rows[1]["cells"]["top1"][1] == "within"
    md = "\n".join(seeds.render(groups, ["guidance"], ["top1", "fid", "nothing"], focus=["a"]))
    assert "| method | guidance | seeds | steps trained | Top 1 ↑ | FID ↓ |" in md
    assert "| a | g1 | s1, s2, s3 | 100 | **0.310 [0.300, 0.320] ±0.004** |" in md
    assert "| guidance | against | Top 1 ↑ | FID ↓ |" in md and "| g1 | b | +0.043 ✓ |" in md
    assert "| g2 | b | +0.012 | -1.050 ✗ |" in md
    assert "- Top 1 ↑ (guidance g2): a 0.307 > b 0.295; a over b within the training noise." in md


def test_the_spec_declares_the_seed_axis(tmp_path):
    p = tmp_path / "g.yaml"
    spec = {"name": "g", "axes": {"seed": {"s1": ["seed=1"]}, "m": {"x": ["v.a=1"]}}}
    p.write_text(yaml.safe_dump({**spec, "seeds": {"axis": "seed", "within": ["m"], "focus": ["x"]}}))
    assert load_sweep(str(p))["seeds"] == {"axis": "seed", "within": ["m"], "focus": ["x"]}
    p.write_text(yaml.safe_dump({**spec, "seeds": {"axis": "seed", "within": ["m"], "curve": "m"}}))
    assert load_sweep(str(p))["seeds"]["curve"] == "m"
    for bad in ({"axis": "run"}, {"axis": "seed", "within": ["seed"]}, {"axis": "seed", "within": [], "foo": 1},
                {"axis": "seed", "within": [], "columns": "top1"}, {"axis": "seed", "within": [], "curve": "m"}):
        p.write_text(yaml.safe_dump({**spec, "seeds": bad}))
        with pytest.raises(ValueError, match="'seeds'|seeds.curve"):
            load_sweep(str(p))
    for name in ("gen_methods", "gen_tab5_spec", "gen_seeds", "gen_seeds_holistic", "gen_budget",
                 "gen_budget_gpu"):   # the shipped grids
        assert load_sweep(name)["seeds"]["axis"] == "seed"
    for name in ("gen_budget", "gen_budget_gpu"):       # budgets with their lr milestone scaled (3/4 of the steps)
        spec = load_sweep(name)
        assert spec["seeds"]["curve"] == "budget" and list(spec["axes"])[0] == "budget"
        for label, ov in spec["axes"]["budget"].items():
            kv = dict(o.split("=", 1) for o in ov)
            steps, milestone = int(kv["generator.train.max_steps"]), int(kv["generator.optim.milestone"])
            assert milestone == (100000 if label == "paper" else steps * 3 // 4), label


def test_the_results_page_shows_a_seeded_grid_over_its_seeds(tmp_path):
    from test_results_page import evaluation, project

    root = project(tmp_path, evaluation(alpha_fid=10.0, beta_fid=20.0), None, grid=False)
    (root / "conf" / "sweep").mkdir(parents=True)
    (root / "conf" / "sweep" / "gm.yaml").write_text(yaml.safe_dump({
        "name": "gm", "axes": {"seed": {s: [] for s in ("s1", "s2", "s3")}, "method": {"a": [], "b": []},
                               "guidance": {"g1": [], "g2": []}},
        "seeds": {"axis": "seed", "within": ["guidance"], "focus": ["a"], "columns": ["top1", "fid", "side"]}},
        sort_keys=False))
    g = root / "data" / "ablations" / "gm"
    (g / "side").mkdir(parents=True)
    points = {r["point"]: {"status": "done", "row": r} for r in grid_rows()}
    points["s3-b-g2"] = {"status": "running"}
    (g / "status.json").write_text(json.dumps({"name": "gm", "sweep": "conf/sweep/gm.yaml", "points": points}))
    (g / "table.md").write_text("# gm\n\n| point | top1 |\n|---|---|\n")
    for r in grid_rows():
        (g / "side" / f"{r['point']}.json").write_text(json.dumps({r["method"]: {"mean": 0.9 if r["method"] == "a" else 0.5}}))
    assert cli.main(["results", "--root", str(root)]) == 0
    page = (root / "docs" / "results.md").read_text()
    assert "#### gm: mean over training seeds (axis `seed`)" in page
    assert "| method | guidance | seeds | steps trained | Top 1 ↑ | FID ↓ | named side ↑ |" in page
    assert "| b | g2 | s1, s2 | 100 | 0.295 [0.290, 0.300] ±0.004 | **1.050 [1.000, 1.100] ±0.010** | 0.500 [0.500, 0.500] |" in page
    assert "| g1 | b | +0.043 ✓ | 0.000 | +0.400 ✓ |" in page


def budget_rows(short_seed=None):
    """Two methods at two budgets (steps 100 and 300), three seeds; ``short_seed`` trained 100 at b3."""
    out = []
    for b, steps in (("b1", 100), ("b3", 300)):
        for i, s in enumerate(("s1", "s2", "s3")):
            for m, base in (("a", 0.30), ("b", 0.25)):
                top1 = base + (0.05 if b == "b3" else 0.0) + 0.01 * i
                r = {"point": f"{b}-{s}-{m}", "budget": b, "seed": s, "method": m, "top1": top1,
                     "top1_ci95": 0.002, "fid": 1.0, "fid_ci95": 0.01,
                     "steps": 100 if (b, s) == ("b3", short_seed) else steps}
                out.append(r)
    return out


def test_the_curve_over_the_steps_trained(tmp_path):
    axes = ["budget", "seed", "method"]
    groups = seeds.summarize(budget_rows(), axes, "seed")
    c = seeds.curves(groups, "budget", ["top1"])
    assert list(c["top1"]) == ["a", "b"]
    assert c["top1"]["a"] == [pytest.approx((100.0, "b1", 0.31, 0.30, 0.32)), pytest.approx((300.0, "b3", 0.36, 0.35, 0.37))]
    png = seeds.curve_png(groups, "budget", ["top1", "fid"])
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # one budget only: no curve to draw
    assert seeds.curve_png(seeds.summarize([r for r in budget_rows() if r["budget"] == "b1"], axes, "seed"),
                           "budget") is None
    # a point served by a shorter run shows in the table: its group lists both budgets trained
    md = "\n".join(seeds.render(seeds.summarize(budget_rows(short_seed="s2"), axes, "seed"), ["budget"], ["top1"]))
    assert "| budget | method | seeds | steps trained | Top 1 ↑ |" in md
    assert "| b3 | a | s1, s2, s3 | 100, 300 |" in md and "| b1 | a | s1, s2, s3 | 100 |" in md
    # without recorded steps the x is the label's position on the axis
    plain = [{k: v for k, v in r.items() if k != "steps"} for r in budget_rows()]
    assert [p[0] for p in seeds.curves(seeds.summarize(plain, axes, "seed"), "budget")["top1"]["a"]] == [1.0, 2.0]


def test_the_grid_report_and_a_bad_side_cache(tmp_path):
    spec = {"name": "gb", "description": "budgets", "axes": {"budget": {}, "seed": {}, "method": {}},
            "seeds": {"axis": "seed", "within": ["budget"], "focus": ["a"], "curve": "budget"}}
    points = {r["point"]: {"status": "done", "row": r} for r in budget_rows()}
    points["b3-s3-b"] = {"status": "running"}
    path = seeds.write_grid_report(tmp_path, spec, points)
    page = path.read_text()
    assert path == tmp_path / "report.html"
    assert "Metrics against budget" in page and page.count("data:image/png;base64,") == 1
    assert "<td>b3</td><td>b</td><td>s1, s2</td>" in page        # the running point is not in the means
    assert "<li>Top 1 ↑ (budget b1)" in page and "Tables and charts" not in page   # its own legend, lists
    assert seeds.write_grid_report(tmp_path, {**spec, "seeds": None}, points) is None
    (tmp_path / "side").mkdir()
    (tmp_path / "side" / "b1-s1-a.json").write_text('{"a": {"mean": 0.8}}')
    assert seeds.finished_rows(tmp_path, points)[0]["side"] == 0.8
    (tmp_path / "side" / "b1-s1-a.json").write_text('{"a": {}}')
    with pytest.raises(ValueError, match=r"side/b1-s1-a.json: not a named-side check"):
        seeds.finished_rows(tmp_path, points)
