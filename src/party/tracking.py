"""MLflow convention: one SQLite store with artifacts on disk, one run per stage.

Layout (``tracking.dir``, default ``mlruns/`` in the project root)::

    mlruns/mlflow.db        runs, params, metrics, tags (SQLite backend store)
    mlruns/artifacts/<run>  artifacts (config.yaml, json, videos, ...)

The project root is ``$DVC_ROOT`` when set (DVC sets it for every stage, and for queued
experiments it points at the *parent* repository, so runs from temporary workspaces land
in the main store), else the current directory. ``MLFLOW_TRACKING_URI`` wins over
``tracking.uri``, which wins over the SQLite default. With a SQLite URI the artifacts go
next to the database (``<db dir>/artifacts``); with a server URI the server decides.

Stage code::

    with start_run(cfg, "train_vqvae") as run:
        trainer = L.Trainer(logger=lightning_logger(cfg, run), ...)
        log_metrics({"fid": 0.1})
        log_json(report, "eval/metrics.json")
        log_video(joints, "samples/000.gif", title=caption)

Every helper is a no-op when no run is active: tracking disabled (``tracking.enabled:
false``, a ``NullRun`` is yielded), or a non-zero rank under DDP (only global rank 0 opens a
run). MLflow is imported lazily, so disabled runs never pay for it.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

_RANK_VARS = ("RANK", "SLURM_PROCID", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK",
              "JSM_NAMESPACE_RANK")
_BAD_KEY_CHARS = re.compile(r"[^A-Za-z0-9_\-. :/]")


# --------------------------------------------------------------------------- config

def _tcfg(cfg: DictConfig | Mapping) -> Mapping:
    """The ``tracking`` group (conf/tracking/default.yaml holds every key and its value)."""
    t = cfg.get("tracking") if cfg is not None else None
    if t is None:
        raise KeyError("config has no `tracking` group (conf/tracking/default.yaml)")
    return t


def project_root() -> Path:
    """``$DVC_ROOT`` (the parent repo, also for queued DVC experiments) or the cwd."""
    return Path(os.environ.get("DVC_ROOT") or os.getcwd()).resolve()


def tracking_dir(cfg) -> Path:
    d = Path(_tcfg(cfg)["dir"])
    return d if d.is_absolute() else project_root() / d


def _set_tracking_uri(mlflow, uri: str) -> None:
    """Point this process's MLflow at ``uri`` without exporting it.

    ``mlflow.set_tracking_uri`` also writes ``$MLFLOW_TRACKING_URI`` (for subprocesses),
    which ``tracking_uri`` would then take as the user's choice: a later stage in this
    process, or any child process, would log into the first store. Keep the
    environment as the user left it.
    """
    before = os.environ.get("MLFLOW_TRACKING_URI")
    mlflow.set_tracking_uri(uri)
    if before is None:
        os.environ.pop("MLFLOW_TRACKING_URI", None)
    else:
        os.environ["MLFLOW_TRACKING_URI"] = before


def tracking_uri(cfg) -> str:
    """``$MLFLOW_TRACKING_URI`` > ``tracking.uri`` > ``sqlite:///<abs dir>/mlflow.db``."""
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if env:
        return env
    uri = _tcfg(cfg)["uri"]
    if uri:
        return str(uri)
    return f"sqlite:///{tracking_dir(cfg) / 'mlflow.db'}"


def _sqlite_path(uri: str) -> Path | None:
    if not uri.startswith("sqlite:///"):
        return None
    p = uri[len("sqlite:///"):].split("?", 1)[0]
    return Path(p if p.startswith("/") else os.path.join(os.getcwd(), p))


def artifact_location(uri: str) -> str | None:
    """Artifact root for experiments we create: ``<db dir>/artifacts`` for SQLite stores."""
    db = _sqlite_path(uri)
    return None if db is None else (db.parent / "artifacts").resolve().as_uri()


