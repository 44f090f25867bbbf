"""``party generate`` for people logs the files it wrote, not its whole output folder: the default
``outputs/generate`` also holds earlier runs' files and Hydra's run folders (every earlier run's
texts and overrides)."""
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


class _Generator:
    """Stands in for ``party.api.Generator``: a still pose per text (no model to train)."""

    def generate(self, texts, frames=None, seed=None, progress=False):
        from party.api import Motion
        return [Motion(t, np.zeros((16, 263), np.float32), 20.0, "t2m", 22) for t in texts]


def _artifacts(client, run_id: str, path: str = "generate") -> set[str]:
    out = set()
    for f in client.list_artifacts(run_id, path):
        out |= _artifacts(client, run_id, f.path) if f.is_dir else {f.path}
    return out


def test_a_second_run_logs_only_its_own_files(tmp_path, monkeypatch):
    import party.api
    from mlflow.tracking import MlflowClient

    from party import tracking
    from party.config import compose
    from party.stages import generate

    monkeypatch.setattr(party.api, "load", lambda *a, **k: _Generator())
    out = tmp_path / "outputs" / "generate"

    def run(text: str):
        """One ``party generate`` (the Hydra form) of ``text`` into ``out``; (client, its run id)."""
        cfg = compose([f"generator.generate.texts=[{text}]", f"generator.generate.out={out}",
                       "generator.generate.formats=[npy]", f"tracking.dir={tmp_path / 'mlruns'}", "progress=false"],
                      ROOT / "conf")
        generate.run(cfg)
        client = MlflowClient(tracking.tracking_uri(cfg))
        exp = client.get_experiment_by_name(cfg.tracking.experiment)
        (last,) = client.search_runs([exp.experiment_id], order_by=["attributes.start_time DESC"], max_results=1)
        return client, last.info.run_id

    client, first = run("a person waves")
    hydra = out / "earlier" / ".hydra"                   # what Hydra leaves for every run under outputs/generate
    hydra.mkdir(parents=True)
    (hydra / "overrides.yaml").write_text("- generator.generate.texts=[a private text]\n")
    client, second = run("someone kicks")
    assert {p.name for p in out.iterdir()} >= {"000_a_person_waves.feats.npy", "000_someone_kicks.feats.npy"}
    assert _artifacts(client, second) == {"generate/000_someone_kicks.feats.npy",
                                          "generate/000_someone_kicks.joints.npy", "generate/generated.json"}
    assert _artifacts(client, first) == {"generate/000_a_person_waves.feats.npy",
                                         "generate/000_a_person_waves.joints.npy", "generate/generated.json"}
    local = client.download_artifacts(second, "generate/generated.json", str(tmp_path / "dl"))
    assert "someone kicks" in Path(local).read_text() and "waves" not in Path(local).read_text()

