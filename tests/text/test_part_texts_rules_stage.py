"""cache_part_texts with the default rules backend: output, stats, MLflow, no work on rerun."""
from __future__ import annotations

import json

from party.stages import cache_part_texts
from party.text.backends.rules import RulesBackend
from party.text.cache import load_part_texts
from text_helpers import stage_cfg, write_index

CAPS = [["A person waves with their right hand while standing still.", "someone waves the right hand."],
        ["A person runs forward quickly."], ["A person sits down on a chair."],
        ["A person kicks a ball with their right foot."]]


def test_rules_stage_outputs_tracks_and_reruns_without_calls(tmp_path, monkeypatch):
    write_index(tmp_path, CAPS)
    cfg = stage_cfg(tmp_path, "rules", **{"tracking.enabled": True, "tracking.dir": str(tmp_path / "mlruns"),
                                          "tracking.experiment": "text-test"})
    calls = []
    real = RulesBackend.describe
    monkeypatch.setattr(RulesBackend, "describe", lambda self, c: calls.append(c) or real(self, c))
    stats = cache_part_texts.run(cfg)
    captions = [c for caps in CAPS for c in caps]
    assert sorted(calls) == sorted(captions) and stats["calls"] == len(captions)
    out = load_part_texts(cfg.part_texts.out_dir)
    assert list(out) == captions
    assert out["A person sits down on a chair."]["arms"] == "No significant movement"
    assert out["A person waves with their right hand while standing still."]["legs"] == "No significant movement"
    assert "right" in out["A person kicks a ball with their right foot."]["legs"].lower()
    saved = json.loads((tmp_path / "part_texts" / "stats.json").read_text())
    assert saved["backend"] == "rules" and saved["model"].startswith("rules-") and saved["misses"] == len(captions)

    import mlflow
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}")
    runs = mlflow.search_runs(experiment_names=["text-test"])
    assert len(runs) == 1 and runs.iloc[0]["tags.party.stage"] == "cache_part_texts"
    assert runs.iloc[0]["metrics.part_texts/misses"] == len(captions)

    calls.clear()
    stats2 = cache_part_texts.run(cfg)
    assert calls == [] and stats2["calls"] == 0 and stats2["hits"] == len(captions)
    assert load_part_texts(cfg.part_texts.out_dir) == out