def flatten_config(cfg: DictConfig | Mapping, max_value_len: int | None = None,
                   max_key_len: int = 250) -> dict[str, str]:
    """Flatten a (resolved) config into MLflow params: ``{"vqvae.window": "64", ...}``.

    Lists of scalars (and nested lists) become one JSON value; lists holding mappings are
    indexed (``a.0.b``). Values longer than MLflow's limit are cut and end in ``...``
    (the full config is logged as ``config.yaml`` as well). Characters MLflow forbids in
    keys become ``_``.
    """
    if max_value_len is None:
        max_value_len = _mlflow_param_limit()
    data = _to_container(cfg)
    out: dict[str, str] = {}

    def leaf(v: Any) -> str:
        if isinstance(v, (list, dict)):
            return json.dumps(v, separators=(", ", ": "))
        return str(v)

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, dict) and node:
            for k, v in node.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        elif isinstance(node, list) and any(isinstance(x, dict) for x in node):
            for i, v in enumerate(node):
                walk(f"{prefix}.{i}", v)
        else:
            key = _BAD_KEY_CHARS.sub("_", prefix)[:max_key_len]
            val = leaf(node)
            if len(val) > max_value_len:
                val = val[: max_value_len - 3] + "..."
            out[key] = val

    walk("", data)
    return out


def _to_container(cfg) -> dict:
    if isinstance(cfg, DictConfig):
        try:
            return OmegaConf.to_container(cfg, resolve=True)
        except Exception as e:  # e.g. ${hydra:...} outside a Hydra app
            log.warning("config does not fully resolve (%s); logging it unresolved", e)
            return OmegaConf.to_container(cfg, resolve=False)
    return dict(cfg)


def _config_yaml(cfg) -> str:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_yaml(OmegaConf.create(_to_container(cfg)))
    return OmegaConf.to_yaml(OmegaConf.create(dict(cfg)))


def _mlflow_param_limit() -> int:
    try:
        from mlflow.utils.validation import MAX_PARAM_VAL_LENGTH
        return int(MAX_PARAM_VAL_LENGTH)
    except Exception:  # pragma: no cover - older/newer mlflow layouts
        return 6000


# --------------------------------------------------------------------------- ranks

def is_rank_zero() -> bool:
    """True unless an env rank variable (or Lightning's rank_zero_only) says otherwise."""
    rz = sys.modules.get("lightning.fabric.utilities.rank_zero")
    if rz is not None and getattr(rz.rank_zero_only, "rank", 0) not in (0, None):
        return False
    for var in _RANK_VARS:
        v = os.environ.get(var)
        if v not in (None, "", "0"):
            return False
    return True


# --------------------------------------------------------------------------- runs

class _RunMethods:
    """Logging methods bound to ``self.info.run_id`` (no-ops when it is None)."""

    def log_params(self, params):
        if self.info.run_id:
            log_params(params, run_id=self.info.run_id)

    def log_metrics(self, metrics, step=None):
        if self.info.run_id:
            log_metrics(metrics, step, run_id=self.info.run_id)

    def set_tags(self, tags):
        if self.info.run_id:
            set_tags(tags, run_id=self.info.run_id)

    def log_text(self, text, artifact_file):
        if self.info.run_id:
            log_text(text, artifact_file, run_id=self.info.run_id)

    def log_json(self, obj, artifact_file):
        if self.info.run_id:
            log_json(obj, artifact_file, run_id=self.info.run_id)

    def log_file(self, path, artifact_path=None):
        if self.info.run_id:
            log_file(path, artifact_path, run_id=self.info.run_id)

    def log_video(self, motion, artifact_file, **kw):
        if self.info.run_id:
            log_video(motion, artifact_file, run_id=self.info.run_id, **kw)


@dataclass
class _NullInfo:
    run_id: None = None
    experiment_id: None = None
    run_name: str | None = None
    status: str = "DISABLED"
    artifact_uri: None = None


@dataclass
class _NullData:
    params: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    tags: dict = field(default_factory=dict)


