"""``party results``: docs/results.md is rendered from the snapshot docs/results.json alone, which
holds the evaluation's tables with CIs, the stage times and the machine of ``party repro``'s
summary; the page's claims follow the numbers; the committed page is what its snapshot renders."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from party import cli, repro, results
from party.evaluation.report import dvc_metrics, report

ROOT = Path(__file__).resolve().parents[1]
SHA = "0123456789abcdef0123456789abcdef01234567"
MACHINE = {"cpu_model": "Test CPU Model 9000", "cores": 7, "platform": "Linux-test", "python": "3.11.0",
           "torch": "2.0.0", "cpu_capability": "AVX512", "native_bf16": True, "cuda": None,
           "env": {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_AMX"},
           "precision": {"trainer": "32-true", "vqvae": "bf16-mixed", "evaluator": "32-true",
                         "generator": "bf16-mixed", "text": "bf16-mixed"},
           "commit": SHA, "dirty": False, "changed": []}
STAGES = {"prepare": {"status": "ran", "seconds": 12.5, "threads": 2},
          "train_vqvae@arms": {"status": "ran", "seconds": 321.9, "threads": 1, "precision": "32-true"},
          "evaluate": {"status": "ran", "seconds": 45.0, "threads": 2, "precision": ["bf16-mixed", "32-true"]}}


def st(mean, ci):
    return {"mean": mean, "ci95": ci, "n": 2}


def evaluation(alpha_fid=10.0, beta_fid=20.0, ci=0.5):
    """metrics.json's results: real motion, one reconstruction, two generated methods."""
    def src(fid, ci, tc):
        stream = {"fid": st(fid, ci), "mm_dist": st(5.0, 0.01), "diversity": st(2.0, 0.1)}
        return {"holistic": dict(stream), "arms": dict(stream), "legs": dict(stream),
                "coherence": {"tc": st(tc, 0.001), "sc": st(0.9, 0.001)}}
    res = {"ground_truth": src(0.1, 0.01, 0.5), "recon_holistic": {"holistic": {"fid": st(5.0, 0.1)},
                                                                    "reconstruction": {"mpjpe_mm": st(90.0, 0.1)}},
           "alpha": src(alpha_fid, ci, 0.8), "beta": src(beta_fid, ci, 0.7)}
    eff = {"evaluators": {"holistic": 1000, "arms": 900, "legs": 900},
           "tokenizers": {"holistic": {"params": 2000, "window": 8, "ait_ms": 1.5}},
           "generated": {"alpha": {"params": 300, "ait_ms": 2.0}, "beta": {"params": 400, "ait_ms": 3.0}}}
    summary = {"dataset": "synthetic", "split": "test", "n_clips": 8, "replications": 2,
               "evaluators": {"holistic": "trained", "arms": "trained", "legs": "trained"}, "seconds": 1.5,
               "device": "cpu", "workers": 1, "subsets": {}, "generated_clips": {"alpha": 8, "beta": 8}}
    return {"summary": summary, "results": res, "efficiency": eff}


