"""A stage's MLflow run: ``start_run`` (tags, config, status on every way out), the git state
it records, and the link of a resumed training to its earlier runs."""
from __future__ import annotations

import contextlib
import os
import subprocess
from typing import Any, Iterator, Mapping

from party.lifecycle import _SIGNALLED, Busy, Preempted, close_orphans, process_key
from party.tracking.log import NullRun, _config_yaml, _RunMethods, flatten_config, is_rank_zero
from party.tracking.store import _ORPHANS_CLOSED, _experiment_id, _set_tracking_uri, _tcfg, resolve_uri


# files every documented workflow changes (generated or written by the pipeline itself):
# they do not make a run's code or config differ from its commit
GENERATED = ("params.yaml", "dvc.lock", "metrics/", "conf/local/")


def _git_state(root: str | os.PathLike | None = None) -> dict[str, str]:
    """``party.git_commit``; ``party.git_changed``: the tracked files that differ from it;
    ``party.git_dirty``: whether any of those is more than a generated file (``GENERATED``). Of the
    checkout at ``root`` (default: the working folder's)."""
    where = ["-C", str(root)] if root is not None else []

    def git(*args: str) -> str | None:
        try:
            r = subprocess.run(["git", *where, *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return r.stdout.rstrip("\n") if r.returncode == 0 else None   # porcelain lines start with a space

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no")
    if status is None:
        return {"party.git_commit": commit or "unknown", "party.git_dirty": "unknown"}
    changed = sorted(line[3:].split(" -> ")[-1] for line in status.splitlines() if line.strip())
    source = [f for f in changed if not f.startswith(GENERATED)]
    listed = ", ".join(changed)
    return {"party.git_commit": commit or "unknown", "party.git_dirty": str(bool(source)).lower(),
            "party.git_changed": listed if len(listed) <= 4000 else listed[:3997] + "..."}


def link_resumed(run, resume_key: str) -> str | None:
    """A training resumed from a rolling checkpoint continues the runs of the same
    ``party.resume_key``: tag ``party.resumed_from`` (the latest of them) and, unless the run
    already has a parent (a sweep point), ``mlflow.parentRunId`` = the first, so the UI shows
    one training as one run with its continuations beneath. Returns the run resumed from."""
    run_id = getattr(run.info, "run_id", None)
    if not run_id:
        return None
    import mlflow

    client = mlflow.MlflowClient()
    this = client.get_run(run_id)
    earlier = [r for r in client.search_runs(
        [this.info.experiment_id], filter_string=f"tags.`party.resume_key` = '{resume_key}'",
        order_by=["attributes.start_time ASC"], max_results=1000) if r.info.run_id != run_id
        and r.info.start_time <= this.info.start_time]
    if not earlier:
        return None
    root = earlier[0].data.tags.get("party.resume_root", earlier[0].info.run_id)
    tags = {"party.resumed_from": earlier[-1].info.run_id, "party.resume_root": root}
    if "mlflow.parentRunId" not in this.data.tags:
        tags["mlflow.parentRunId"] = root
    run.set_tags(tags)
    return earlier[-1].info.run_id


@contextlib.contextmanager
def start_run(cfg, stage: str, run_name: str | None = None, tags: Mapping[str, Any] | None = None,
              parent_run_id: str | None = None, nested: bool = False) -> Iterator[Any]:
    """Open the stage's MLflow run; yields ``mlflow.ActiveRun`` (or a ``NullRun``).

    Tags: ``party.stage``, ``party.git_commit``, ``party.git_dirty``, ``party.git_changed``, the
    DVC experiment name/baseline when run by ``dvc exp`` (the run is then named
    ``<name>@<dvc exp>``), ``mlflow.parentRunId`` for nested runs (an
    active run with ``nested=True``, or ``parent_run_id`` / ``tracking.parent_run_id``).
    Logs the flattened resolved config as params and the full config as ``config.yaml``.
    The run ends FINISHED, or FAILED (KILLED on Ctrl-C or SIGTERM, and when SLURM preempted it:
    ``Preempted``, tagged ``party.preempted``) when the body raises.
    First marks KILLED the runs left RUNNING by a dead process of this host (``close_orphans``).
    """
    t = _tcfg(cfg)
    name = run_name or stage
    if not t["enabled"] or not is_rank_zero():
        yield NullRun(name)
        return

    import mlflow

    from party.slurm import COLLECT, PARENT_ENV, TASK_ENV
    if os.environ.get(TASK_ENV) is not None and parent_run_id is None and mlflow.active_run() is None:
        # a task of a grid's SLURM array (party.slurm): a point's task opens no stage run (the
        # point's run nests under the grid's parent); the collecting task continues the parent
        if os.environ[TASK_ENV] != COLLECT:
            yield NullRun(name)
        else:
            with _continue_run(cfg, os.environ[PARENT_ENV]) as run:
                yield run
        return

    uri = resolve_uri(cfg)
    _ORPHANS_CLOSED.add(uri)     # closed below at every start, the note naming this stage
    _set_tracking_uri(mlflow, uri)
    exp_id = _experiment_id(t["experiment"], uri)
    mlflow.set_experiment(experiment_id=exp_id)

    import socket

    close_orphans(mlflow.MlflowClient(uri), stage)
    all_tags = {"party.stage": stage, **_git_state(), "party.host": socket.gethostname(),
                "party.process": process_key(os.getpid())}
    for env, tag in (("DVC_EXP_NAME", "party.dvc_exp_name"),
                     ("DVC_EXP_BASELINE_REV", "party.dvc_baseline_rev")):
        if os.environ.get(env):
            all_tags[tag] = os.environ[env]
    all_tags.update({k: str(v) for k, v in (tags or {}).items()})
    active = mlflow.active_run()
    # the configured parent (a sweep's run) applies to top-level runs of this process only
    parent = parent_run_id or (t["parent_run_id"] if active is None else None) or None
    if parent and active is not None and active.info.run_id != parent:
        raise RuntimeError(f"start_run({stage!r}): parent_run_id {parent} is not the active "
                           f"run {active.info.run_id}")
    if os.environ.get("DVC_EXP_NAME"):      # which DVC experiment, visible in the runs list
        name = f"{name}@{os.environ['DVC_EXP_NAME']}"
    run = mlflow.start_run(experiment_id=exp_id, run_name=name, tags=all_tags,
                           parent_run_id=parent, nested=nested or active is not None and bool(parent),
                           log_system_metrics=bool(t["log_system_metrics"]))
    run = _party_run_cls()(run)
    with _ending():
        run.log_params(flatten_config(cfg))
        run.log_text(_config_yaml(cfg), "config.yaml")
        yield run


@contextlib.contextmanager
def _ending() -> Iterator[None]:
    """End the active run when the body ends: FINISHED, or when it raises KILLED on Ctrl-C, SIGTERM,
    SLURM's preemption (tag ``party.preempted``) or ``Busy`` (tag ``party.busy``), else FAILED."""
    import mlflow
    try:
        yield
    except BaseException as e:
        killed = isinstance(e, (KeyboardInterrupt, Preempted, Busy)) or bool(_SIGNALLED)
        _SIGNALLED.clear()
        if isinstance(e, Preempted):
            mlflow.set_tag("party.preempted", str(e.job_id))
        if isinstance(e, Busy):
            mlflow.set_tag("party.busy", str(e)[:250])
        mlflow.end_run("KILLED" if killed else "FAILED")
        raise
    mlflow.end_run("FINISHED")


@contextlib.contextmanager
def _continue_run(cfg, run_id: str) -> Iterator[Any]:
    """Make the existing run ``run_id`` active again, ending it FINISHED (FAILED, KILLED) like ``start_run``."""
    import mlflow
    _set_tracking_uri(mlflow, resolve_uri(cfg))
    mlflow.start_run(run_id=run_id)
    with _ending():
        yield _party_run_cls()(mlflow.active_run())


def create_run(cfg, stage: str, run_name: str, tags: Mapping[str, Any] = ()) -> str | None:
    """A run left RUNNING for other processes to nest under and end (a grid submitted as a SLURM
    array: its jobs' point runs nest under it, the collecting job ends it): ``start_run``'s tags,
    params and ``config.yaml``, no ``party.process`` tag (``close_orphans`` keys it by its
    ``party.slurm_job``). None when tracking is disabled."""
    t = _tcfg(cfg)
    if not t["enabled"]:
        return None
    import socket

    import mlflow
    from mlflow.entities import Param

    uri = resolve_uri(cfg)
    _set_tracking_uri(mlflow, uri)       # set_run_tags / end_run of this process use the same store
    client = mlflow.MlflowClient(uri)
    exp_id = _experiment_id(t["experiment"], uri)
    all_tags = {"party.stage": stage, **_git_state(), "party.host": socket.gethostname(),
                **{k: str(v) for k, v in dict(tags).items()}}
    run = client.create_run(exp_id, run_name=run_name, tags=all_tags)
    params = [Param(k, v) for k, v in flatten_config(cfg).items()]
    for i in range(0, len(params), 100):
        client.log_batch(run.info.run_id, params=params[i:i + 100])
    client.log_text(run.info.run_id, _config_yaml(cfg), "config.yaml")
    return run.info.run_id


def _client():
    """A client of the store this process set (``create_run``, ``start_run``)."""
    import mlflow
    return mlflow.MlflowClient()


def set_run_tags(run_id: str, tags: Mapping[str, Any]) -> None:
    """Tags on a run that is not this process's active run (``create_run``'s)."""
    client = _client()
    for k, v in tags.items():
        client.set_tag(run_id, k, str(v))


def end_run(run_id: str, status: str, error: str | None = None) -> None:
    """End a run that is not this process's active run, with ``status`` (and ``party.error``)."""
    client = _client()
    if error:
        client.set_tag(run_id, "party.error", error[:4000])
    client.set_terminated(run_id, status)


_PARTY_RUN_CLS = None


def _party_run_cls():
    """``mlflow.ActiveRun`` plus the logging methods (built lazily: mlflow imports slowly)."""
    global _PARTY_RUN_CLS
    if _PARTY_RUN_CLS is None:
        from mlflow import ActiveRun

        class PartyRun(ActiveRun, _RunMethods):
            active = True

        _PARTY_RUN_CLS = PartyRun
    return _PARTY_RUN_CLS
