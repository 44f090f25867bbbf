"""Slow: the evaluator with the real offline text encoder (MiniLM) in both text modes."""

import json

import pytest
from eval_fixtures import make_cfg, prepare, write_dataset


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["words", "tokens"])
def test_train_and_evaluate_with_minilm(tmp_path, mode):
    from party.evaluation.checkpoint import load_trained
    from party.stages import evaluate, train_evaluator

    root = write_dataset(tmp_path / "H3D")
    cfg = make_cfg(tmp_path, root, [f"evaluator.text_input={mode}", "evaluator.train.max_steps=200"])
    prepare(cfg, root)
    m = train_evaluator.run(cfg)
    assert m["test_gt"]["top3"] > 0.4                       # chance 3/32
    ev = load_trained(tmp_path / "evaluators/holistic/finest.tar")   # tokens mode rebuilds MiniLM
    assert ev.embed_text(["a person walk forward"], [None]).shape == (1, 32)
    out = evaluate.run(cfg)
    assert out["results"]["ground_truth"]["holistic"]["top3"]["mean"] > 0.4
    assert json.loads((tmp_path / "eval/metrics.json").read_text())["summary"]["replications"] == 3