def project(root: Path, metrics: dict, summary: dict | None, grid: bool = True) -> Path:
    """A project's outputs as the pipeline leaves them: params.yaml, data/eval, metrics/eval, the
    repro summary, one sweep's table."""
    params = {"dataset": {"parts": {"streams": ["holistic", "arms", "legs"],
                                    "stream_parts": {"arms": ["left_arm"], "legs": ["left_leg"]}}},
              "eval": {"out_dir": "data/eval", "metrics_dir": "metrics/eval"},
              "generator": {"ablation": {"out_dir": "data/ablations"}}}
    (root / "params.yaml").write_text(yaml.safe_dump(params))
    ev = root / "data" / "eval"
    ev.mkdir(parents=True, exist_ok=True)
    (ev / "metrics.json").write_text(json.dumps(metrics))
    tables = report(metrics["results"], metrics["efficiency"], {}, "## Evaluation: synthetic / test (8 clips)",
                    whole_stream="holistic", part_streams=["arms", "legs"])
    (ev / "tables.md").write_text(tables)
    md = root / "metrics" / "eval"
    shutil.rmtree(md, ignore_errors=True)
    md.mkdir(parents=True)
    for source, means in dvc_metrics(metrics["results"], 4).items():
        (md / f"{source}.json").write_text(json.dumps(means))
    if summary is not None:
        (root / "logs" / "repro").mkdir(parents=True, exist_ok=True)
        (root / "logs" / "repro" / "summary.json").write_text(json.dumps(summary))
    if grid:
        g = root / "data" / "ablations" / "gen_tab5"
        g.mkdir(parents=True, exist_ok=True)
        (g / "table.md").write_text("# gen_tab5\n\nablation\n\n| point | fid |\n|---|---|\n| no_pg | 12.345 |\n")
        (g / "status.json").write_text(json.dumps({"name": "gen_tab5", "points": {"no_pg": {"status": "done"}}}))
    return root


def page_of(root: Path) -> str:
    assert cli.main(["results", "--root", str(root)]) == 0
    return (root / "docs" / "results.md").read_text()


def test_the_page_holds_tables_times_machine_and_claims_that_follow_the_numbers(tmp_path):
    summary = {"jobs": 2, "seconds": 300.0, "stages": STAGES, "machine": MACHINE}
    page = page_of(project(tmp_path, evaluation(alpha_fid=10.0, beta_fid=20.0), summary))
    assert page.startswith("# Results\n\n" + results.NOTICE)
    rows = page.splitlines()
    assert any(r.startswith("| alpha |") and "10.000±.500" in r for r in rows)          # Table 1, with its CI
    assert any(r.startswith("| beta | Legs |") and "20.000±.500" in r for r in rows)    # Table 2
    assert "| train_vqvae@arms | ran | 1 | 32-true | 321.9 |" in page       # stage times, threads, precision
    assert "| prepare | ran | 2 | - | 12.5 |" in page and "| 2 | bf16-mixed, 32-true | 45.0 |" in page
    assert "| **sum of the stages** | | | | 379.4 | 100% |" in page
    assert "Total wall time: 300.0 s (5.0 min), with `party repro -j 2`" in page
    assert "The longest stage is train_vqvae@arms" in page
    assert "Test CPU Model 9000, 7 cores" in page and "CPU capability AVX512" in page
    assert "`ONEDNN_MAX_CPU_ISA=AVX512_CORE_AMX`" in page
    assert "tokenizers (vqvae): bf16-mixed (bf16 autocast)" in page and "evaluators: 32-true (fp32)" in page
    assert f"Commit: `{SHA}` (clean" in page
    assert "### gen_tab5" in page and "| no_pg | 12.345 |" in page and "points: 1 done" in page
    fid = "FID ↓ (holistic): **alpha** is best (10.000 ± 0.500), then beta (20.000 ± 0.500); beyond the 95% CIs"
    assert fid in page
    assert "Temporal Coherence (TC) ↑ (coherence): **alpha** is best" in page
    snap = results.load(tmp_path / "docs" / "results.json")
    assert snap["machine"]["cpu_model"] == MACHINE["cpu_model"] and snap["commit"]["sha"] == SHA
    assert snap["evaluation"]["results"]["alpha"]["holistic"]["fid"] == st(10.0, 0.5)
    assert snap["repro"]["stages"] == STAGES and snap["grids"][0]["name"] == "gen_tab5"
    assert results.render(snap) == page

    # the numbers flip: so does the claim; overlapping CIs: the lead is no longer beyond them
    page = page_of(project(tmp_path, evaluation(alpha_fid=20.0, beta_fid=10.0), summary))
    assert "FID ↓ (holistic): **beta** is best (10.000 ± 0.500), then alpha (20.000 ± 0.500); beyond" in page
    assert fid not in page
    page = page_of(project(tmp_path, evaluation(alpha_fid=10.0, beta_fid=11.0, ci=2.0), summary))
    assert "**alpha** is best (10.000 ± 2.000), then beta (11.000 ± 2.000); not beyond the 95% CIs" in page


