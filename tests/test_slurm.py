"""SLURM: resources from Hydra's launcher config, a grid as a job array with one parent run, DDP
through srun. The fast tests need no cluster; the slow ones use the cluster of
``scripts/slurm_local.sh`` (``.ci/run`` starts it) and skip with the reason where none answers."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from party import slurm, tracking
from party.cli import main
from party.sweep import load_sweep, read_status, record_submission, run_grid

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


# --------------------------------------------------------------------------- no cluster needed

def test_launcher_config_is_hydras_with_overrides():
    res = slurm.launcher_config("slurm_local", ["hydra.launcher.mem_gb=3"], ROOT / "conf")
    base = slurm.launcher_config("slurm", [], ROOT / "conf")
    assert res["mem_gb"] == 3 and res["gpus_per_node"] == 0 and res["cpus_per_task"] == 1
    assert res["array_parallelism"] == base["array_parallelism"] == 8       # inherited from slurm.yaml
    assert base["gpus_per_node"] == 1 and "signal_delay_s" in base          # the submitit plugin's keys
    with pytest.raises(FileNotFoundError, match="hydra/launcher/nope.yaml"):
        slurm.launcher_config("nope", [], ROOT / "conf")
    lines = slurm.sbatch_lines(res, job_name="j", output="o", array="0,2%8", dependency="afterany:7")
    for want in ("--ntasks-per-node=1", "--mem=3G", "--signal=USR1@30", "--requeue", "--array=0,2%8",
                 "--dependency=afterany:7", "--time=60"):
        assert f"#SBATCH {want}" in lines
    assert not any("gpus" in x for x in lines)


def _tracked_cfg(tmp_path):
    return OmegaConf.create({"tracking": {"enabled": True, "experiment": "arr", "dir": str(tmp_path / "mlruns"),
                                          "uri": None, "parent_run_id": None, "log_system_metrics": False,
                                          "log_model": False}, "v": {"a": 0}})


def _grid(tmp_path):
    grid = tmp_path / "g.yaml"
    grid.write_text("name: g\naxes:\n  a: {x: [v.a=1], y: [v.a=2], z: [v.a=3]}\n")
    return load_sweep(str(grid))


def test_array_tasks_run_one_point_each_under_one_parent_and_collect_the_table(tmp_path, monkeypatch):
    """What each task of a submitted grid does (``$PARTY_SWEEP_TASK``), in-process: a point task runs
    its point only, nested under the parent created at submission, opening no stage run of its own;
    the collecting task writes the table into the parent and ends it FINISHED, or FAILED naming the
    points that did not finish."""
    import mlflow

    from party.tracking.run import create_run
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    cfg, spec, out = _tracked_cfg(tmp_path), _grid(tmp_path), tmp_path / "out"
    parent = create_run(cfg, "s", "s-g", {"party.sweep": "g"})
    record_submission(out, spec, {"array": "41", "collect": "42", "parent_run": parent,
                                  "points": {"x": "41_0", "y": "41_1", "z": "41_2"}})
    assert main(["sweep-status", str(out)]) == 0
    calls = []

    def point(pcfg, p, run):
        calls.append(p["label"])
        return {"value": pcfg.v.a * 10}

    def task(which, fn=point):
        monkeypatch.setenv(slurm.TASK_ENV, which)
        monkeypatch.setenv(slurm.PARENT_ENV, parent)
        with tracking.start_run(cfg, "s") as stage_run:
            assert (getattr(stage_run.info, "run_id", None) == parent) == (which == slurm.COLLECT)
            return run_grid(cfg, spec, "s", fn, out, ["point", "value", "status"])

    task("2")
    task("0")
    assert calls == ["z", "x"]
    assert {k: v["status"] for k, v in read_status(out)["points"].items()} == {"x": "done", "y": "queued", "z": "done"}
    with pytest.raises(RuntimeError, match=r"1 of 3 points did not finish \(y queued\)"):
        task(slurm.COLLECT)
    client = mlflow.MlflowClient(tracking.tracking_uri(cfg))
    assert client.get_run(parent).info.status == "FAILED"
    task("1")                                          # the point's job again: the grid is complete
    rows = task(slurm.COLLECT)
    assert calls == ["z", "x", "y"] and [r["value"] for r in rows] == [10, 20, 30]
    run = client.get_run(parent)
    assert run.info.status == "FINISHED" and run.data.metrics["y.value"] == 20
    kids = client.search_runs([run.info.experiment_id], f"tags.mlflow.parentRunId = '{parent}'")
    assert sorted(k.data.tags["party.sweep_point"] for k in kids) == ["x", "y", "z"]
    assert all(k.info.status == "FINISHED" for k in kids)
    assert len(client.search_runs([run.info.experiment_id])) == 4          # no stage run of a point task
    names = {a.path for a in client.list_artifacts(parent)}
    assert {"table.md", "table.csv", "status.json", "sweep.yaml"} <= names
    monkeypatch.setenv(slurm.TASK_ENV, "9")
    with pytest.raises(ValueError, match="not a point of this grid"):
        run_grid(cfg, spec, "s", point, out, ["point"])


def test_a_parent_whose_slurm_job_is_gone_is_closed(tmp_path, monkeypatch):
    import mlflow

    from party.lifecycle import close_orphans
    from party.tracking.run import create_run, set_run_tags
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    cfg = _tracked_cfg(tmp_path)
    parent = create_run(cfg, "s", "s-g")
    set_run_tags(parent, {"party.slurm_job": "77"})
    client = mlflow.MlflowClient(tracking.tracking_uri(cfg))
    monkeypatch.setattr(slurm, "available", lambda: True)
    monkeypatch.setattr(slurm, "job_alive", lambda j: True)
    assert close_orphans(client, "s") == []
    monkeypatch.setattr(slurm, "job_alive", lambda j: j != "77")
    assert close_orphans(client, "s") == [parent]
    run = client.get_run(parent)
    assert run.info.status == "KILLED" and "SLURM job 77" in run.data.tags["party.error"]


def test_submit_dry_run_writes_an_array_and_a_table_job(tmp_path, monkeypatch):
    from party.config import write_params
    (tmp_path / "conf").symlink_to(ROOT / "conf")
    grid = tmp_path / "mini.yaml"
    grid.write_text("name: mini\nstream: holistic\naxes:\n  seed: {s1: [seed=1], s2: [seed=2]}\n")
    write_params(tmp_path / "params.yaml", ["experiment=tiny", f"vqvae.ablation.sweep={grid}",
                                            f"vqvae.ablation.out_dir={tmp_path / 'abl'}"], ROOT / "conf")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PARTY_PARAMS", str(tmp_path / "params.yaml"))
    out = slurm.submit("vq_ablation", ["hydra.launcher.array_parallelism=1"], "slurm_local", dry_run=True)
    points, table = out["scripts"]["party-vq_ablation-mini"], out["scripts"]["party-vq_ablation-mini-table"]
    assert "#SBATCH --array=0,1%1" in points and 'export PARTY_SWEEP_TASK="$SLURM_ARRAY_TASK_ID"' in points
    assert "srun --kill-on-bad-exit=1 " in points and "-m party.cli vq_ablation" in points
    assert "#SBATCH --dependency=afterany:" in table and "export PARTY_SWEEP_TASK=collect" in table
    assert f"export PARTY_PARAMS={tmp_path / 'params.yaml'}" in table
    one = slurm.submit("train_vqvae", ["vqvae.train.max_steps=3"], "slurm_local", dry_run=True)["scripts"]
    assert list(one) == ["party-train_vqvae"] and "party.cli train_vqvae vqvae.train.max_steps=3" in one[
        "party-train_vqvae"]
    assert main(["submit", "nope"]) == 2 and main(["submit", "--wait"]) == 2


# --------------------------------------------------------------------------- the local cluster

def _project(tmp_path, name, *overrides):
    from party.config import write_params
    proj = tmp_path / name
    proj.mkdir()
    (proj / "conf").symlink_to(ROOT / "conf")
    write_params(proj / "params.yaml", ["experiment=tiny", f"paths.prepared={tmp_path / 'prepared'}",
                                        f"tracking.dir={proj / 'mlruns'}", "progress=false",
                                        "tracking.n_render_samples=0", f"vqvae.resume_dir={proj / 'resume'}",
                                        f"vqvae.ablation.out_dir={proj / 'abl'}", *overrides], ROOT / "conf")
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "DVC_ROOT", "LOCAL_RANK")}
    env.update(PARTY_PARAMS=str(proj / "params.yaml"), PARTY_NO_RENDER="1", OMP_NUM_THREADS="1")
    return proj, env


def _party(proj, env, *args, timeout=900):
    r = subprocess.run([str(BIN / "party"), *args], cwd=proj, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, (f"party {' '.join(args)}: exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-5000:]}"
                               f"\n{_logs(proj, 4000) if (proj / 'logs' / 'slurm').is_dir() else ''}")
    return r


def _untimed(table_csv: Path) -> list[dict]:
    """A grid table's rows without its timing column (``train_s``: the seconds each point trained,
    which differ between any two runs)."""
    import csv
    return [{k: v for k, v in row.items() if k != "train_s"} for row in csv.DictReader(table_csv.open())]


def _logs(proj, tail: int | None = None) -> str:
    """The jobs' logs (each cut to its last ``tail`` characters)."""
    return "\n".join(f"== {p.name}\n{p.read_text()[-(tail or 0):]}" for p in sorted((proj / "logs" / "slurm").glob("*.out")))