class NullRun(_RunMethods):
    """Stands in for ``mlflow.ActiveRun`` when tracking is off (or on a non-zero rank)."""

    active = False

    def __init__(self, run_name: str | None = None):
        self.info = _NullInfo(run_name=run_name)
        self.data = _NullData()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


# files every documented workflow changes (generated or written by the pipeline itself):
# they do not make a run's code or config differ from its commit
GENERATED = ("params.yaml", "dvc.lock", "metrics/", "conf/local/")


def _git_state() -> dict[str, str]:
    """``party.git_commit``; ``party.git_changed``: the tracked files that differ from it;
    ``party.git_dirty``: whether any of those is more than a generated file (``GENERATED``)."""
    def git(*args: str) -> str | None:
        try:
            r = subprocess.run(["git", *args], capture_output=True, text=True, timeout=10)
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
def _store_lock(uri: str):
    """Serialise store creation/migration and experiment creation across processes."""
    db = _sqlite_path(uri)
    if db is None:
        yield
        return
    from filelock import FileLock

    db.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(db.parent / ".mlflow.lock"), timeout=300):
        yield


_LOCATION_COLUMNS = (("experiments", "artifact_location", "experiment_id"), ("runs", "artifact_uri", "run_uuid"),
                     ("logged_models", "artifact_location", "model_id"),
                     ("model_versions", "source", "rowid"), ("model_versions", "storage_location", "rowid"))


def relocate_store(uri: str) -> int:
    """Point a moved or copied SQLite store at its own artifacts: MLflow records absolute
    artifact locations (``file:///old/clone/mlruns/artifacts/...``), so a clone moved elsewhere
    would read from and write into the original's folder. Every location under the old store
    folder is rewritten to this store's folder (``<db dir>``); locations elsewhere (a server's,
    an artifact root configured on purpose) are left alone. Returns the rows changed."""
    import sqlite3

    db = _sqlite_path(uri)
    if db is None or not db.exists():
        return 0
    new_root = db.parent.resolve()
    con = sqlite3.connect(db)
    try:
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if "experiments" not in tables:
            return 0
        old_roots = set()
        for (loc,) in con.execute("SELECT artifact_location FROM experiments"):
            path = Path(loc[len("file://"):] if loc.startswith("file://") else loc)
            if loc.startswith(("file://", "/")) and path.parent != new_root and \
                    (path.name == "artifacts" or path.name.isdigit()):
                old_roots.add(str(path.parent))
        changed = 0
        with con:
            for old in sorted(old_roots, key=len, reverse=True):
                for table, col, key in _LOCATION_COLUMNS:
                    if table not in tables:
                        continue
                    rows = con.execute(f"SELECT {key}, {col} FROM {table}").fetchall()
                    for k, value in rows:
                        for prefix in (f"file://{old}/", f"{old}/"):
                            if isinstance(value, str) and value.startswith(prefix):
                                new = prefix.replace(old, str(new_root), 1) + value[len(prefix):]
                                con.execute(f"UPDATE {table} SET {col}=? WHERE {key}=?", (new, k))
                                changed += 1
                                break
        if changed:
            log.warning("%s: moved from %s; %d artifact locations now point under %s",
                        db, ", ".join(sorted(old_roots)), changed, new_root)
        return changed
    finally:
        con.close()


# the MLflow UI opens an experiment of this kind in its model-training view ("Training runs"),
# not the GenAI one, and does not ask which kind it is
EXPERIMENT_KIND, MODEL_TRAINING = "mlflow.experimentKind", "custom_model_development"


