"""One MLflow tracking server for many jobs (scripts/mlflow_server.sh, docs/tracking.md): the script
starts, reports and stops it; party's stages, sweeps, registry, ``party.load`` and the review notebook
work against its ``http://`` URI as against the SQLite store; concurrent processes (and SLURM jobs,
where a cluster answers) log to it at once and lose nothing."""
from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from party import tracking

from helpers import (MlflowServer, free_port, server_env, start_mlflow_server,  # noqa: E402
                     stop_mlflow_server)

REPO = Path(__file__).resolve().parents[1]
# variables that would send a worker's runs elsewhere or make it a non-zero rank
@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A server started through the script on a free port in a tmp dir; stopped through it after."""
    srv = start_mlflow_server(tmp_path_factory.mktemp("server") / "srv")
    try:
        yield srv
    finally:
        stop_mlflow_server(srv)


def make_cfg(uri: str | None, experiment: str, **extra):
    return OmegaConf.create({**extra, "tracking": {
        "enabled": True, "experiment": experiment, "uri": uri, "dir": "mlruns-unused", "parent_run_id": None,
        "log_system_metrics": False, "log_model": False, "n_render_samples": 1}})


# one job: a run with params (its config), a metric over every step, a JSON and a binary artifact
_WORKER = textwrap.dedent("""
    import sys, tempfile
    from pathlib import Path
    from omegaconf import OmegaConf
    from party import tracking
    worker, steps, experiment = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    cfg = OmegaConf.create({"model": {"width": 8 * (int(worker) + 1)}, "tracking": {
        "enabled": True, "experiment": experiment, "uri": None, "dir": "mlruns-unused", "parent_run_id": None,
        "log_system_metrics": False, "log_model": False}})
    with tracking.start_run(cfg, "server_load", run_name=f"worker-{worker}", tags={"worker": worker}) as run:
        for step in range(steps):
            run.log_metrics({"loss": 1.0 / (step + 1), "worker": float(worker)}, step=step)
        run.log_json({"worker": worker, "steps": steps}, "out/result.json")
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / "blob.bin").write_bytes(bytes(range(256)) * (16 * (int(worker) + 1)))
            run.log_file(Path(d) / "blob.bin", "files")
    print(run.info.run_id)
""")


def _check_jobs(uri: str, experiment: str, n: int, steps: int, tmp: Path) -> list:
    """Every job's run FINISHED, its metric with every step, its artifacts downloadable through the server."""
    import mlflow

    client = mlflow.MlflowClient(uri)
    exps = [e for e in client.search_experiments() if e.name == experiment]
    assert len(exps) == 1, [e.name for e in exps]
    runs = client.search_runs([exps[0].experiment_id], max_results=100)
    assert sorted(r.data.tags["worker"] for r in runs) == [str(i) for i in range(n)]
    assert {r.info.status for r in runs} == {"FINISHED"}
    for r in runs:
        w = int(r.data.tags["worker"])
        assert r.info.artifact_uri.startswith("mlflow-artifacts:"), r.info.artifact_uri   # served, no shared path
        assert r.data.params["model.width"] == str(8 * (w + 1))
        hist = sorted(client.get_metric_history(r.info.run_id, "loss"), key=lambda m: m.step)
        assert [m.step for m in hist] == list(range(steps))
        assert [m.value for m in hist] == pytest.approx([1.0 / (s + 1) for s in range(steps)])
        dst = tmp / r.info.run_id
        dst.mkdir()
        local = Path(mlflow.artifacts.download_artifacts(run_id=r.info.run_id, tracking_uri=uri, dst_path=str(dst)))
        assert json.loads((local / "out" / "result.json").read_text()) == {"worker": str(w), "steps": steps}
        assert (local / "files" / "blob.bin").read_bytes() == bytes(range(256)) * (16 * (w + 1))
        assert "model:" in (local / "config.yaml").read_text()
    return runs


# ------------------------------------------------------------------------------------ the script

def test_script_status_a_second_start_and_a_taken_port(server, tmp_path):
    r = server.script("status")
    assert r.returncode == 0 and f"answering at {server.uri}" in r.stdout, r.stdout + r.stderr
    again = server.script("start")
    assert again.returncode == 0 and "already running" in again.stdout and server.uri in again.stdout
    other = server.script("start", PARTY_MLFLOW_DIR=str(tmp_path / "other"))
    assert other.returncode == 1 and "is taken by another process" in other.stderr, other.stdout + other.stderr
    bad = server.script("restart")
    assert bad.returncode == 2 and "usage:" in bad.stderr