def test_check_fails_on_a_page_edited_by_hand(tmp_path, capsys):
    page_of(project(tmp_path, evaluation(), {"jobs": 1, "seconds": 10.0, "stages": STAGES, "machine": MACHINE}))
    assert cli.main(["results", "--root", str(tmp_path), "--check"]) == 0
    page = tmp_path / "docs" / "results.md"
    page.write_text(page.read_text().replace("**alpha** is best", "**beta** is best"))
    assert cli.main(["results", "--root", str(tmp_path), "--check"]) == 1
    assert "edited by hand, or stale" in capsys.readouterr().err
    assert cli.main(["results", "--root", str(tmp_path), "--render-only"]) == 0
    assert cli.main(["results", "--root", str(tmp_path), "--check"]) == 0


def test_a_summary_without_machine_and_a_run_without_summary(tmp_path):
    page = page_of(project(tmp_path, evaluation(), {"jobs": 2, "seconds": 10.0, "stages": STAGES}, grid=False))
    assert "Machine not recorded" in page and "Commit: not recorded" in page
    assert "| prepare | ran | 2 | - | 12.5 |" in page and "No sweep ran" in page
    (tmp_path / "logs" / "repro" / "summary.json").unlink()
    page = page_of(tmp_path)
    assert "Stage times" in page and "Not recorded: no `logs/repro/summary.json`" in page


def test_stale_tracked_means_are_refused(tmp_path):
    project(tmp_path, evaluation(), None)
    (tmp_path / "metrics" / "eval" / "alpha.json").write_text(json.dumps({"holistic": {"fid": 99.0}}))
    with pytest.raises(SystemExit, match=r"disagree.*alpha\.holistic\.fid"):
        results.gather(tmp_path)
    shutil.rmtree(tmp_path / "data" / "eval")
    with pytest.raises(SystemExit, match="metrics.json not found"):
        results.gather(tmp_path)


def test_the_committed_page_is_what_its_snapshot_renders():
    snap = ROOT / "docs" / "results.json"
    if not snap.is_file():
        pytest.skip("docs/results.json does not exist yet: `party results` writes it (with docs/results.md) "
                    "after a pipeline run")
    page = ROOT / "docs" / "results.md"
    assert page.is_file(), "docs/results.json without docs/results.md: run `party results --render-only`"
    assert page.read_text() == results.render(results.load(snap)), (
        "docs/results.md differs from what docs/results.json renders (edited by hand, or stale): "
        "run `party results --render-only`, or `party results` after a pipeline run")


def test_repro_records_the_machine_in_its_summary(tmp_path, monkeypatch):
    """``party repro``'s summary.json holds the machine block ``party results`` publishes: CPU
    model and cores, torch's CPU capability, the CPU environment variables set, the precision each
    part resolved to (from params.yaml), and the commit the run started from."""
    import torch

    from party.training import cpu_has_native_bf16
    script = tmp_path / "dvc"
    script.write_text(f"#!{sys.executable}\nprint('Running stage', flush=True)\n")
    script.chmod(0o755)
    monkeypatch.chdir(ROOT)
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    monkeypatch.delenv("ATEN_CPU_CAPABILITY", raising=False)
    summary = repro.run({"a": [], "b": ["a"]}, 2, dvc=str(script), log_dir=tmp_path / "logs")
    saved = json.loads((tmp_path / "logs" / "summary.json").read_text())
    assert saved == summary and {s: r["status"] for s, r in saved["stages"].items()} == {"a": "ran", "b": "ran"}
    m = saved["machine"]
    assert m["cpu_model"] == repro.cpu_model() and m["cpu_model"] not in ("", "unknown")
    assert m["cores"] == os.cpu_count()
    assert m["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert m["env"].get("ONEDNN_MAX_CPU_ISA") == "AVX2" and "ATEN_CPU_CAPABILITY" not in m["env"]
    assert m["native_bf16"] == cpu_has_native_bf16()
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    assert set(m["precision"]) >= {"trainer", "vqvae", "evaluator", "generator", "text"}
    assert set(m["precision"].values()) <= {"32-true", "bf16-mixed"}
    if params["vqvae"]["trainer"]["precision"] == "auto" and not torch.cuda.is_available():
        assert m["precision"]["vqvae"] == ("bf16-mixed" if cpu_has_native_bf16() else "32-true")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=False)
    if head.returncode == 0:
        assert m["commit"] == head.stdout.strip() and isinstance(m["dirty"], bool)
    monkeypatch.chdir(tmp_path)                                  # no params.yaml: what auto resolves to
    assert set(repro.resolved_precisions()) == {"auto"}


