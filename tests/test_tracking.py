"""party.tracking: the MLflow convention (SQLite store + artifacts on disk under mlruns/)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from party import tracking

REPO = Path(__file__).resolve().parents[1]


def make_cfg(store: Path, **tracking_kw):
    t = {"enabled": True, "experiment": "test", "uri": None, "dir": str(store),
         "parent_run_id": None, "log_system_metrics": False, "log_model": False,
         "n_render_samples": 1, "video": {"format": "gif", "max_frames": 8}}
    t.update(tracking_kw)
    return OmegaConf.create({
        "seed": 3,
        "vqvae": {"window": 64, "codebook": {"size": 512, "dim": 512}, "lr": 2e-4,
                  "note": "x" * 7000, "chains": [[0, 2, 5], [0, 1, 4]]},
        "parts": [{"name": "arms", "joints": [9, 13]}, {"name": "legs", "joints": [1, 2]}],
        "derived": "${vqvae.window}",
        "tracking": t,
    })


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """One SQLite store for the module (creating it and importing MLflow is the slow part)."""
    with pytest.MonkeyPatch.context() as mp:
        for var in ("MLFLOW_TRACKING_URI", "DVC_ROOT", "DVC_EXP_NAME", "RANK", "LOCAL_RANK",
                    "SLURM_PROCID", "NODE_RANK", "MLFLOW_RUN_ID"):
            mp.delenv(var, raising=False)
        yield tmp_path_factory.mktemp("tracking") / "mlruns"


def _runs(cfg, **kw):
    import mlflow
    return mlflow.search_runs(experiment_names=[cfg.tracking.experiment], **kw)


# ------------------------------------------------------------------ pure (no MLflow)

def test_tracking_uri_precedence(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.delenv("DVC_ROOT", raising=False)
    monkeypatch.chdir(tmp_path)
    cfg = make_cfg(Path("mlruns"))
    assert tracking.tracking_uri(cfg) == f"sqlite:///{tmp_path.resolve()}/mlruns/mlflow.db"
    assert tracking.artifact_location(tracking.tracking_uri(cfg)) == \
        (tmp_path.resolve() / "mlruns" / "artifacts").as_uri()
    # DVC sets DVC_ROOT to the parent repo, also for queued experiments in temp copies
    monkeypatch.setenv("DVC_ROOT", "/somewhere/repo")
    assert tracking.tracking_uri(cfg) == "sqlite:////somewhere/repo/mlruns/mlflow.db"
    cfg.tracking.uri = "http://127.0.0.1:5000"
    assert tracking.tracking_uri(cfg) == "http://127.0.0.1:5000"
    assert tracking.artifact_location("http://127.0.0.1:5000") is None
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:////elsewhere/x.db")
    assert tracking.tracking_uri(cfg) == "sqlite:////elsewhere/x.db"
    assert tracking.artifact_location("sqlite:////elsewhere/x.db") == "file:///elsewhere/artifacts"


def test_flatten_config_keys_lists_truncation(tmp_path):
    flat = tracking.flatten_config(make_cfg(tmp_path), max_value_len=100)
    assert flat["vqvae.window"] == "64"
    assert flat["vqvae.codebook.size"] == "512"
    assert flat["vqvae.lr"] == "0.0002"
    assert flat["derived"] == "64"                      # interpolations resolved
    assert json.loads(flat["vqvae.chains"]) == [[0, 2, 5], [0, 1, 4]]
    assert flat["parts.1.name"] == "legs" and json.loads(flat["parts.0.joints"]) == [9, 13]
    assert len(flat["vqvae.note"]) == 100 and flat["vqvae.note"].endswith("...")
    assert flat["tracking.uri"] == "None"
    assert tracking.flatten_config({"a b": {"c(d)": 1}}) == {"a b.c_d_": "1"}
    # unresolvable interpolations (e.g. ${hydra:...} outside Hydra) are logged as written
    bad = OmegaConf.create({"x": "${oops.missing}", "y": 1})
    assert tracking.flatten_config(bad) == {"x": "${oops.missing}", "y": "1"}


def test_disabled_runs_without_mlflow(tmp_path):
    cfg = make_cfg(tmp_path / "mlruns", enabled=False)
    code = textwrap.dedent(f"""
        import sys
        from omegaconf import OmegaConf
        from party import tracking
        cfg = OmegaConf.create({OmegaConf.to_container(cfg)!r})
        with tracking.start_run(cfg, "prepare") as run:
            assert run.info.run_id is None and not run.active
            run.log_metrics({{"a": 1.0}}); run.log_json({{"a": 1}}, "x.json"); run.log_params({{"p": 1}})
            tracking.log_metrics({{"a": 1.0}}); tracking.log_json({{"a": 1}}, "x.json")
            tracking.log_video(None, "v.gif")
            assert tracking.lightning_logger(cfg, run) is False
        assert "mlflow" not in sys.modules, "disabled tracking must not import mlflow"
        print("ok")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"
    assert not (tmp_path / "mlruns").exists()


