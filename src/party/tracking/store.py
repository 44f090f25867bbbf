"""The MLflow store: where it is (``tracking_uri``), its artifact root, the experiment of the
project (created once, under a lock shared by processes), a copied store pointed back at
its own artifacts (``relocate_store``), and the runs of dead processes marked KILLED when a
process first opens the store (``close_orphans_once``)."""
from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import Mapping

from omegaconf import DictConfig

log = logging.getLogger("party.tracking")


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


def resolve_uri(cfg) -> str:
    """``$MLFLOW_TRACKING_URI`` > ``tracking.uri`` > ``sqlite:///<abs dir>/mlflow.db`` (nothing opened)."""
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if env:
        return env
    uri = _tcfg(cfg)["uri"]
    if uri:
        return str(uri)
    return f"sqlite:///{tracking_dir(cfg) / 'mlflow.db'}"


def tracking_uri(cfg) -> str:
    """The store of ``cfg`` (``resolve_uri``), the way party code opens it: the first time in a
    process, the runs a dead process left RUNNING there are marked KILLED (``close_orphans_once``),
    so whatever reads the store next (a stage, ``party.load``, the notebooks) sees them ended."""
    uri = resolve_uri(cfg)
    close_orphans_once(uri)
    return uri


#: stores this process has looked at for runs left RUNNING by dead processes
_ORPHANS_CLOSED: set[str] = set()


def close_orphans_once(uri: str, when: str | None = None) -> list[str]:
    """Mark KILLED the runs a dead process of this host left RUNNING in the local SQLite store at
    ``uri`` (``party.lifecycle.close_orphans``), once per process and store: one query. A store
    that does not exist yet is not created, and no server is contacted (a stage's start closes
    orphans there). ``when`` ends the note left on the run (default: the store was next opened,
    by this process). A failure is a warning, never the caller's error. Returns the closed run ids."""
    if uri in _ORPHANS_CLOSED:
        return []
    _ORPHANS_CLOSED.add(uri)
    db = _sqlite_path(uri)
    if db is None or not db.is_file():
        return []
    import sqlite3
    import sys

    try:
        con = sqlite3.connect(db)
        try:
            ready = con.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='runs'").fetchone()
        finally:
            con.close()
        if not ready:
            return []
        import mlflow

        from party.lifecycle import close_orphans
        prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
        return close_orphans(mlflow.MlflowClient(uri), None,
                             when or f"when the store was next opened (process {os.getpid()}, {prog})")
    except Exception as e:  # noqa: BLE001 - a reader of the store must not fail for this
        log.warning("%s: could not look for runs left RUNNING by dead processes: %s", db, e)
        return []


def _sqlite_path(uri: str) -> Path | None:
    if not uri.startswith("sqlite:///"):
        return None
    p = uri[len("sqlite:///"):].split("?", 1)[0]
    return Path(p if p.startswith("/") else os.path.join(os.getcwd(), p))


def artifact_location(uri: str) -> str | None:
    """Artifact root for experiments we create: ``<db dir>/artifacts`` for SQLite stores; None for a
    tracking server, which picks its own (``mlflow-artifacts:/`` when it serves the artifacts,
    ``scripts/mlflow_server.sh``): clients then up- and download them through it."""
    db = _sqlite_path(uri)
    return None if db is None else (db.parent / "artifacts").resolve().as_uri()


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


def _location_path(value) -> tuple[str, Path] | None:
    """(``"file"`` or ``"path"``, absolute local path) of a recorded artifact location; None for
    anything else (a server's ``s3://``, ``mlflow-artifacts:``, a relative path)."""
    if not isinstance(value, str):
        return None
    if value.startswith("file://"):
        from urllib.parse import unquote, urlparse
        p = unquote(urlparse(value).path)
        return ("file", Path(p)) if p.startswith("/") else None
    return ("path", Path(value)) if value.startswith("/") else None


def _under(path: Path, root: Path) -> Path | None:
    """``path`` relative to ``root`` when it lies under it (root itself excluded), else None."""
    try:
        rel = path.relative_to(root)
    except ValueError:
        return None
    return rel if rel.parts else None


