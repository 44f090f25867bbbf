"""The MLflow model registry: an artifact folder of a run as a registered model version."""
from __future__ import annotations

from typing import Any, Mapping

from party.tracking.store import _store_lock


def register_model(run, artifact_path: str, name: str, tags: Mapping[str, Any] | None = None,
                   description: str = "") -> str:
    """Register the artifact folder ``artifact_path`` of ``run`` as a new version of the
    registered model ``name`` (created if absent); returns the version. The folder is any
    set of files (no MLflow flavour): ``models:/<name>/<version>`` downloads it."""
    import mlflow
    from mlflow.exceptions import MlflowException

    client = mlflow.MlflowClient()
    with _store_lock(mlflow.get_tracking_uri()):   # a SQLite store's; a server has none of ours
        try:
            client.get_registered_model(name)
        except MlflowException:
            try:
                client.create_registered_model(name, description="party generator packages (party register)")
            except MlflowException as e:    # another job registered it meanwhile (a tracking server)
                if e.error_code != "RESOURCE_ALREADY_EXISTS":
                    raise
    mv = client.create_model_version(name, f"{run.info.artifact_uri.rstrip('/')}/{artifact_path}",
                                     run_id=run.info.run_id, description=description,
                                     tags={k: str(v) for k, v in (tags or {}).items()})
    return str(mv.version)
