"""The logging API: the methods of a run object (``run.log_params``, ``log_metrics``,
``set_tags``, ``log_text``, ``log_json``, ``log_file``, ``log_video``), which the stages use,
and the same functions at module level logging into the active run (``run_id=None``), which
sweeps use for their parent run. All are no-ops without a run (tracking disabled, a non-zero
DDP rank): ``NullRun`` stands in for the run then. Also the config as MLflow params."""
from __future__ import annotations

import json
import logging
import os
import re
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from party.secrets import redact, redact_tree

log = logging.getLogger("party.tracking")


_RANK_VARS = ("RANK", "SLURM_PROCID", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK",
              "JSM_NAMESPACE_RANK")


_BAD_KEY_CHARS = re.compile(r"[^A-Za-z0-9_\-. :/]")


def flatten_config(cfg: DictConfig | Mapping, max_value_len: int | None = None,
                   max_key_len: int = 250) -> dict[str, str]:
    """Flatten a (resolved) config into MLflow params: ``{"vqvae.window": "64", ...}``.

    Lists of scalars (and nested lists) become one JSON value; lists holding mappings are
    indexed (``a.0.b``). Values longer than MLflow's limit are cut and end in ``...``
    (the full config is logged as ``config.yaml`` as well). Characters MLflow forbids in
    keys become ``_``. Credentials are masked (``party.secrets.redact``).
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
            val = redact(leaf(node))
            if len(val) > max_value_len:
                val = val[: max_value_len - 3] + "..."
            out[key] = val

    walk("", data)
    return out


def _to_container(cfg) -> dict:
    from party.secrets import scan
    scan(cfg)               # the values it reads with oc.env are masked wherever it is logged
    if isinstance(cfg, DictConfig):
        try:
            return OmegaConf.to_container(cfg, resolve=True)
        except Exception as e:  # e.g. ${hydra:...} outside a Hydra app
            log.warning("config does not fully resolve (%s); logging it unresolved", e)
            return OmegaConf.to_container(cfg, resolve=False)
    return dict(cfg)


def _config_yaml(cfg) -> str:
    """The resolved config as YAML, credentials masked."""
    return OmegaConf.to_yaml(OmegaConf.create(redact_tree(_to_container(cfg))))


def _mlflow_param_limit() -> int:
    try:
        from mlflow.utils.validation import MAX_PARAM_VAL_LENGTH
        return int(MAX_PARAM_VAL_LENGTH)
    except Exception:  # pragma: no cover - older/newer mlflow layouts
        return 6000


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

    items = [Param(str(k), redact(v)) for k, v in params.items()]
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

    client.log_batch(run_id, tags=[RunTag(str(k), redact(v)) for k, v in tags.items()])


def log_text(text: str, artifact_file: str, run_id: str | None = None) -> None:
    client, run_id = _client(run_id)
    if client is not None:
        client.log_text(run_id, redact(text), artifact_file)


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