def relocate_store(uri: str) -> int:
    """Point a moved or copied SQLite store at its own artifacts: MLflow records absolute
    artifact locations (``file:///old/clone/mlruns/artifacts/...``), so a clone moved elsewhere
    would read from and write into the original's folder.

    Only the store's own previous folder is moved: a folder ``<old>`` holding an experiment's
    root (``<old>/artifacts``, party's, or ``<old>/<id>``, MLflow's default) is the store's old
    folder when the artifacts of a run recorded under it came along, i.e. ``<old>/<rest>`` is
    found here as ``<db dir>/<rest>``. Its locations are then rewritten to this folder; every
    other location (a server's, an artifact root configured on purpose elsewhere, whose runs'
    files are still there and not here) is left as it is. Returns the rows changed. Opening the
    store this way (``scripts/mlflow_ui.sh`` does) also ends the runs of dead processes
    (``close_orphans_once``). Any other URI (a tracking server: its artifacts are its own) has
    nothing to relocate: 0."""
    db = _sqlite_path(uri)
    if db is None or not db.exists():
        return 0
    try:
        return _relocate(db)
    finally:     # scripts/mlflow_ui.sh opens the store through this: runs of dead processes end
        close_orphans_once(uri)


def _relocate(db: Path) -> int:
    import sqlite3

    new_root = db.parent.resolve()
    con = sqlite3.connect(db)
    try:
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if "experiments" not in tables:
            return 0
        candidates = set()
        for (loc,) in con.execute("SELECT artifact_location FROM experiments"):
            found = _location_path(loc)
            if found and found[1].parent != new_root and (found[1].name == "artifacts" or found[1].name.isdigit()):
                candidates.add(found[1].parent)
        runs = [_location_path(u) for (u,) in con.execute("SELECT artifact_uri FROM runs")] \
            if candidates and "runs" in tables else []
        runs = [p for _, p in filter(None, runs)]
        old_roots = {old for old in candidates
                     if any((rel := _under(p, old)) is not None and (new_root / rel).is_dir() for p in runs)}
        if candidates - old_roots:
            log.debug("%s: artifact roots %s left as recorded (no run's artifacts of theirs are under %s)",
                      db, ", ".join(sorted(map(str, candidates - old_roots))), new_root)
        if not old_roots:
            return 0
        changed = 0
        with con:
            for table, col, key in _LOCATION_COLUMNS:
                if table not in tables:
                    continue
                for k, value in con.execute(f"SELECT {key}, {col} FROM {table}").fetchall():
                    found = _location_path(value)
                    if not found:
                        continue
                    kind, path = found
                    for old in sorted(old_roots, key=lambda r: len(r.parts), reverse=True):
                        rel = _under(path, old)
                        if rel is not None:
                            moved = new_root / rel
                            new = moved.as_uri() if kind == "file" else str(moved)
                            con.execute(f"UPDATE {table} SET {col}=? WHERE {key}=?", (new, k))
                            changed += 1
                            break
        if changed:
            log.warning("%s: moved from %s; %d artifact locations now point under %s",
                        db, ", ".join(sorted(map(str, old_roots))), changed, new_root)
        return changed
    finally:
        con.close()


# the MLflow UI opens an experiment of this kind in its model-training view ("Training runs"),
# not the GenAI one, and does not ask which kind it is
EXPERIMENT_KIND, MODEL_TRAINING = "mlflow.experimentKind", "custom_model_development"


def _experiment_id(name: str, uri: str) -> str:
    import mlflow
    from mlflow.exceptions import MlflowException

    with _store_lock(uri):  # the client creates (and migrates) a new store eagerly
        relocate_store(uri)
        client = mlflow.MlflowClient(uri)
        exp = client.get_experiment_by_name(name)
        if exp is None:
            try:
                return client.create_experiment(name, artifact_location=artifact_location(uri),
                                                tags={EXPERIMENT_KIND: MODEL_TRAINING})
            except MlflowException as e:
                # a server's store has no lock of ours: a job on another node created it meanwhile
                if e.error_code != "RESOURCE_ALREADY_EXISTS":
                    raise
                exp = client.get_experiment_by_name(name)
                if exp is None:
                    raise
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
