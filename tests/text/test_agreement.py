"""The rules backend against the synthetic dataset's ground-truth part texts (acceptance:
>= 95% agreement on which parts move, >= 95% on the side for captions naming one)."""
from __future__ import annotations

import pytest

from party.config import compose
from party.text.agreement import agreement, load_ground_truth, main, part_side
from party.text.backends.rules import RulesBackend


@pytest.fixture(scope="module")
def small_synthetic(tmp_path_factory):
    from party.data.synthetic import write_synthetic_dataset
    root = tmp_path_factory.mktemp("syn") / "synthetic"
    cfg = compose(["dataset=synthetic", "dataset.synthetic.n_motions=60", "dataset.synthetic.num_workers=1",
                   "dataset.synthetic.seed=4321"], config_dir=_conf()).dataset
    write_synthetic_dataset(cfg, root, progress=False)
    return root


def _conf():
    from pathlib import Path
    return Path(__file__).resolve().parents[2] / "conf"


def test_rules_agree_with_synthetic_ground_truth(small_synthetic, capsys):
    rules = RulesBackend()
    rows = load_ground_truth(small_synthetic, rules.part_names)
    assert len(rows) >= 60 * 2 * 3 * 0.9                     # whole-clip captions of originals + mirrors
    res = agreement(rows, rules.parts, rules.part_names)
    assert res["moves"] >= 0.95, res["disagree_moves"][:5]
    assert res["captions_naming_side"] >= 0.5 * len(rows)
    assert res["side"] >= 0.95, res["disagree_side"][:5]
    assert main([str(small_synthetic), "--show", "0"]) == 0
    assert "moves agree" in capsys.readouterr().out


def test_agreement_can_fail():
    """The metric is not vacuous: a backend that always answers 'both arms swing' is caught."""
    rows = [("m1", "a person kicks with the left leg.", {"arms": "No significant movement.",
                                                         "legs": "The left leg kicks."}),
            ("m2", "a person waves the right hand.", {"arms": "The right arm waves.",
                                                      "legs": "No significant movement."})]
    res = agreement(rows, lambda c: {"arms": "Both arms swing.", "legs": "Both legs walk."}, ["arms", "legs"])
    assert res["moves"] == 0 and res["side"] == 0
    assert part_side("The arms stay still, then the left arm waves.") == "left"
    assert part_side("The legs step sideways to the left.") == "both"