# ------------------------------------------------------------------ with a SQLite store

def test_run_roundtrip(store, tmp_path):
    import mlflow

    cfg = make_cfg(store)
    extra = tmp_path / "report.txt"
    extra.write_text("hello")
    joints = np.zeros((6, 22, 3))
    joints[:, :, 1] = np.linspace(0, 1.7, 22)
    with tracking.start_run(cfg, "train_vqvae", run_name="rt", tags={"purpose": "test"}) as run:
        assert isinstance(run, mlflow.ActiveRun)
        run.log_metrics({"loss": 1.5}, step=0)
        tracking.log_metrics({"loss": 0.5}, step=1)
        tracking.log_json({"fid": 0.25}, "eval/metrics.json")
        tracking.log_file(extra, "reports")
        run.log_video(joints, "samples/rest.gif", title="stands still", max_frames=3)
        run_id = run.info.run_id
    df = _runs(cfg, filter_string="tags.purpose = 'test'")
    assert len(df) == 1
    row = df.iloc[0]
    assert row.run_id == run_id and row.status == "FINISHED"
    assert row["tags.party.stage"] == "train_vqvae" and row["tags.mlflow.runName"] == "rt"
    assert row["tags.party.git_commit"] and row["tags.party.git_dirty"] in ("true", "false", "unknown")
    assert row["params.vqvae.window"] == "64" and row["params.derived"] == "64"
    assert len(row["params.vqvae.note"]) <= tracking._mlflow_param_limit()
    assert row["metrics.loss"] == 0.5
    client = mlflow.MlflowClient()
    assert [m.value for m in client.get_metric_history(run_id, "loss")] == [1.5, 0.5]
    # artifacts live on disk next to the database
    exp = client.get_experiment_by_name("test")
    assert exp.artifact_location == (store / "artifacts").resolve().as_uri()
    art = store / "artifacts" / run_id / "artifacts"
    assert (store / "mlflow.db").is_file()
    assert json.loads((art / "eval" / "metrics.json").read_text()) == {"fid": 0.25}
    assert (art / "reports" / "report.txt").read_text() == "hello"
    assert (art / "samples" / "rest.gif").read_bytes()[:6] == b"GIF89a"
    logged = OmegaConf.load(art / "config.yaml")
    assert logged.vqvae.note == "x" * 7000 and logged.derived == 64  # full, resolved


def test_failed_run_is_marked(store):
    cfg = make_cfg(store)
    with pytest.raises(RuntimeError, match="boom"):
        with tracking.start_run(cfg, "evaluate", tags={"purpose": "fail"}):
            tracking.log_metrics({"x": 1.0})
            raise RuntimeError("boom")
    row = _runs(cfg, filter_string="tags.purpose = 'fail'").iloc[0]
    assert row.status == "FAILED" and row["metrics.x"] == 1.0
    assert tracking.active_run_id() is None


