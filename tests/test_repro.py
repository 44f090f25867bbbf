"""``party repro -j N``: stages start only after what they depend on, independent ones overlap,
a failure blocks its dependents, DVC's "didn't change" is reported as unchanged. A fake ``dvc``
executable stands in for DVC here; tests/test_pipeline.py runs the real one."""
import json
import os
import subprocess
import signal
import sys
import textwrap
import time
from pathlib import Path

import pytest
import yaml

from party import repro

ROOT = Path(__file__).resolve().parents[1]

FAKE = textwrap.dedent("""\
    import json, os, sys, time
    assert sys.argv[1:4] == ["--wait-for-lock", "repro", "--single-item"], sys.argv
    stage = sys.argv[4]
    spec = json.load(open(os.environ["FAKE_SPEC"]))
    with open(os.environ["FAKE_TRACE"], "a") as f:
        f.write(json.dumps([stage, "start", time.time(), os.environ.get("OMP_NUM_THREADS")]) + "\\n")
    time.sleep(spec.get("sleep", {}).get(stage, 0.3))
    if stage in spec.get("noted", {}):       # what party.training.note_stage writes
        json.dump(spec["noted"][stage], open(os.environ["PARTY_STAGE_INFO"], "w"))
    if stage in spec.get("unchanged", []):
        print(f"Stage '{stage}' didn't change, skipping")
    else:
        print(f"Running stage '{stage}':")
    with open(os.environ["FAKE_TRACE"], "a") as f:
        f.write(json.dumps([stage, "end", time.time(), None]) + "\\n")
    sys.exit(3 if stage in spec.get("fail", []) else 0)
""")
GRAPH = {"a": [], "b": ["a"], "c": ["a"], "d": ["b", "c"], "e": ["a"]}


@pytest.fixture
def fake(tmp_path, monkeypatch):
    script = tmp_path / "dvc"
    script.write_text(f"#!{sys.executable}\n" + FAKE)
    script.chmod(0o755)
    trace = tmp_path / "trace.jsonl"
    monkeypatch.setenv("FAKE_TRACE", str(trace))
    monkeypatch.setenv("FAKE_SPEC", str(tmp_path / "spec.json"))
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)

    def go(spec, jobs, graph=GRAPH, **kw):
        (tmp_path / "spec.json").write_text(json.dumps(spec))
        trace.write_text("")
        summary = repro.run(graph, jobs, dvc=str(script), log_dir=tmp_path / "logs", **kw)
        events = [json.loads(x) for x in trace.read_text().splitlines()]
        return summary, {(s, k): t for s, k, t, _ in events}, events
    return go