@pytest.mark.slow
def test_a_grid_as_a_slurm_array_equals_the_local_run(slurm_cluster, tmp_path):
    """A two-point grid (two seeds of the tiny holistic tokenizer): run locally into the SQLite store,
    and submitted as an array (one task per point) plus the table job, every job logging to one
    tracking server (scripts/mlflow_server.sh). The tables agree; the points' runs nest under one
    parent run that ends FINISHED; ``party sweep-status`` names the jobs."""
    import mlflow

    from helpers import start_mlflow_server, stop_mlflow_server
    grid = tmp_path / "seeds.yaml"
    grid.write_text("name: seeds\nstream: holistic\nfixed: [vqvae.train.max_steps=4]\n"
                    "axes:\n  seed: {s1: [seed=1], s2: [seed=2]}\n")
    local, lenv = _project(tmp_path, "local", f"vqvae.ablation.sweep={grid}")
    _party(local, lenv, "prepare")
    _party(local, lenv, "vq_ablation")
    arr, aenv = _project(tmp_path, "array", f"vqvae.ablation.sweep={grid}")
    srv = start_mlflow_server(tmp_path / "server")
    try:
        aenv["MLFLOW_TRACKING_URI"] = srv.uri
        r = _party(arr, aenv, "submit", "vq_ablation", "--launcher", "slurm_local", "--wait")
        assert "array " in r.stdout and "ended:" in r.stdout, r.stdout
        status = read_status(arr / "abl" / "seeds")
        sl = status["slurm"]
        assert {p: e["status"] for p, e in status["points"].items()} == {"s1": "done", "s2": "done"}, _logs(arr, 3000)
        assert [e["worker"]["slurm_job"] for e in status["points"].values()] == [f"{sl['array']}_0",
                                                                                  f"{sl['array']}_1"]
        want = _untimed(local / "abl" / "seeds" / "table.csv")
        assert _untimed(arr / "abl" / "seeds" / "table.csv") == want
        st = _party(arr, aenv, "sweep-status", str(arr / "abl" / "seeds")).stdout
        assert f"array {sl['array']}" in st and f"job {sl['array']}_1 COMPLETED" in st, st
        client = mlflow.MlflowClient(srv.uri)
        parent = client.get_run(sl["parent_run"])
        assert parent.info.status == "FINISHED" and parent.data.tags["party.slurm_job"] == sl["collect"]
        kids = client.search_runs([parent.info.experiment_id], f"tags.mlflow.parentRunId = '{parent.info.run_id}'")
        assert sorted(k.data.tags["party.sweep_point"] for k in kids) == ["s1", "s2"]
        assert all(k.info.status == "FINISHED" for k in kids)
        assert not client.search_runs([parent.info.experiment_id], "attributes.status = 'RUNNING'")
        table = client.download_artifacts(parent.info.run_id, "table.csv", str(tmp_path))
        assert _untimed(Path(table)) == want
        assert not (arr / "mlruns" / "mlflow.db").exists()          # nothing went to a local store
        # submitted again: nothing to run, only the table job
        r = _party(arr, aenv, "submit", "vq_ablation", "--launcher", "slurm_local", "--wait")
        assert "every point done" in r.stdout and _untimed(arr / "abl" / "seeds" / "table.csv") == want
    finally:
        stop_mlflow_server(srv)