def _experiment_id(name: str, uri: str) -> str:
    import mlflow

    with _store_lock(uri):  # the client creates (and migrates) a new store eagerly
        relocate_store(uri)
        client = mlflow.MlflowClient(uri)
        exp = client.get_experiment_by_name(name)
        if exp is None:
            return client.create_experiment(name, artifact_location=artifact_location(uri),
                                            tags={EXPERIMENT_KIND: MODEL_TRAINING})
        if EXPERIMENT_KIND not in exp.tags:
            client.set_experiment_tag(exp.experiment_id, EXPERIMENT_KIND, MODEL_TRAINING)
    if exp.lifecycle_stage == "deleted":
        raise RuntimeError(f"MLflow experiment {name!r} in {uri} is deleted; restore it "
                           f"(`mlflow experiments restore`) or set tracking.experiment")
    want = artifact_location(uri)
    if want and exp.artifact_location.rstrip("/") != want.rstrip("/"):
        log.warning("experiment %r stores artifacts in %s, not %s", name,
                    exp.artifact_location, want)
    return exp.experiment_id


def process_key(pid: int) -> str | None:
    """``"<pid>:<start time>"`` of a live process (Linux ``/proc``; ``"<pid>"`` elsewhere), or
    None when it is gone: a reused pid has another start time, so it is not mistaken for it."""
    from party.io import pid_alive

    if not pid_alive(pid):
        return None
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return str(pid)
    return f"{pid}:{stat.rsplit(')', 1)[1].split()[19]}"     # field 22: start time in ticks


def close_orphans(client, stage: str) -> list[str]:
    """Mark KILLED the RUNNING runs in this store (any experiment, any stage) whose process, on
    this host, is gone (``kill -9``, the OOM killer, a crash the process could not report): the
    next start of any stage (``stage``, named in the note it leaves) cleans up after it, so the
    UI and ``search_runs`` never show a dead run as running. Runs of other hosts (multi-node), of
    live processes, or without the ``party.process`` tag (older versions) are left alone.
    Returns the run ids it closed."""
    import socket

    host = socket.gethostname()
    ids = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(ids, max_results=1000, filter_string=(
        f"attributes.status = 'RUNNING' and tags.`party.host` = '{host}'")) if ids else []
    closed, named = [], []
    for r in runs:
        key = r.data.tags.get("party.process", "")
        pid = key.split(":", 1)[0]
        if not pid.isdigit() or process_key(int(pid)) == key:
            continue
        client.set_tag(r.info.run_id, "party.error",
                       f"process {pid} on {host} ended without closing this run (killed?); "
                       f"marked KILLED when {stage} next started")
        client.set_terminated(r.info.run_id, "KILLED")
        closed.append(r.info.run_id)
        named.append(f"{r.data.tags.get('party.stage', '?')} {r.info.run_id}")
    if closed:
        log.warning("marked %d orphaned run(s) KILLED: %s", len(closed), ", ".join(named))
    return closed


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM (``kill``, ``scancel``, a timeout) during a stage,
    so the run ends KILLED with the error recorded, as on Ctrl-C."""


_SIGNALLED: list[int] = []


@contextlib.contextmanager
def terminate_on_sigterm() -> Iterator[None]:
    """Turn SIGTERM into ``Terminated`` for the duration (main thread only; the previous
    handler is restored). Lightning composes its own SIGTERM handler with this one during
    ``fit``; its graceful shutdown then exits, and ``start_run`` still records KILLED."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    owner = os.getpid()

    def handler(signum, frame):
        if os.getpid() != owner:    # a forked worker (a multiprocessing pool's, when it is
            signal.signal(signum, signal.SIG_DFL)   # terminated): end quietly, as without us
            os.kill(os.getpid(), signum)
            return
        _SIGNALLED.append(signum)
        raise Terminated(f"received signal {signum} (SIGTERM)")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


