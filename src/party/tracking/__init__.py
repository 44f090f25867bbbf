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
        run.log_metrics({"fid": 0.1})
        run.log_json(report, "eval/metrics.json")
        run.log_video(joints, "samples/000.gif", title=caption)

Every logging call is a no-op when no run is active: tracking disabled (``tracking.enabled:
false``, a ``NullRun`` is yielded), or a non-zero rank under DDP (only global rank 0 opens a
run). MLflow is imported lazily, so disabled runs never pay for it.

One module per concern: ``store`` (URI, experiment, a moved store's artifact locations),
``log`` (the logging API: run methods, and module functions into the active run), ``run``
(``start_run``, git state, resumed runs), ``lightning`` (the logger bound to a run),
``registry`` (model versions). How a stage's process ends (SIGTERM, orphaned runs) is
``party.lifecycle``, beside the stage skeleton.
"""
from party.lifecycle import Terminated, close_orphans, process_key, terminate_on_sigterm
from party.tracking.lightning import lightning_logger
from party.tracking.log import (NullRun, _mlflow_param_limit, active_run_id, flatten_config, is_rank_zero, log_file,
                                log_json, log_metrics, log_params, log_text, log_video, set_tags)
from party.tracking.registry import register_model
from party.tracking.run import GENERATED, _git_state, link_resumed, start_run
from party.tracking.store import (EXPERIMENT_KIND, MODEL_TRAINING, artifact_location, project_root, relocate_store,
                                  tracking_dir, tracking_uri)

__all__ = ["EXPERIMENT_KIND", "GENERATED", "MODEL_TRAINING", "NullRun", "Terminated", "active_run_id",
           "artifact_location", "close_orphans", "flatten_config", "is_rank_zero", "lightning_logger", "link_resumed",
           "log_file", "log_json", "log_metrics", "log_params", "log_text", "log_video", "process_key",
           "project_root", "register_model", "relocate_store", "set_tags", "start_run", "terminate_on_sigterm",
           "tracking_dir", "tracking_uri", "_git_state", "_mlflow_param_limit"]
