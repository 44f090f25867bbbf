"""party.sweep.run_grid for unattended sweeps: status.json, failures recorded, resume reuses done points."""
import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from party.cli import main
from party.sweep import expand, load_sweep, read_status, run_grid


def _setup(tmp_path):
    grid = tmp_path / "g.yaml"
    grid.write_text("name: g\naxes:\n  a: {x: [v.a=1], y: [v.a=2], z: [v.a=3]}\n")
    cfg = OmegaConf.create({"tracking": {"enabled": False}, "v": {"a": 0}})
    return load_sweep(str(grid)), cfg, tmp_path / "out"


def test_a_failing_point_is_recorded_the_rest_run_and_the_stage_fails(tmp_path, capsys):
    spec, cfg, out = _setup(tmp_path)
    calls, fail = [], {"label": "y"}

    def point(pcfg, p, run):
        calls.append(p["label"])
        if p["label"] == fail["label"]:
            raise ValueError("boom")
        return {"value": pcfg.v.a * 10}

    with pytest.raises(RuntimeError, match=r"1 of 3 points failed \(y\)"):
        run_grid(cfg, spec, "s", point, out, ["point", "value", "status"])
    assert calls == ["x", "y", "z"]
    st = read_status(out)
    assert {k: v["status"] for k, v in st["points"].items()} == {"x": "done", "y": "failed", "z": "done"}
    assert st["points"]["y"]["error"] == "ValueError: boom"
    assert "| y |  | failed |" in (out / "table.md").read_text()
    assert main(["sweep-status", str(out)]) == 1
    assert "2 done, 0 running, 1 failed, 0 pending" in capsys.readouterr().out

    # the rerun retries only the failed point and reuses the others' rows
    calls.clear()
    fail["label"] = None                # the cause is fixed; the configs are unchanged
    rows = run_grid(cfg, spec, "s", point, out, ["point", "value"])
    assert calls == ["y"]
    assert [r["value"] for r in rows] == [10, 20, 30]
    assert main(["sweep-status", str(out)]) == 0
    head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:            # each finished point records the commit it ran (party results prints it)
        assert {e.get("commit") for e in read_status(out)["points"].values()} == {head.stdout.strip()}


def test_sweep_status_into_a_pipe_closed_early_is_quiet(tmp_path):
    """`party sweep-status ... | head`: head's one line, no BrokenPipeError traceback."""
    spec, cfg, out = _setup(tmp_path)
    run_grid(cfg, spec, "s", lambda pcfg, p, run: {"value": 1}, out, ["point", "value"])
    party = f'{sys.executable} -c "import sys; from party.cli import main; sys.exit(main())"'
    r = subprocess.run(["bash", "-c", f"{party} sweep-status {' '.join([out.name] * 5000)} | head -1"],
                       capture_output=True, text=True, timeout=120, cwd=out.parent)   # ~1 MB of output
    assert r.stdout.count("\n") == 1 and "Error" not in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_changed_point_config_reruns_that_point(tmp_path):
    spec, cfg, out = _setup(tmp_path)
    calls = []
    point = lambda pcfg, p, run: calls.append(p["label"]) or {"value": pcfg.v.a}  # noqa: E731
    run_grid(cfg, spec, "s", point, out, ["point", "value"])
    cfg.v.other = 1                     # every point's config changes
    calls.clear()
    run_grid(cfg, spec, "s", point, out, ["point", "value"])
    assert calls == ["x", "y", "z"]
    (out / "status.json").write_text("{oops")
    with pytest.raises(ValueError, match="status.json"):
        read_status(out)
    assert main(["sweep-status", str(tmp_path / "nowhere")]) == 2
    assert len(expand(spec)) == 3


def _slow_point(log_path):
    """A point that logs ``label pid`` and waits until two points have started (so two workers
    each hold one), then returns."""
    import os
    import time

    def point(pcfg, p, run):
        with open(log_path, "a") as f:
            f.write(f"{p['label']} {os.getpid()}\n")
        deadline = time.time() + 20
        while len(open(log_path).read().splitlines()) < 2 and time.time() < deadline:
            time.sleep(0.05)
        return {"value": pcfg.v.a}
    return point