def test_weights_are_scaled_to_the_last_runs_times():
    """``repro.expected_seconds`` are relative weights: next to measured times they are scaled by
    the ratio over the stages both have, so the mix orders as the measured machine would."""
    w = {"a": 1.0, "b": 2.0, "c": 3.0}
    assert repro.scaled_weights(w, {"a": 10.0, "b": 20.0}) == {"a": 10.0, "b": 20.0, "c": 30.0}
    assert repro.scaled_weights(w, {"x": 5.0}) == w
    graph = {"p": [], "slow": ["p"], "quick": ["p"]}
    # the last run measured quick only (slow was unchanged); unscaled, slow's weight (5) would lose
    prio = repro.priorities(graph, {**repro.scaled_weights({"slow": 5.0, "quick": 1.0}, {"quick": 60.0}),
                                    "quick": 60.0})
    assert prio["slow"] > prio["quick"]
    conf = yaml.safe_load((ROOT / "conf" / "config.yaml").read_text())["repro"]["expected_seconds"]
    assert max(conf.values()) == 100                             # relative: the costliest stage = 100


def test_readme_headline_table_comes_from_the_snapshot(tmp_path, capsys):
    """README's headline block is written by `party results`, bolds the best method per column
    (and every method inside its CI), and `--check` fails when the block is edited by hand."""
    summary = {"jobs": 2, "seconds": 300.0, "stages": STAGES, "machine": MACHINE}
    project(tmp_path, evaluation(alpha_fid=10.0, beta_fid=20.0), summary)
    start, end = results.HEADLINE
    (tmp_path / "README.md").write_text(f"# x\n\n{start}\nSTALE-BLOCK\n{end}\n\nrest\n")
    page_of(tmp_path)
    readme = (tmp_path / "README.md").read_text()
    block = readme[readme.index(start):readme.index(end)]
    assert "STALE-BLOCK" not in block and readme.endswith(f"{end}\n\nrest\n")
    rows = {r.split(" | ")[0]: r for r in block.splitlines() if r.startswith("| ")}
    assert "**10.000** ± 0.500" in rows["| alpha"] and "**" not in rows["| beta"].split(" | ")[1]
    assert "| real motion | 0.100 ± 0.010" in block and "Test CPU Model 9000" in block
    assert cli.main(["results", "--root", str(tmp_path), "--check"]) == 0
    (tmp_path / "README.md").write_text(readme.replace("**10.000**", "**9.000**"))
    assert cli.main(["results", "--root", str(tmp_path), "--check"]) == 1
    assert "headline table" in capsys.readouterr().err
    # overlapping CIs: both methods are bold
    page_of(project(tmp_path, evaluation(alpha_fid=10.0, beta_fid=11.0, ci=2.0), summary))
    block = (tmp_path / "README.md").read_text()
    assert "**10.000** ± 2.000" in block and "**11.000** ± 2.000" in block