def test_a_server_that_cannot_start_fails_with_its_log(tmp_path):
    """A database the server cannot open: `start` fails at once and shows the log's end."""
    d = tmp_path / "srv"
    d.mkdir()
    (d / "mlflow.db").write_text("not a database")
    srv = MlflowServer("", d, server_env(PARTY_MLFLOW_DIR=str(d), PARTY_MLFLOW_PORT=str(free_port())))
    r = srv.script("start")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "exited before answering" in r.stderr and f"last lines of {d}/server.log" in r.stderr
    assert not (d / "server.pid").exists()


# ------------------------------------------------------------------------ party against a server

def test_four_processes_log_to_one_server_at_once(server, tmp_path):
    """Four processes start runs (creating the experiment at the same time), log their config,
    30 metric steps one request each and artifacts: every run FINISHED, nothing lost."""
    steps, env = 30, server_env(MLFLOW_TRACKING_URI=server.uri)
    t0 = time.time()
    procs = [subprocess.Popen([sys.executable, "-c", _WORKER, str(i), str(steps), "four"], env=env, cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(4)]
    outs = [p.communicate(timeout=300) for p in procs]
    took = time.time() - t0
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    runs = _check_jobs(server.uri, "four", 4, steps, tmp_path)
    assert sorted(r.info.run_id for r in runs) == sorted(out.split()[-1] for out, _ in outs)
    assert not (tmp_path / "mlruns-unused").exists()      # nothing went to a local store
    print(f"4 concurrent processes x {steps} steps to {server.uri}: {took:.1f} s")


def test_a_sweep_nests_under_its_parent_and_the_review_notebook_reads_it(server, tmp_path):
    """``run_grid`` under a parent run with ``tracking.uri`` set to the server: the points' runs
    nest under the parent, its table is downloadable, and notebooks/review_runs.py groups them."""
    import mlflow

    from party.sweep import load_sweep, run_grid

    grid = tmp_path / "g.yaml"
    grid.write_text("name: g\naxes:\n  a: {x: [v.a=1], y: [v.a=2], z: [v.a=3]}\n")
    cfg = make_cfg(server.uri, "sweep", v={"a": 0})

    def point(pcfg, p, run):
        run.log_metrics({"value": pcfg.v.a * 10.0})
        return {"value": pcfg.v.a * 10}

    with tracking.start_run(cfg, "vq_ablation", run_name="grid-g") as parent:
        rows = run_grid(cfg, load_sweep(str(grid)), "vq_ablation", point, tmp_path / "out", ["point", "value"])
    assert [r["value"] for r in rows] == [10, 20, 30]
    assert "MLFLOW_TRACKING_URI" not in os.environ
    client = mlflow.MlflowClient(server.uri)
    pid = parent.info.run_id
    kids = client.search_runs([parent.info.experiment_id], f"tags.mlflow.parentRunId = '{pid}'")
    assert sorted(k.data.tags["party.sweep_point"] for k in kids) == ["x", "y", "z"]
    assert {k.info.status for k in kids} == {"FINISHED"} and client.get_run(pid).info.status == "FINISHED"
    assert {k.data.tags["party.sweep_point"]: k.data.metrics["value"] for k in kids} == {"x": 10, "y": 20, "z": 30}
    assert client.get_run(pid).data.metrics["y.value"] == 20
    table = mlflow.artifacts.download_artifacts(run_id=pid, artifact_path="table.md", tracking_uri=server.uri,
                                                dst_path=str(tmp_path / "dl"))
    assert Path(table).read_text() == (tmp_path / "out" / "table.md").read_text()
    r = subprocess.run([sys.executable, str(REPO / "notebooks" / "review_runs.py")], cwd=tmp_path, timeout=300,
                       env=server_env(MLFLOW_TRACKING_URI=server.uri, PARTY_EXPERIMENT="sweep", MPLBACKEND="Agg"),
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"parent {pid}: 3 child run(s)" in r.stdout and "sweep g: 3 point(s)" in r.stdout, r.stdout[-3000:]


def test_register_and_load_models_and_runs_uris_through_the_server(server, tmp_path):
    """``party register``'s ``register_model`` and ``party.api.fetch`` (``party.load``) against the server."""
    from party.api import fetch

    cfg = make_cfg(server.uri, "registry")
    pkg = tmp_path / "package"
    pkg.mkdir()
    (pkg / "weights.txt").write_text("w")
    with tracking.start_run(cfg, "register") as run:
        run.log_file(pkg, "package")
        v1 = tracking.register_model(run, "package", "party-server-test", tags={"party.method": "m"})
        v2 = tracking.register_model(run, "package", "party-server-test")
    assert (v1, v2) == ("1", "2")
    for uri in (f"models:/party-server-test/{v2}", f"runs:/{run.info.run_id}/package"):
        assert (fetch(uri, cfg) / "weights.txt").read_text() == "w", uri
    with pytest.raises(FileNotFoundError, match="cannot fetch it from the MLflow store"):
        fetch("models:/party-server-test/9", cfg)


_HOLDER = textwrap.dedent("""
    import os, signal, sys
    from omegaconf import OmegaConf
    from party import tracking
    cfg = OmegaConf.create({"tracking": {"enabled": True, "experiment": "orphans", "uri": None, "dir": "unused",
                                         "parent_run_id": None, "log_system_metrics": False, "log_model": False}})
    with tracking.start_run(cfg, "train_vqvae") as run:
        print(run.info.run_id, flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
""")


def test_a_killed_jobs_run_is_closed_by_the_next_start_on_its_host(server, tmp_path):
    """``kill -9`` leaves the run RUNNING on the server; the next stage start on the same host marks
    it KILLED (``close_orphans``). The SQLite-only maintenance (``close_orphans_once`` when a process
    opens a store, ``relocate_store``) does nothing for a server, without an error."""
    import mlflow

    p = subprocess.run([sys.executable, "-c", _HOLDER], env=server_env(MLFLOW_TRACKING_URI=server.uri), cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == -signal.SIGKILL, p.stderr[-2000:]
    dead = p.stdout.split()[0]
    client = mlflow.MlflowClient(server.uri)
    assert client.get_run(dead).info.status == "RUNNING"
    assert tracking.relocate_store(server.uri) == 0
    assert tracking.store.close_orphans_once(server.uri) == []
    with tracking.start_run(make_cfg(server.uri, "orphans"), "evaluate"):
        pass
    run = client.get_run(dead)
    assert run.info.status == "KILLED" and "marked KILLED when evaluate next started" in run.data.tags["party.error"]
    assert tracking.tracking_uri(make_cfg(server.uri, "orphans")) == server.uri


# -------------------------------------------------------------------------------- SLURM jobs

@pytest.mark.slow
def test_four_slurm_jobs_log_to_one_server(slurm_cluster, tmp_path):
    """The four workers as four ``sbatch --wrap`` jobs, each logging through ``$MLFLOW_TRACKING_URI``
    to a server bound to every interface (jobs on other nodes reach it by this node's name; the
    worker's code travels in the command, so only the venv and the project need to be shared)."""
    srv = start_mlflow_server(tmp_path / "srv", host="0.0.0.0")
    try:
        assert srv.uri.startswith("http://") and "0.0.0.0" not in srv.uri
        steps, code = 30, base64.b64encode(_WORKER.encode()).decode()
        env = server_env(MLFLOW_TRACKING_URI=srv.uri)
        jobs = []
        for i in range(4):
            cmd = f"{sys.executable} -c \"import base64; exec(base64.b64decode('{code}'))\" {i} {steps} slurm"
            r = subprocess.run(["sbatch", "--parsable", f"--job-name=party-mlflow-{i}", "--ntasks=1",
                                "--cpus-per-task=1", "--mem=1500M", "--time=15", f"--chdir={tmp_path}",
                                f"--output={tmp_path}/job-{i}.out", "--export=ALL", f"--wrap={cmd}"],
                               env=env, capture_output=True, text=True, timeout=60)
            assert r.returncode == 0, r.stderr
            jobs.append(r.stdout.strip().split(";")[0])
        t0, deadline = time.time(), time.time() + 900
        try:
            while True:   # no accounting (sacct) on every cluster: a job is done when squeue no longer lists it
                q = subprocess.run(["squeue", "-h", "-o", "%i", "-j", ",".join(jobs)], capture_output=True,
                                   text=True, timeout=30)
                if not q.stdout.split():
                    break
                assert time.time() < deadline, f"jobs {jobs} still queued or running after 900 s"
                time.sleep(2)
        finally:
            if time.time() >= deadline:
                subprocess.run(["scancel", *jobs], capture_output=True, timeout=30)
        took = time.time() - t0
        logs = "\n".join(f"== job {i}\n{p.read_text()[-1500:]}" for i in range(4)
                         if (p := tmp_path / f"job-{i}.out").exists())
        try:
            _check_jobs(srv.uri, "slurm", 4, steps, tmp_path)
        except AssertionError as e:
            raise AssertionError(f"{e}\njob logs:\n{logs}") from e
        print(f"4 SLURM jobs ({', '.join(jobs)}) x {steps} steps to {srv.uri}: {took:.1f} s from submission")
    finally:
        stop_mlflow_server(srv)