def test_two_worker_processes_share_a_grid_and_run_each_point_once(tmp_path):
    import multiprocessing as mp
    grid = tmp_path / "g.yaml"
    grid.write_text("name: g\naxes:\n  a: {w: [v.a=1], x: [v.a=2], y: [v.a=3], z: [v.a=4]}\n")
    spec, cfg, out = load_sweep(str(grid)), OmegaConf.create({"tracking": {"enabled": False}, "v": {"a": 0}}), tmp_path / "out"
    log_path = tmp_path / "calls.log"
    point = _slow_point(log_path)
    ctx = mp.get_context("fork")
    workers = [ctx.Process(target=run_grid, args=(cfg, spec, "s", point, out, ["point", "value"])) for _ in range(2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(60)
    assert [w.exitcode for w in workers] == [0, 0]
    calls = [line.split() for line in log_path.read_text().splitlines()]
    assert sorted(label for label, _ in calls) == ["w", "x", "y", "z"]          # each point exactly once
    assert len({pid for _, pid in calls}) == 2                                 # by both workers
    st = read_status(out)
    assert {k: v["status"] for k, v in st["points"].items()} == dict.fromkeys("wxyz", "done")
    assert all(str(st["points"][label]["worker"]["pid"]) == pid for label, pid in calls)
    md = (out / "table.md").read_text()                                        # the last worker's table is complete
    assert all(f"| {label} | {v} |" in md for label, v in zip("wxyz", (1, 2, 3, 4)))


def test_a_running_point_of_a_dead_worker_is_rerun_a_live_workers_is_left_alone(tmp_path):
    import json
    import os
    import socket
    import subprocess
    spec, cfg, out = _setup(tmp_path)
    dead = subprocess.Popen(["true"])
    dead.wait()
    host = socket.gethostname()
    out.mkdir()
    (out / "status.json").write_text(json.dumps({"name": "g", "points": {
        "x": {"status": "running", "key": "k", "worker": {"host": host, "pid": dead.pid}},
        "y": {"status": "running", "key": "k", "worker": {"host": host, "pid": os.getppid()}}}}))
    calls = []
    rows = run_grid(cfg, spec, "s", lambda pcfg, p, run: calls.append(p["label"]) or {"value": pcfg.v.a}, out,
                    ["point", "value", "status"])
    assert calls == ["x", "z"]
    assert [r.get("status") for r in rows] == [None, "running", None]
    st = read_status(out)
    assert st["points"]["y"]["worker"]["pid"] == os.getppid() and st["points"]["y"]["status"] == "running"
    assert "| y |  | running |" in (out / "table.md").read_text()


def test_an_interrupted_point_is_recorded_and_retried_by_the_next_run(tmp_path):
    spec, cfg, out = _setup(tmp_path)
    calls, stop = [], {"label": "y"}

    def point(pcfg, p, run):
        calls.append(p["label"])
        if p["label"] == stop["label"]:
            raise KeyboardInterrupt
        return {"value": pcfg.v.a}

    with pytest.raises(KeyboardInterrupt):
        run_grid(cfg, spec, "s", point, out, ["point", "value"])
    st = read_status(out)
    assert {k: v["status"] for k, v in st["points"].items()} == {"x": "done", "y": "failed", "z": "pending"}
    assert st["points"]["y"]["error"] == "interrupted (KeyboardInterrupt)"
    calls.clear()
    stop["label"] = None
    assert [r["value"] for r in run_grid(cfg, spec, "s", point, out, ["point", "value"])] == [1, 2, 3]
    assert calls == ["y", "z"]


def _unattended(tmp_path, party_body: str):
    """A folder with scripts/sweep_unattended.sh and a stand-in ``.venv/bin/party`` (bash body
    ``party_body``, where ``{calls}`` is a file it may append to); returns that file's path."""
    import shutil
    import sys
    from pathlib import Path
    repo = Path(__file__).resolve().parents[1]
    (tmp_path / "scripts").mkdir()
    shutil.copy(repo / "scripts/sweep_unattended.sh", tmp_path / "scripts")
    (tmp_path / "params.yaml").write_text("generator: {ablation: {out_dir: data/ablations}}\n")
    bin_ = tmp_path / ".venv/bin"
    bin_.mkdir(parents=True)
    (bin_ / "python").symlink_to(sys.executable)
    calls = tmp_path / "calls"
    (bin_ / "party").write_text("#!/usr/bin/env bash\n" + party_body.replace("{calls}", str(calls)))
    (bin_ / "party").chmod(0o755)
    return calls


def test_sweep_unattended_starts_n_workers_and_exits_nonzero_when_one_fails(tmp_path):
    """scripts/sweep_unattended.sh with PARTY_SWEEP_WORKERS=2, against a stand-in ``party``."""
    import os
    import subprocess
    calls = _unattended(tmp_path, 'echo "$OMP_NUM_THREADS $*" >> {calls}\n[[ $1 == sweep-status ]] && exit 0\n'
                                  '[[ $(grep -c gen_ablation {calls}) == 2 ]] && exit 3\nexit 0\n')
    env = {**os.environ, "PARTY_SWEEP_WORKERS": "2"}
    r = subprocess.run(["bash", "scripts/sweep_unattended.sh", "gen_ablation", "gen_tab5", "a=1"], cwd=tmp_path,
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 3, r.stderr
    lines = calls.read_text().splitlines()
    threads = max(1, len(os.sched_getaffinity(0)) // 2)      # what nproc counts
    assert lines[:2] == [f"{threads} gen_ablation generator.ablation.sweep=gen_tab5 a=1"] * 2
    assert lines[2].endswith("sweep-status data/ablations/gen_tab5")
    log = (tmp_path / "logs/gen_tab5.log").read_text()
    assert "gen_tab5: start" in log and "gen_tab5: exit 3" in log


def test_sweep_unattended_queues_a_second_grid_until_the_first_ends(tmp_path):
    """Two grids started at once on one machine run one after the other (logs/.sweeps.lock), so
    they do not split the cores between 2 x N workers; PARTY_SWEEP_OVERLAP=1 runs them side by side."""
    import os
    import subprocess
    import time
    calls = _unattended(tmp_path, '[[ $1 == sweep-status ]] && exit 0\n'
                                  'echo "start $2 $(date +%s.%N)" >> {calls}\nsleep 1.5\n'
                                  'echo "end $2 $(date +%s.%N)" >> {calls}\n')

    def both(extra: dict) -> dict:
        calls.unlink(missing_ok=True)
        env = {**os.environ, "PARTY_SWEEP_WORKERS": "1", **extra}
        a = subprocess.Popen(["bash", "scripts/sweep_unattended.sh", "gen_ablation", "ga"], cwd=tmp_path, env=env)
        time.sleep(0.5)
        b = subprocess.Popen(["bash", "scripts/sweep_unattended.sh", "gen_ablation", "gb"], cwd=tmp_path, env=env)
        assert a.wait(timeout=60) == 0 and b.wait(timeout=60) == 0
        return {(w, g.split("=")[1]): float(t) for w, g, t in (ln.split() for ln in calls.read_text().splitlines())}

    t = both({})
    assert t["start", "gb"] >= t["end", "ga"]
    assert "gb: waiting for another grid to finish" in (tmp_path / "logs/gb.log").read_text()
    t = both({"PARTY_SWEEP_OVERLAP": "1"})
    assert t["start", "gb"] < t["end", "ga"]


def test_a_point_whose_training_is_held_is_put_back_and_taken_again(tmp_path, monkeypatch):
    """``Busy`` (another process trains the same model): the point goes back to pending with what it
    waits for, the worker runs the other points, then takes it again; nothing is marked failed."""
    import party.sweep
    from party.lifecycle import Busy
    monkeypatch.setattr(party.sweep, "BUSY_RETRY_S", 0.01)
    spec, cfg, out = _setup(tmp_path)
    calls, seen = [], {}

    def point(pcfg, p, run):
        calls.append(p["label"])
        if calls.count("y") == 1 and p["label"] == "y":
            raise Busy("data/checkpoints/generator/party/abc: a training run with the same settings is running")
        if p["label"] == "z":
            seen.update(read_status(out)["points"]["y"])
        return {"value": pcfg.v.a}
    rows = run_grid(cfg, spec, "s", point, out, ["point", "value"])
    assert calls == ["x", "y", "z", "y"]
    assert seen["status"] == "pending" and "generator/party/abc" in seen["waiting"]
    assert [r["value"] for r in rows] == [1, 2, 3]
    assert {k: v["status"] for k, v in read_status(out)["points"].items()} == dict.fromkeys("xyz", "done")


def test_two_workers_on_points_of_one_training_wait_for_it_instead_of_failing(tmp_path, monkeypatch):
    """Two points that share one resume folder (g1 / g2 of one model), two workers: one trains, the
    other's point waits and then runs; never both in the folder at once, and no point fails."""
    import multiprocessing as mp
    import time

    import party.sweep
    from party.training import hold_resume_dir
    for var in ("RANK", "LOCAL_RANK", "SLURM_PROCID"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(party.sweep, "BUSY_RETRY_S", 0.1)
    grid = tmp_path / "g.yaml"
    grid.write_text("name: g\naxes:\n  guidance: {g1: [v.a=1], g2: [v.a=2]}\n")
    spec, cfg, out = load_sweep(str(grid)), OmegaConf.create({"tracking": {"enabled": False}, "v": {"a": 0}}), tmp_path / "out"
    log_path = tmp_path / "calls.log"

    def point(pcfg, p, run):
        with hold_resume_dir(tmp_path / "train"):
            with open(log_path, "a") as f:
                f.write(f"in {p['label']} {time.time()}\n")
            time.sleep(1.0)
            with open(log_path, "a") as f:
                f.write(f"out {p['label']} {time.time()}\n")
        return {"value": pcfg.v.a}
    ctx = mp.get_context("fork")
    workers = [ctx.Process(target=run_grid, args=(cfg, spec, "s", point, out, ["point", "value"])) for _ in range(2)]
    for w in workers:
        w.start()
        time.sleep(0.2)
    for w in workers:
        w.join(60)
    assert [w.exitcode for w in workers] == [0, 0]
    events = [line.split() for line in log_path.read_text().splitlines()]
    assert [e[0] for e in events] == ["in", "out", "in", "out"]                  # one at a time
    assert sorted(e[1] for e in events if e[0] == "in") == ["g1", "g2"]
    assert {k: v["status"] for k, v in read_status(out)["points"].items()} == {"g1": "done", "g2": "done"}


def test_gpu_budget_runs_one_worker_per_gpu_and_refuses_without_one(tmp_path):
    """scripts/gpu_budget.sh against stand-ins (setup, ``party``, torch's GPU count, seed_table.py):
    without a GPU it stops with a message naming the CPU grid; with two it composes trainer=gpu,
    reproduces the generators' inputs, starts gen_budget_gpu on two workers, each on its own GPU and
    one device, then writes the report."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path
    repo = Path(__file__).resolve().parents[1]
    calls = _unattended(tmp_path, 'echo "${CUDA_VISIBLE_DEVICES:-none} $*" >> {calls}\nexit 0\n')
    shutil.copy(repo / "scripts/gpu_budget.sh", tmp_path / "scripts")
    (tmp_path / "scripts/setup.sh").write_text("exit 0\n")
    (tmp_path / "scripts/seed_table.py").write_text(f"import sys\nopen({str(calls)!r}, 'a').write('seed_table ' + ' '.join(sys.argv[1:]) + '\\n')\n")
    py = tmp_path / ".venv/bin/python"
    py.unlink()
    py.write_text(f'#!/usr/bin/env bash\nif [[ "$*" == *device_count* ]]; then echo "$FAKE_GPUS"; exit 0; fi\nexec {sys.executable} "$@"\n')
    py.chmod(0o755)
    run = lambda gpus: subprocess.run(["bash", "scripts/gpu_budget.sh", "dataset=x"], cwd=tmp_path, capture_output=True,  # noqa: E731
                                      text=True, timeout=60, env={**os.environ, "FAKE_GPUS": gpus})
    r = run("0")
    assert r.returncode == 1 and "no CUDA GPU visible" in r.stderr and "gen_budget" in r.stderr
    assert not calls.exists()
    r = run("2")
    assert r.returncode == 0, r.stderr
    lines = calls.read_text().splitlines()
    assert lines[:2] == ["none params trainer=gpu dataset=x", "none repro -j 2 embed_texts extract_tokens train_evaluator"]
    workers = sorted(ln for ln in lines if "gen_ablation" in ln)
    assert workers == [f"{i} gen_ablation generator.ablation.sweep=gen_budget_gpu generator.ablation.replications=20 "
                       "trainer.devices=1 trainer.strategy=auto" for i in (0, 1)]
    assert lines[-1] == "seed_table --grid data/ablations/gen_budget_gpu --side"


def test_a_seeded_grid_with_a_curve_writes_its_report(tmp_path):
    """run_grid writes <out>/report.html for a grid with a seeds: entry: the seed table with the
    steps trained and the curve over the declared axis; a grid without one gets none."""
    grid = tmp_path / "g.yaml"
    grid.write_text("name: g\nseeds: {axis: seed, within: [budget], curve: budget}\naxes:\n"
                    "  budget: {b1: [v.steps=10], b3: [v.steps=30]}\n  seed: {s1: [v.s=1], s2: [v.s=2]}\n"
                    "  method: {a: [v.m=1], b: [v.m=2]}\n")
    cfg = OmegaConf.create({"tracking": {"enabled": False}, "v": {"steps": 0, "s": 0, "m": 0}})
    point = lambda pcfg, p, run: {"top1": 0.1 * pcfg.v.m + 0.001 * pcfg.v.steps + 0.01 * pcfg.v.s,  # noqa: E731
                                  "top1_ci95": 0.001, "steps": pcfg.v.steps}
    run_grid(cfg, load_sweep(str(grid)), "s", point, tmp_path / "curve", ["point", "top1", "top1_ci95", "steps"])
    page = (tmp_path / "curve" / "report.html").read_text()
    assert "Metrics against budget" in page and "data:image/png;base64," in page
    assert "<td>b3</td><td>b</td><td>s1, s2</td><td>30</td>" in page
    spec, cfg, out = _setup(tmp_path)
    run_grid(cfg, spec, "s", lambda pcfg, p, run: {"value": 1}, out, ["point", "value"])
    assert not (out / "report.html").exists()