def test_nested_and_parent_runs(store):
    cfg = make_cfg(store)
    with tracking.start_run(cfg, "sweep", tags={"purpose": "nest"}) as parent:
        with tracking.start_run(cfg, "train_vqvae", nested=True, tags={"purpose": "nest"}) as child:
            assert tracking.active_run_id() == child.info.run_id
        assert tracking.active_run_id() == parent.info.run_id
    # a later process joins the sweep through tracking.parent_run_id (e.g. dvc exp -S)
    cfg2 = make_cfg(store, parent_run_id=parent.info.run_id)
    with tracking.start_run(cfg2, "evaluate", tags={"purpose": "nest"}) as late:
        # the configured parent is for the top-level run; runs nested inside nest under it
        with tracking.start_run(cfg2, "render", nested=True, tags={"purpose": "nest"}) as inner:
            pass
    df = _runs(cfg, filter_string="tags.purpose = 'nest'").set_index("run_id")
    assert df.loc[child.info.run_id, "tags.mlflow.parentRunId"] == parent.info.run_id
    assert df.loc[late.info.run_id, "tags.mlflow.parentRunId"] == parent.info.run_id
    assert df.loc[inner.info.run_id, "tags.mlflow.parentRunId"] == late.info.run_id
    assert df.loc[parent.info.run_id].isna()["tags.mlflow.parentRunId"]


def test_non_zero_rank_logs_nothing(store, monkeypatch):
    cfg = make_cfg(store)
    monkeypatch.setenv("LOCAL_RANK", "1")
    with tracking.start_run(cfg, "train_vqvae", tags={"purpose": "rank1"}) as run:
        assert run.info.run_id is None
        tracking.log_metrics({"x": 1.0})
        assert tracking.lightning_logger(cfg, run) is False
    monkeypatch.delenv("LOCAL_RANK")
    assert len(_runs(cfg, filter_string="tags.purpose = 'rank1'")) == 0


def test_lightning_logger_bound_to_run(store):
    pytest.importorskip("lightning")
    cfg = make_cfg(store)
    with tracking.start_run(cfg, "train_vqvae", tags={"purpose": "pl"}) as run:
        logger = tracking.lightning_logger(cfg, run)
        assert logger.run_id == run.info.run_id
        logger.log_metrics({"train/loss": 2.0}, step=3)
        logger.log_hyperparams({"model": {"width": 8}})
        logger.finalize("success")          # the stock logger would end the run here
        assert tracking.active_run_id() == run.info.run_id
        tracking.log_metrics({"after_fit": 1.0})
    row = _runs(cfg, filter_string="tags.purpose = 'pl'").iloc[0]
    assert row["metrics.train/loss"] == 2.0 and row["metrics.after_fit"] == 1.0
    assert row["params.model/width"] == "8" and row.status == "FINISHED"


_WORKER = textwrap.dedent("""
    import sys
    from omegaconf import OmegaConf
    from party import tracking
    cfg = OmegaConf.create({"tracking": {"enabled": True, "experiment": "conc", "dir": sys.argv[1], "uri": None,
                                         "parent_run_id": None, "log_system_metrics": False, "log_model": False},
                            "worker": int(sys.argv[2])})
    with tracking.start_run(cfg, "worker", tags={"worker": sys.argv[2]}) as run:
        for step in range(40):
            tracking.log_metrics({"m": float(step), "w": float(sys.argv[2])}, step=step)
        tracking.log_json({"worker": sys.argv[2]}, "w.json")
    print(run.info.run_id)
""")


