"""A run whose process was killed (``kill -9``, the OOM killer) is marked KILLED the next time
anything opens the store, not only when a stage next starts: ``party.load`` of a ``runs:/`` URI,
the notebooks (``tracking.tracking_uri``), ``scripts/mlflow_ui.sh`` (``tracking.relocate_store``)."""
import os
import signal
import socket
import subprocess
import sys
import textwrap

from omegaconf import OmegaConf

_KILLED = textwrap.dedent("""
    import os, signal, sys
    from omegaconf import OmegaConf
    from party import tracking
    cfg = OmegaConf.create({"tracking": {"enabled": True, "experiment": "night", "dir": sys.argv[1], "uri": None,
                                         "parent_run_id": None, "log_system_metrics": False, "log_model": False}})
    with tracking.start_run(cfg, "train_generator") as run:
        print(run.info.run_id, flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
""")


def _cfg(d):
    return OmegaConf.create({"tracking": {"enabled": True, "experiment": "night", "dir": str(d), "uri": None,
                                          "parent_run_id": None, "log_system_metrics": False, "log_model": False}})


def _client(d):
    from mlflow.tracking import MlflowClient
    return MlflowClient(f"sqlite:///{d}/mlflow.db")            # MLflow's own: opens nothing of party's


def test_a_killed_stage_run_ends_when_the_store_is_next_opened(tmp_path):
    """A stage run killed with kill -9 stays RUNNING; the next process that opens the store the
    way the notebooks and ``party.load`` do (``tracking_uri``) marks it KILLED, saying why."""
    d = tmp_path / "mlruns"
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "DVC_ROOT")}
    p = subprocess.run([sys.executable, "-c", _KILLED, str(d)], env=env, capture_output=True, text=True, timeout=300,
                       check=False)
    assert p.returncode == -signal.SIGKILL, p.stderr[-2000:]
    run_id = p.stdout.split()[0]
    assert _client(d).get_run(run_id).info.status == "RUNNING"          # what kill -9 leaves

    from party import tracking
    uri = tracking.tracking_uri(_cfg(d))                                 # a reader opens the store
    assert uri == f"sqlite:///{d}/mlflow.db"
    run = _client(d).get_run(run_id)
    assert run.info.status == "KILLED"
    assert run.info.end_time is not None
    note = run.data.tags["party.error"]
    assert "ended without closing this run" in note and "when the store was next opened" in note, note


def test_mlflow_ui_marks_the_runs_of_dead_processes(tmp_path):
    """``scripts/mlflow_ui.sh`` opens the store through ``relocate_store``: a RUNNING run of a
    dead process of this host is marked KILLED there; a live process's run and another host's
    are left alone."""
    d = tmp_path / "mlruns"
    d.mkdir()
    uri = f"sqlite:///{d}/mlflow.db"
    client = _client(d)
    exp = client.create_experiment("night", artifact_location=(d / "artifacts").as_uri())
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    host = socket.gethostname()

    def plant(process: str, on: str = host) -> str:
        run = client.create_run(exp, tags={"party.stage": "evaluate", "party.host": on, "party.process": process})
        return run.info.run_id

    from party.lifecycle import process_key
    dead = plant(f"{gone.pid}:1")                   # its pid is gone (or reused: another start time)
    live = plant(process_key(os.getpid()))
    elsewhere = plant(f"{gone.pid}:1", on=host + "-other")

    from party.tracking import relocate_store
    relocate_store(uri)
    assert client.get_run(dead).info.status == "KILLED"
    assert "when the store was next opened" in client.get_run(dead).data.tags["party.error"]
    assert client.get_run(live).info.status == "RUNNING"
    assert client.get_run(elsewhere).info.status == "RUNNING"