@contextlib.contextmanager
def start_run(cfg, stage: str, run_name: str | None = None, tags: Mapping[str, Any] | None = None,
              parent_run_id: str | None = None, nested: bool = False) -> Iterator[Any]:
    """Open the stage's MLflow run; yields ``mlflow.ActiveRun`` (or a ``NullRun``).

    Tags: ``party.stage``, ``party.git_commit``, ``party.git_dirty``, ``party.git_changed``, the
    DVC experiment name/baseline when run by ``dvc exp`` (the run is then named
    ``<name>@<dvc exp>``), ``mlflow.parentRunId`` for nested runs (an
    active run with ``nested=True``, or ``parent_run_id`` / ``tracking.parent_run_id``).
    Logs the flattened resolved config as params and the full config as ``config.yaml``.
    The run ends FINISHED, or FAILED (KILLED on Ctrl-C or SIGTERM) when the body raises.
    First marks KILLED the runs left RUNNING by a dead process of this host (``close_orphans``).
    """
    t = _tcfg(cfg)
    name = run_name or stage
    if not t["enabled"] or not is_rank_zero():
        yield NullRun(name)
        return

    import mlflow

    uri = tracking_uri(cfg)
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
    try:
        run.log_params(flatten_config(cfg))
        run.log_text(_config_yaml(cfg), "config.yaml")
        yield run
    except BaseException as e:
        killed = isinstance(e, KeyboardInterrupt) or bool(_SIGNALLED)
        _SIGNALLED.clear()
        mlflow.end_run("KILLED" if killed else "FAILED")
        raise
    else:
        mlflow.end_run("FINISHED")


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


def lightning_logger(cfg, run):
    """An ``MLFlowLogger`` bound to the open run, or ``False`` (no logger) without a run.

    Pass the result straight to ``Trainer(logger=...)``. Unlike the stock logger it does
    not end the run when ``fit`` finishes (``start_run`` owns the run's status). Its
    ``save_dir`` is None for SQLite URIs: give ``ModelCheckpoint`` an explicit ``dirpath``.
    ``tracking.log_model`` (default false) uploads checkpoints as artifacts too.
    """
    run_id = getattr(getattr(run, "info", None), "run_id", None)
    if run_id is None or not is_rank_zero():
        return False
    t = _tcfg(cfg)
    return _bound_logger_cls()(experiment_name=t["experiment"], tracking_uri=tracking_uri(cfg), run_id=run_id,
                               log_model=t["log_model"])


_LOGGER_CLS = None


def _bound_logger_cls():
    global _LOGGER_CLS
    if _LOGGER_CLS is None:
        from lightning.pytorch.loggers import MLFlowLogger
        from lightning.pytorch.utilities import rank_zero_only

        class RunBoundMLFlowLogger(MLFlowLogger):
            """MLFlowLogger that logs into an existing run and leaves its status alone."""

            @rank_zero_only
            def finalize(self, status: str = "success") -> None:
                if self._initialized and self._checkpoint_callback:
                    self._scan_and_log_checkpoints(self._checkpoint_callback)

        _LOGGER_CLS = RunBoundMLFlowLogger
    return _LOGGER_CLS


def register_model(run, artifact_path: str, name: str, tags: Mapping[str, Any] | None = None,
                   description: str = "") -> str:
    """Register the artifact folder ``artifact_path`` of ``run`` as a new version of the
    registered model ``name`` (created if absent); returns the version. The folder is any
    set of files (no MLflow flavour): ``models:/<name>/<version>`` downloads it."""
    import mlflow
    from mlflow.exceptions import MlflowException

    client = mlflow.MlflowClient()
    with _store_lock(mlflow.get_tracking_uri()):
        try:
            client.get_registered_model(name)
        except MlflowException:
            client.create_registered_model(name, description="party generator packages (party register)")
    mv = client.create_model_version(name, f"{run.info.artifact_uri.rstrip('/')}/{artifact_path}",
                                     run_id=run.info.run_id, description=description,
                                     tags={k: str(v) for k, v in (tags or {}).items()})
    return str(mv.version)


# --------------------------------------------------------------------------- helpers
# Module-level helpers log into the active run; the same methods on a run object log into
# that run. All are no-ops without a run (tracking disabled, non-zero rank).