def test_concurrent_processes_share_a_fresh_store(tmp_path):
    """Two processes create the store and the experiment and log at the same time."""
    import mlflow

    d = tmp_path / "mlruns"
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "DVC_ROOT")}
    procs = [subprocess.Popen([sys.executable, "-c", _WORKER, str(d), str(i)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=180) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
    client = mlflow.MlflowClient(f"sqlite:///{d}/mlflow.db")
    exps = [e for e in client.search_experiments() if e.name == "conc"]
    assert len(exps) == 1
    runs = client.search_runs([exps[0].experiment_id])
    assert len(runs) == 2 and all(r.info.status == "FINISHED" for r in runs)
    for r in runs:
        assert len(client.get_metric_history(r.info.run_id, "m")) == 40
        art = d / "artifacts" / r.info.run_id / "artifacts" / "w.json"
        assert json.loads(art.read_text()) == {"worker": r.data.tags["worker"]}


def test_review_notebook_runs(store, tmp_path):
    """notebooks/review_runs.py (jupytext percent) runs as a script against a store."""
    cfg = make_cfg(store)
    with tracking.start_run(cfg, "evaluate", tags={"purpose": "nb"}) as run:
        tracking.log_metrics({"fid": 0.3})
        joints = np.zeros((4, 22, 3))
        joints[:, :, 1] = np.linspace(0, 1.7, 22)
        tracking.log_video(joints, "samples/a.gif")
    env = os.environ | {"MLFLOW_TRACKING_URI": tracking.tracking_uri(cfg),
                        "PARTY_EXPERIMENT": "test", "MPLBACKEND": "Agg"}
    r = subprocess.run([sys.executable, str(REPO / "notebooks" / "review_runs.py")], env=env,
                       capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert run.info.run_id in r.stdout and "samples/a.gif" in r.stdout


def test_review_notebook_executes_as_a_notebook_with_embedded_motion(store, tmp_path):
    """Executed by a Jupyter kernel (nbclient, as `pytest --nbmake` does): the GIF is embedded
    as HTML (an exported notebook shows it), runs show their DVC experiment, and RUNNING or
    FAILED runs are hidden unless asked for."""
    import jupytext
    from nbclient import NotebookClient

    cfg = make_cfg(store, experiment="nb")
    with tracking.start_run(cfg, "evaluate") as done:
        joints = np.zeros((4, 22, 3))
        joints[:, :, 1] = np.linspace(0, 1.7, 22)
        tracking.log_video(joints, "samples/a.gif")
    with pytest.raises(RuntimeError):
        with tracking.start_run(cfg, "evaluate") as failed:
            raise RuntimeError("boom")
    nb = jupytext.read(REPO / "notebooks" / "review_runs.py")
    nb.cells.insert(2, jupytext.reads(f"# %%\ntracking_uri = {tracking.tracking_uri(cfg)!r}\n"
                                      "experiment = 'nb'\n", fmt="py:percent").cells[0])
    NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    html = "".join(o.get("data", {}).get("text/html", "") for o in outputs)
    assert 'src="data:image/gif;base64,' in html and "IPython.core.display.Image" not in html
    assert done.info.run_id in html and failed.info.run_id not in html
    assert "dvc_exp_name" in html


def test_runs_do_not_export_the_store_to_later_runs(store, tmp_path):
    """mlflow.set_tracking_uri exports $MLFLOW_TRACKING_URI; a second stage with another
    store (in this process or a child) must not log into the first one."""
    import os
    first = make_cfg(store)
    with tracking.start_run(first, "prepare"):
        pass
    assert "MLFLOW_TRACKING_URI" not in os.environ
    other = make_cfg(tmp_path / "other")
    assert tracking.tracking_uri(other) != tracking.tracking_uri(first)
    with tracking.start_run(other, "evaluate", tags={"purpose": "second-store"}):
        pass
    assert (tmp_path / "other" / "mlflow.db").exists()


_HOLDER = textwrap.dedent("""
    import os, signal, sys, time
    from omegaconf import OmegaConf
    from party import tracking
    cfg = OmegaConf.create({"tracking": {"enabled": True, "experiment": "orphans", "dir": sys.argv[1],
                                         "uri": None, "parent_run_id": None, "log_system_metrics": False,
                                         "log_model": False}})
    with tracking.terminate_on_sigterm(), tracking.start_run(cfg, sys.argv[2]) as run:
        print(run.info.run_id, flush=True)
        if sys.argv[3] == "kill9":
            os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(120)
""")


def _holder(d, stage, how):
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "DVC_ROOT")}
    p = subprocess.Popen([sys.executable, "-c", _HOLDER, str(d), stage, how], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return p, p.stdout.readline().strip()


def test_runs_of_killed_processes_are_not_left_running(tmp_path):
    """kill -9 leaves a run RUNNING; the next start of any stage marks it KILLED (whatever
    stage or experiment it was), and leaves a live process's run alone. SIGTERM ends the run
    KILLED at once, with the signal as the error."""
    from mlflow.tracking import MlflowClient

    d = tmp_path / "mlruns"
    dead, dead_id = _holder(d, "train_vqvae", "kill9")
    dead.wait(60)
    client = MlflowClient(f"sqlite:///{d}/mlflow.db")
    assert client.get_run(dead_id).info.status == "RUNNING"            # what kill -9 leaves
    other, other_id = _holder(d, "embed_texts", "kill9")               # another stage's start closes it
    other.wait(60)
    assert client.get_run(dead_id).info.status == "KILLED"
    assert "when embed_texts next started" in client.get_run(dead_id).data.tags["party.error"]
    assert client.get_run(other_id).info.status == "RUNNING"
    live, live_id = _holder(d, "train_vqvae", "sleep")                 # closes other_id itself
    client.set_terminated(other_id, "RUNNING")                         # so that this start does
    try:
        cfg = OmegaConf.create({"tracking": {"enabled": True, "experiment": "another", "dir": str(d),
                                             "uri": None, "parent_run_id": None,
                                             "log_system_metrics": False, "log_model": False}})
        with tracking.start_run(cfg, "evaluate"):                       # another stage, another experiment
            pass
        assert client.get_run(other_id).info.status == "KILLED"
        assert "ended without closing" in client.get_run(other_id).data.tags["party.error"]
        assert "when evaluate next started" in client.get_run(other_id).data.tags["party.error"]
        assert client.get_run(live_id).info.status == "RUNNING"        # its process is alive
        live.terminate()                                                # SIGTERM
        live.wait(60)
        assert client.get_run(live_id).info.status == "KILLED"
    finally:
        live.kill()


def test_a_moved_clone_logs_into_its_own_store(tmp_path):
    """Copy a project with its store elsewhere: runs opened there log artifacts under the copy,
    old runs' artifacts are read from the copy, and the original's folder is not touched."""
    import shutil

    from mlflow.tracking import MlflowClient

    a, b = tmp_path / "a", tmp_path / "b"
    cfg_a = make_cfg(a / "mlruns", experiment="moved")
    with tracking.start_run(cfg_a, "prepare") as run:
        tracking.log_json({"where": "a"}, "w.json")
    old_id = run.info.run_id
    shutil.copytree(a, b)
    before = sorted(str(p) for p in (a / "mlruns").rglob("*"))
    cfg_b = make_cfg(b / "mlruns", experiment="moved")
    with tracking.start_run(cfg_b, "evaluate") as run:
        tracking.log_json({"where": "b"}, "w.json")
    new_id = run.info.run_id
    assert (b / "mlruns" / "artifacts" / new_id / "artifacts" / "w.json").exists()
    assert sorted(str(p) for p in (a / "mlruns").rglob("*")) == before      # the original untouched
    client = MlflowClient(tracking.tracking_uri(cfg_b))
    old = client.get_run(old_id)
    assert old.info.artifact_uri.startswith((b / "mlruns").resolve().as_uri())
    local = client.download_artifacts(old_id, "w.json", str(tmp_path))
    assert json.loads(Path(local).read_text()) == {"where": "a"}
    assert tracking.relocate_store(tracking.tracking_uri(cfg_b)) == 0      # nothing left to move


def test_runs_tell_apart_dvc_experiment_git_changes_and_resumes(tmp_path, monkeypatch):
    """The DVC experiment in the run name; git_dirty false when only generated files differ,
    with the differing files listed; a resumed training linked to the run it continues."""
    from mlflow.tracking import MlflowClient

    repo = tmp_path / "repo"
    (repo / "src").mkdir(parents=True)
    for f in ("params.yaml", "dvc.lock", "src/a.py"):
        (repo / f).write_text("x\n")
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t"]
    subprocess.run([*git, "init", "-q"], cwd=repo, check=True)
    subprocess.run([*git, "add", "-A"], cwd=repo, check=True)
    subprocess.run([*git, "commit", "-qm", "x"], cwd=repo, check=True)
    monkeypatch.chdir(repo)
    for f in ("params.yaml", "dvc.lock"):
        (repo / f).write_text("y\n")
    state = tracking._git_state()
    assert state["party.git_dirty"] == "false" and state["party.git_changed"] == "dvc.lock, params.yaml"
    (repo / "src/a.py").write_text("z\n")
    assert tracking._git_state()["party.git_dirty"] == "true"

    cfg = make_cfg(tmp_path / "mlruns", experiment="apart")
    monkeypatch.setenv("DVC_EXP_NAME", "lr-high")
    with tracking.start_run(cfg, "train_vqvae", run_name="train_vqvae-arms") as first:
        first.set_tags({"party.resume_key": "k1"})
    monkeypatch.delenv("DVC_EXP_NAME")
    with tracking.start_run(cfg, "train_vqvae", run_name="train_vqvae-arms") as second:
        second.set_tags({"party.resume_key": "k1"})
        assert tracking.link_resumed(second, "k1") == first.info.run_id
    with tracking.start_run(cfg, "train_vqvae", run_name="train_vqvae-arms") as third:
        third.set_tags({"party.resume_key": "k1"})
        assert tracking.link_resumed(third, "k1") == second.info.run_id
    client = MlflowClient(tracking.tracking_uri(cfg))
    assert client.get_run(first.info.run_id).info.run_name == "train_vqvae-arms@lr-high"
    assert client.get_run(second.info.run_id).info.run_name == "train_vqvae-arms"
    for r in (second, third):
        assert client.get_run(r.info.run_id).data.tags["mlflow.parentRunId"] == first.info.run_id
    assert client.get_run(third.info.run_id).data.tags["party.resumed_from"] == second.info.run_id


def test_experiments_open_in_the_model_training_view(store):
    from mlflow.tracking import MlflowClient
    cfg = make_cfg(store, experiment="kind")
    with tracking.start_run(cfg, "prepare"):
        pass
    exp = MlflowClient(tracking.tracking_uri(cfg)).get_experiment_by_name("kind")
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"


_FORKED = textwrap.dedent("""
    import multiprocessing as mp, time
    from party import tracking
    if __name__ == "__main__":
        with tracking.terminate_on_sigterm():
            worker = mp.get_context("fork").Process(target=time.sleep, args=(60,))
            worker.start()
            time.sleep(1)
            worker.terminate()                   # SIGTERM, as a pool's terminate() sends its workers
            worker.join()
            print("exit code", worker.exitcode, flush=True)
""")


def test_sigterm_in_a_forked_worker_ends_it_quietly():
    """A worker forked during a stage inherits the SIGTERM handler; terminating it must not raise
    ``Terminated`` in it (a traceback per worker, exit code 1): it ends as it would without it."""
    res = subprocess.run([sys.executable, "-c", _FORKED], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "exit code -15" in res.stdout, res.stdout + res.stderr
    assert "Traceback" not in res.stderr, res.stderr