def test_the_committed_readme_headline_is_what_the_snapshot_renders():
    snap = ROOT / "docs" / "results.json"
    if not snap.is_file():
        pytest.skip("docs/results.json does not exist yet")
    readme = (ROOT / "README.md").read_text()
    assert results.HEADLINE[0] in readme, "README.md lost its headline markers"
    assert results.with_headline(readme, results.load(snap)) == readme, (
        "README.md's headline table differs from docs/results.json: run `party results --render-only`")


def test_a_rerun_without_a_grid_keeps_the_earlier_grid_marked_with_its_commit(tmp_path):
    """A grid takes hours: `party results` after a fresh run of the default keeps the earlier
    snapshot's grids that this project did not run, each marked kept with the commit it was read
    with; `--drop-grids` leaves only this project's."""
    summary = {"jobs": 2, "seconds": 300.0, "stages": STAGES, "machine": MACHINE}
    page = page_of(project(tmp_path, evaluation(alpha_fid=10.0, beta_fid=20.0), summary))
    assert f"(points: 1 done; commit `{SHA[:7]}`)" in page
    shutil.rmtree(tmp_path / "data" / "ablations")
    later = {**summary, "machine": {**MACHINE, "commit": "f" * 40}}
    page = page_of(project(tmp_path, evaluation(alpha_fid=10.0, beta_fid=20.0), later, grid=False))
    assert "| no_pg | 12.345 |" in page
    assert f"(points: 1 done; kept from an earlier run, commit `{SHA[:7]}`, not rerun for this page)" in page
    snap = results.load(tmp_path / "docs" / "results.json")
    assert snap["commit"]["sha"] == "f" * 40 and [g["name"] for g in snap["grids"]] == ["gen_tab5"]
    assert snap["grids"][0]["kept"] and "data/ablations/gen_tab5/table.md" in snap["inputs"]
    assert cli.main(["results", "--root", str(tmp_path), "--drop-grids"]) == 0
    assert "gen_tab5" not in (tmp_path / "docs" / "results.md").read_text()
    assert results.load(tmp_path / "docs" / "results.json")["grids"] == []


def test_grids_only_puts_another_workspaces_grid_onto_the_page(tmp_path):
    """`party results --grids-only --root W`: W's grid tables replace those of the same name on the
    page (its evaluation and other grids kept), each marked with the commits its points recorded."""
    summary = {"jobs": 2, "seconds": 300.0, "stages": STAGES, "machine": MACHINE}
    main = tmp_path / "main"
    main.mkdir()
    page_of(project(main, evaluation(alpha_fid=10.0, beta_fid=20.0), summary))
    other = tmp_path / "other"
    for name, commits in (("gen_tab5", ["a" * 40]), ("tomato_groups", ["b" * 40, "c" * 40])):
        g = other / "data" / "ablations" / name
        g.mkdir(parents=True)
        (g / "table.md").write_text(f"# {name}\n\n| point | mpjpe |\n|---|---|\n| p0 | 1.5 |\n")
        (g / "status.json").write_text(json.dumps({"name": name, "points": {
            f"p{i}": {"status": "done", "commit": c} for i, c in enumerate(commits)}}))
    assert cli.main(["results", "--root", str(other), "--out", str(main / "docs"), "--grids-only"]) == 0
    page = (main / "docs" / "results.md").read_text()
    assert "| alpha |" in page and "10.000±.500" in page                       # the evaluation kept
    assert "| no_pg | 12.345 |" not in page                                   # gen_tab5 replaced ...
    assert f"(points: 1 done; commit `{'a' * 7}`)" in page                      # ... marked with its commit
    assert f"(points: 2 done; commits `{'b' * 7}`, `{'c' * 7}`)" in page and "### tomato_groups" in page
    assert page == results.render(results.load(main / "docs" / "results.json"))
    with pytest.raises(SystemExit, match="no grid table under"):
        cli.main(["results", "--root", str(tmp_path / "none"), "--out", str(main / "docs"), "--grids-only"])