def _client(run_id: str | None):
    """(MlflowClient, run_id) when this process should log, else (None, None)."""
    mlflow = sys.modules.get("mlflow")
    if mlflow is None or not is_rank_zero():
        return None, None
    if run_id is None:
        active = mlflow.active_run()
        if active is None:
            return None, None
        run_id = active.info.run_id
    return mlflow.MlflowClient(), run_id


def active_run_id() -> str | None:
    return _client(None)[1]


def log_params(params: Mapping[str, Any], run_id: str | None = None) -> None:
    client, run_id = _client(run_id)
    if client is None:
        return
    from mlflow.entities import Param

    items = [Param(str(k), str(v)) for k, v in params.items()]
    for i in range(0, len(items), 100):  # MLflow's batch limit
        client.log_batch(run_id, params=items[i:i + 100])


def log_metrics(metrics: Mapping[str, float], step: int | None = None,
                run_id: str | None = None) -> None:
    client, run_id = _client(run_id)
    if client is None:
        return
    import time

    from mlflow.entities import Metric

    now = int(time.time() * 1000)
    items = [Metric(str(k), float(v), now, int(step or 0)) for k, v in metrics.items()]
    for i in range(0, len(items), 1000):
        client.log_batch(run_id, metrics=items[i:i + 1000])


def set_tags(tags: Mapping[str, Any], run_id: str | None = None) -> None:
    client, run_id = _client(run_id)
    if client is None:
        return
    from mlflow.entities import RunTag

    client.log_batch(run_id, tags=[RunTag(str(k), str(v)) for k, v in tags.items()])


def log_text(text: str, artifact_file: str, run_id: str | None = None) -> None:
    client, run_id = _client(run_id)
    if client is not None:
        client.log_text(run_id, text, artifact_file)


def log_json(obj: Any, artifact_file: str, run_id: str | None = None) -> None:
    """Log ``obj`` as pretty JSON at ``artifact_file`` (e.g. ``"eval/metrics.json"``)."""
    log_text(json.dumps(obj, indent=2, sort_keys=True, default=str), artifact_file, run_id)


def log_file(path: str | os.PathLike, artifact_path: str | None = None,
             run_id: str | None = None) -> None:
    """Log a file or a whole directory under ``artifact_path`` (a directory in the run)."""
    client, run_id = _client(run_id)
    if client is None:
        return
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"log_file: {p} does not exist")
    if p.is_dir():
        client.log_artifacts(run_id, str(p), artifact_path)
    else:
        client.log_artifact(run_id, str(p), artifact_path)


def log_video(motion, artifact_file: str, skeleton_name: str = "t2m", fps: float = 20,
              title: str = "", titles=None, run_id: str | None = None, **render_kw) -> None:
    """Render and log a motion video at ``artifact_file`` (``.gif``/``.mp4`` picks the format).

    ``motion``: a (T, J, 3) joint array, a list of them (side by side, ``titles`` per
    panel), or the path of an existing video file. ``PARTY_NO_RENDER=1`` skips rendering.
    """
    client, run_id = _client(run_id)
    if client is None:
        return
    art_dir, name = os.path.split(artifact_file)
    if isinstance(motion, (str, os.PathLike)):
        src = Path(motion)
        if not src.is_file():
            raise FileNotFoundError(f"log_video: {src} does not exist")
        if src.name == name:
            client.log_artifact(run_id, str(src), art_dir or None)
            return
    elif os.environ.get("PARTY_NO_RENDER"):
        return
    from party import render

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / name
        if isinstance(motion, (str, os.PathLike)):
            out.write_bytes(Path(motion).read_bytes())
        elif isinstance(motion, (list, tuple)):
            render.render_comparison(list(motion), list(titles or []), out,
                                     skeleton_name=skeleton_name, fps=fps, title=title, **render_kw)
        else:
            render.render_motion(motion, out, skeleton_name=skeleton_name, fps=fps, title=title,
                                 **render_kw)
        client.log_artifact(run_id, str(out), art_dir or None)