@pytest.mark.slow
def test_ddp_through_srun_equals_one_process(slurm_cluster, tmp_path):
    """tests/generator/ddp_equivalence.py as one SLURM job of two tasks (srun; Lightning's SLURM
    environment gives the ranks) against one process: the weights agree."""
    script = ROOT / "tests" / "generator" / "ddp_equivalence.py"
    res = slurm.launcher_config("slurm_local", ["hydra.launcher.tasks_per_node=2"], ROOT / "conf")
    (tmp_path / "two").mkdir()
    job = slurm.sbatch(slurm.batch_script([sys.executable, str(script), "2", "8", str(tmp_path / "two" / "w.pt")],
                                          res, job_name="party-ddp", output=str(tmp_path / "ddp.out"), cwd=tmp_path,
                                          env={"PYTHONUNBUFFERED": "1"}), tmp_path, "ddp")
    (tmp_path / "one").mkdir()
    env = os.environ | {"PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    for k in [k for k in env if k.startswith("SLURM_") and k != "SLURM_CONF"]:
        env.pop(k)
    r = subprocess.run([sys.executable, str(script), "1", "8", str(tmp_path / "one" / "w.pt")], env=env,
                       capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    states = slurm.wait([job], timeout=600)
    log = (tmp_path / "ddp.out").read_text()
    assert states[job] == "COMPLETED", log[-4000:]
    assert "distributed_backend=gloo" in log and "All distributed processes registered. Starting with 2 processes" in log
    one = torch.load(tmp_path / "one" / "w.pt", weights_only=True)
    two = torch.load(tmp_path / "two" / "w.pt", weights_only=True)
    diff = max((two[k] - one[k]).abs().max().item() for k in one)
    print(f"DDP through srun vs one process: max |Δw| = {diff:.3g}")
    for k in one:
        torch.testing.assert_close(two[k], one[k], rtol=1e-4, atol=1e-5, msg=k)


@pytest.mark.slow
def test_a_training_stage_runs_ddp_as_one_slurm_job(slurm_cluster, tmp_path):
    """``party submit train_evaluator`` with two tasks and trainer.devices=2: one job, two ranks,
    one MLflow run (rank zero's), the outputs written once; then the same with ``--multirun
    hydra/launcher=slurm_local`` (Hydra's submitit launcher)."""
    import mlflow

    proj, env = _project(tmp_path, "ddp")
    _party(proj, env, "prepare")
    r = _party(proj, env, "submit", "train_evaluator", "--launcher", "slurm_local", "--wait",
               "hydra.launcher.tasks_per_node=2", "trainer.accelerator=cpu", "trainer.devices=2",
               "trainer.strategy=ddp", "evaluator.train.max_steps=2", "evaluator.movement_pretrain.max_steps=2",
               f"evaluator.out_dir={proj / 'ev'}")
    log = _logs(proj)
    assert "COMPLETED" in r.stdout, r.stdout + log[-5000:]
    assert log.count("Starting with 2 processes") == 2 and log.count("GLOBAL_RANK: 1, MEMBER: 2/2") >= 1
    out = proj / "ev" / "holistic"
    assert (out / "finest.tar").exists() and (out / "metrics.json").exists()
    client = mlflow.MlflowClient(f"sqlite:///{proj / 'mlruns' / 'mlflow.db'}")
    exp = client.get_experiment_by_name(OmegaConf.load(proj / "params.yaml").tracking.experiment)
    runs = client.search_runs([exp.experiment_id], "tags.`party.stage` = 'train_evaluator'")
    assert [x.info.status for x in runs] == ["FINISHED"], [x.info.status for x in runs]
    json.loads((out / "metrics.json").read_text())
    # the same through Hydra's submitit launcher (it waits on the job itself)
    r = _party(proj, env, "train_evaluator", "--multirun", "hydra/launcher=slurm_local",
               "hydra.launcher.tasks_per_node=2", "trainer.accelerator=cpu", "trainer.devices=2",
               "trainer.strategy=ddp", "evaluator.train.max_steps=3", "evaluator.movement_pretrain.max_steps=2",
               f"evaluator.out_dir={proj / 'ev2'}")
    logs = "".join(p.read_text() for p in (proj / "multirun").rglob("*_log.out"))
    assert "global_rank=1(2)" in logs and "Starting with 2 processes" in logs, r.stdout[-3000:] + logs[-3000:]
    assert (proj / "ev2" / "holistic" / "finest.tar").exists()
    runs = client.search_runs([exp.experiment_id], "tags.`party.stage` = 'train_evaluator'")
    assert [x.info.status for x in runs] == ["FINISHED", "FINISHED"]
    shutil.rmtree(proj / "resume", ignore_errors=True)


def test_a_point_put_back_as_busy_ends_its_run_killed_with_the_reason(tmp_path, monkeypatch):
    """The attempt that found the training held is not a failure: its run is KILLED, tag party.busy."""
    import mlflow

    import party.sweep
    from party.lifecycle import Busy
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.setattr(party.sweep, "BUSY_RETRY_S", 0.01)
    cfg, spec, tries = _tracked_cfg(tmp_path), _grid(tmp_path), []

    def point(pcfg, p, run):
        tries.append(p["label"])
        if tries == ["x"]:
            raise Busy("ckpt/abc: a training run with the same settings is running there")
        return {"value": 1}
    with tracking.start_run(cfg, "s", run_name="grid"):
        run_grid(cfg, spec, "s", point, tmp_path / "out", ["point", "value"])
    client = mlflow.MlflowClient(tracking.tracking_uri(cfg))
    runs = client.search_runs([client.get_experiment_by_name("arr").experiment_id])
    x = sorted((r for r in runs if r.data.tags.get("party.sweep_point") == "x"), key=lambda r: r.info.start_time)
    assert [r.info.status for r in x] == ["KILLED", "FINISHED"]
    assert "ckpt/abc" in x[0].data.tags["party.busy"]
