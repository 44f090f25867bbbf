"""``relocate_store`` (every stage start, ``scripts/mlflow_ui.sh``) moves only what lived in the
store's own previous folder: an experiment whose artifact root was configured elsewhere on
purpose keeps it, and its files stay listed."""
import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from party import tracking


def _cfg(store: Path):
    return OmegaConf.create({"seed": 0, "tracking": {
        "enabled": True, "experiment": "party", "uri": None, "dir": str(store), "parent_run_id": None,
        "log_system_metrics": False, "log_model": False, "n_render_samples": 1}})


def _project(root: Path) -> tuple[str, str, str]:
    """A store under ``root/mlruns`` with a party run (its own artifact folder) and an experiment
    whose artifacts live on ``root.parent/bigdisk`` on purpose; (own run, elsewhere run, uri)."""
    from mlflow.tracking import MlflowClient

    cfg = _cfg(root / "mlruns")
    with tracking.start_run(cfg, "prepare") as run:
        tracking.log_json({"where": "own"}, "w.json")
    uri = tracking.tracking_uri(cfg)
    client = MlflowClient(uri)
    big = root.parent / "bigdisk" / "artifacts"
    eid = client.create_experiment("on-bigdisk", artifact_location=big.as_uri())
    far = client.create_run(eid)
    client.log_text(far.info.run_id, "kept", "far.txt")
    client.set_terminated(far.info.run_id)
    assert (big / far.info.run_id / "artifacts" / "far.txt").exists()
    return run.info.run_id, far.info.run_id, uri


def _listed(uri: str, run_id: str) -> list[str]:
    from mlflow.tracking import MlflowClient
    return sorted(f.path for f in MlflowClient(uri).list_artifacts(run_id))


def test_an_artifact_root_configured_elsewhere_is_left_as_it_is(tmp_path):
    from mlflow.tracking import MlflowClient

    own, far, uri = _project(tmp_path / "a")
    big = (tmp_path / "bigdisk" / "artifacts").as_uri()
    assert tracking.relocate_store(uri) == 0
    with tracking.start_run(_cfg(tmp_path / "a" / "mlruns"), "evaluate"):      # a stage start relocates too
        pass
    client = MlflowClient(uri)
    assert client.get_experiment_by_name("on-bigdisk").artifact_location == big
    assert client.get_run(far).info.artifact_uri.startswith(big + "/")
    assert _listed(uri, far) == ["far.txt"]
    assert _listed(uri, own) == ["config.yaml", "w.json"]


@pytest.mark.parametrize("how", ["copy", "move"])
def test_a_moved_store_moves_its_own_locations_only(tmp_path, how):
    from mlflow.tracking import MlflowClient

    own, far, _ = _project(tmp_path / "a")
    (shutil.copytree if how == "copy" else shutil.move)(tmp_path / "a", tmp_path / "b")
    uri = tracking.tracking_uri(_cfg(tmp_path / "b" / "mlruns"))
    assert tracking.relocate_store(uri) > 0
    client = MlflowClient(uri)
    new_root = (tmp_path / "b" / "mlruns").resolve().as_uri()
    assert client.get_experiment_by_name("party").artifact_location == new_root + "/artifacts"
    assert client.get_run(own).info.artifact_uri.startswith(new_root + "/")
    assert _listed(uri, own) == ["config.yaml", "w.json"]
    big = (tmp_path / "bigdisk" / "artifacts").as_uri()
    assert client.get_experiment_by_name("on-bigdisk").artifact_location == big       # configured: kept
    assert _listed(uri, far) == ["far.txt"]
    assert tracking.relocate_store(uri) == 0                                           # nothing left to move