def test_independent_stages_overlap_and_wait_for_their_inputs(fake, tmp_path):
    summary, t, events = fake({"sleep": {"b": 1.0, "c": 1.0}, "unchanged": ["e"]}, jobs=2)
    st = {s: r["status"] for s, r in summary["stages"].items()}
    assert st == {"a": "ran", "b": "ran", "c": "ran", "d": "ran", "e": "unchanged"}
    for s, deps in GRAPH.items():
        for d in deps:
            assert t[(s, "start")] >= t[(d, "end")], (s, d)
    assert t[("b", "start")] < t[("c", "end")] and t[("c", "start")] < t[("b", "end")]   # side by side
    threads = {e[0]: e[3] for e in events if e[1] == "start"}
    cores = os.cpu_count() or 1
    assert threads["a"] == str(cores)                    # alone: every core
    assert threads["b"] == threads["c"] == str(max(1, cores // 2))   # two side by side: half each
    assert (tmp_path / "logs" / "b.log").read_text().startswith("Running stage 'b'")
    saved = json.loads((tmp_path / "logs" / "summary.json").read_text())
    assert saved["stages"]["b"]["seconds"] >= 1.0 and saved["jobs"] == 2


def test_the_summary_says_what_each_stage_ran_with(fake, tmp_path, monkeypatch):
    noted = {"b": {"precision": ["32-true"]}, "c": {"precision": ["bf16-mixed", "32-true"]}}
    summary, _, events = fake({"noted": noted}, jobs=2)
    threads = {e[0]: int(e[3]) for e in events if e[1] == "start"}
    st = summary["stages"]
    assert {s: r["threads"] for s, r in st.items()} == threads
    assert st["b"]["precision"] == "32-true" and st["c"]["precision"] == ["bf16-mixed", "32-true"]
    assert "precision" not in st["a"] and not list((tmp_path / "logs").glob("*.info.json"))   # read, then removed
    from party.training import STAGE_INFO_ENV, note_stage
    f = tmp_path / "noted.json"
    note_stage(precision="32-true")                          # outside party repro: nothing
    assert not f.exists()
    monkeypatch.setenv(STAGE_INFO_ENV, str(f))
    for p in ("bf16-mixed", "32-true", "bf16-mixed"):
        note_stage(precision=p)
    assert json.loads(f.read_text()) == {"precision": ["bf16-mixed", "32-true"]}


def test_never_more_than_jobs_at_once(fake):
    graph = {s: [] for s in "pqrst"}
    _, t, _ = fake({"sleep": {s: 0.4 for s in graph}}, jobs=2, graph=graph)
    for s in graph:                      # at any stage's start, at most one other is running
        at = t[(s, "start")]
        assert sum(t[(o, "start")] <= at < t[(o, "end")] for o in graph if o != s) <= 1


def test_a_failure_blocks_what_depends_on_it(fake, capsys):
    summary, t, _ = fake({"fail": ["b"], "sleep": {"c": 1.0}}, jobs=2)
    st = {s: r["status"] for s, r in summary["stages"].items()}
    assert st["b"] == "failed" and st["d"] in ("blocked", "not started") and ("d", "start") not in t
    assert st["c"] == "ran"                       # already running: allowed to finish
    assert "b: FAILED" in capsys.readouterr().err
    summary, t, _ = fake({"fail": ["b"]}, jobs=1, keep_going=True)
    st = {s: r["status"] for s, r in summary["stages"].items()}
    assert st["d"] == "blocked" and st["c"] == st["e"] == "done"


def test_stages_status_found_unchanged_start_no_dvc_unless_upstream_ran(fake):
    """`unchanged` (one `dvc status` before the run): such a stage is not started when everything
    upstream of it was unchanged too; once an upstream stage ran, DVC decides (it may rerun)."""
    summary, t, _ = fake({"unchanged": ["d"]}, jobs=2, unchanged={"a", "c", "d", "e"})
    st = {s: r["status"] for s, r in summary["stages"].items()}
    assert st == {"a": "unchanged", "b": "ran", "c": "unchanged", "d": "unchanged", "e": "unchanged"}
    assert {s for s, _ in t} == {"b", "d"}       # b: status said changed; d: b ran before it
    summary, t, _ = fake({"unchanged": ["b"]}, jobs=2, unchanged={"a", "c", "d", "e"})
    assert {s for s, _ in t} == {"b"}            # DVC found b unchanged after all: d's inputs are as before
    summary, t, _ = fake({}, jobs=1, unchanged=set(GRAPH))
    assert not t and all(r["status"] == "unchanged" for r in summary["stages"].values())


def test_changed_stages_is_dvcs_status(tmp_path, monkeypatch):
    """The real DVC: a two-stage pipeline, run, then one parameter of the second changed."""
    monkeypatch.chdir(tmp_path)
    subprocess.run(["git", "init", "-q"], check=True)
    subprocess.run([sys.executable, "-m", "dvc", "init", "-q"], check=True)
    (tmp_path / "params.yaml").write_text("x: 1\ny: 1\n")
    (tmp_path / "dvc.yaml").write_text(textwrap.dedent("""\
        stages:
          one:
            cmd: echo 1 > one.txt
            params: [x]
            outs: [one.txt]
          two:
            cmd: cat one.txt > two.txt
            deps: [one.txt]
            params: [y]
            outs: [two.txt]
        """))
    from dvc.repo import Repo

    def changed():
        with Repo(".") as repo:
            assert set(repro.stage_graph(repo)) == {"one", "two"}      # the same addresses
            return repro.changed_stages(repo)
    assert changed() == {"one", "two"}           # never run: not in dvc.lock
    subprocess.run([sys.executable, "-m", "dvc", "repro", "-q"], check=True)
    assert changed() == set()
    (tmp_path / "params.yaml").write_text("x: 1\ny: 2\n")
    assert changed() == {"two"}


def test_targets_select_upstream_and_longest_path_starts_first():
    assert set(repro.select(GRAPH, ["d"])) == {"a", "b", "c", "d"}
    g = {"prep": [], "tok@x": ["prep"], "tok@y": ["prep"], "ev": ["prep"], "gen": ["tok@x", "tok@y"],
         "end": ["gen", "ev"]}
    assert set(repro.select(g, ["tok"])) == {"prep", "tok@x", "tok@y"}
    with pytest.raises(SystemExit, match="no stage 'nope'"):
        repro.select(g, ["nope"])
    p = repro.priorities(g, {"ev": 100.0, "gen": 5.0})
    assert p["ev"] > p["tok@x"]          # known to be long: first
    p = repro.priorities(g, {})
    assert p["tok@x"] > p["ev"]          # unknown costs: more stages downstream first


def test_main_refuses_outside_a_project(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert repro.main(["-j", "2"]) == 2 and "no dvc.yaml" in capsys.readouterr().err


def test_a_fresh_checkout_orders_stages_by_the_expected_times(tmp_path):
    """Without logs/repro/summary.json, repro.expected_seconds of params.yaml gives the order: the
    long stage goes first although both paths have as many stages."""
    params = tmp_path / "params.yaml"
    cfg = yaml.safe_load((ROOT / "params.yaml").read_text())
    cfg["repro"]["expected_seconds"] = {"slow": 600, "quick": 20}
    params.write_text(yaml.safe_dump(cfg))
    assert repro.expected_times(params) == {"slow": 600.0, "quick": 20.0}
    graph = {"a": [], "quick": ["a"], "slow": ["a"], "end": ["quick", "slow"]}
    prio = repro.priorities(graph, repro.expected_times(params))
    assert prio["slow"] > prio["quick"] and prio["a"] == max(prio.values())
    assert repro.expected_times(tmp_path / "missing.yaml") == {}
    cfg["repro"]["expected_seconds"] = {"slow": "a while"}
    params.write_text(yaml.safe_dump(cfg))
    with pytest.raises(ValueError, match=r"params\.yaml.*repro\.expected_seconds"):
        repro.expected_times(params)          # bad input: named, not silently unordered


def test_an_item_without_its_own_entry_takes_its_templates_time(tmp_path):
    """``repro.expected_seconds`` per stage template: every ``template@item`` takes the template's
    value unless it has an entry of its own; a stage with neither stays unknown (1)."""
    params = tmp_path / "params.yaml"
    cfg = yaml.safe_load((ROOT / "params.yaml").read_text())
    cfg["repro"]["expected_seconds"] = {"prep": 10, "train": 300, "train@big": 900}
    params.write_text(yaml.safe_dump(cfg))
    graph = {"prep": [], "train@big": ["prep"], "train@small": ["prep"], "train@other": ["prep"],
             "eval": ["train@big", "train@small", "train@other"]}
    times = repro.stage_times(repro.expected_times(params), graph)
    assert times == {"prep": 10.0, "train@big": 900.0, "train@small": 300.0, "train@other": 300.0}
    prio = repro.priorities(graph, times)
    assert prio["train@big"] > prio["train@small"] == prio["train@other"] and prio["eval"] == 1.0


def test_the_expected_times_cover_every_stage():
    """conf/config.yaml's ``repro.expected_seconds`` gives every stage of the DAG a time (the items
    of a ``foreach`` by their template's entry) and names no stage dvc.yaml lacks."""
    expected = repro.expected_times(ROOT / "params.yaml")
    templates = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    assert {k.split("@", 1)[0] for k in expected} <= set(templates)           # no stale entry
    out = subprocess.run([str(Path(sys.executable).parent / "dvc"), "stage", "list", "--name-only"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    stages = out.stdout.split()
    assert "generate@party" in stages and set(repro.stage_times(expected, stages)) == set(stages)


STAGE = textwrap.dedent("""\
    import os, subprocess, sys, time
    # a stand-in for DVC: runs the stage as a child and dies on SIGTERM without passing it on, as DVC does
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    with open(os.environ["FAKE_PIDS"], "a") as f:
        f.write(f"{child.pid}\\n")
    child.wait()
""")


def test_sigterm_ends_the_running_stages_under_dvc(tmp_path):
    """``kill`` of ``party repro`` (SIGTERM) reaches the stages DVC runs, not only DVC: no stage is
    left running without the command that started it."""
    script = tmp_path / "dvc"
    script.write_text(f"#!{sys.executable}\n" + STAGE)
    script.chmod(0o755)
    pids = tmp_path / "pids"
    code = (f"from party import repro; repro.run({{'a': [], 'b': []}}, 2, dvc={str(script)!r}, "
            f"log_dir=__import__('pathlib').Path({str(tmp_path / 'logs')!r}))")
    proc = subprocess.Popen([sys.executable, "-c", code], env={**os.environ, "FAKE_PIDS": str(pids)},
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(pids.read_text().split() if pids.exists() else []) < 2:
        time.sleep(0.1)
    stages = [int(x) for x in pids.read_text().split()]
    assert len(stages) == 2
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode != 0 and "Terminated" in err
    summary = json.loads((tmp_path / "logs" / "summary.json").read_text())     # written before it re-raises
    assert {s: r["status"] for s, r in summary["stages"].items()} == {"a": "failed", "b": "failed"}
    for pid in stages:                     # the stages are gone (reaped or not: no longer running)
        try:
            state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
        except FileNotFoundError:
            continue
        assert state in ("Z", "X"), (pid, state)


@pytest.mark.parametrize("signal_name,code", [("SIGTERM", 143), ("Ctrl-C", 130)])
def test_a_stopped_repro_says_so_in_one_line(tmp_path, monkeypatch, capsys, signal_name, code):
    """``party repro`` stopped by SIGTERM or Ctrl-C: one line saying what happened to the running
    stages and how to go on, exit 143 / 130, no traceback."""
    import contextlib

    import dvc.repo

    from party.lifecycle import Terminated
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(dvc.repo, "Repo", lambda *a, **k: contextlib.nullcontext())
    monkeypatch.setattr(repro, "stage_graph", lambda r: {"a": []})
    monkeypatch.setattr(repro, "changed_stages", lambda r: {"a"})

    def stopped(*a, **k):
        raise Terminated("received signal 15 (SIGTERM)") if signal_name == "SIGTERM" else KeyboardInterrupt()
    monkeypatch.setattr(repro, "run", stopped)
    assert repro.main(["-j", "2"]) == code
    err = capsys.readouterr().err
    assert err.startswith(f"party repro: stopped by {signal_name}: the stages that were running were ended")
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
