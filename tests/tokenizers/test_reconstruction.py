"""Tokenizers must reconstruct, not decode the mean pose (issue: collapsed tokenizers).

Trains a small tokenizer with the default CPU recipe's loss terms and schedule
shape (``conf/vqvae/cpu.yaml``, scaled down) on controlled synthetic motions and
checks what a collapsed autoencoder fails: a raised hand and arms down decode
to different poses; the error is a fraction of the mean-pose baseline's; codes
decode to different poses. The diagnostics must also flag a collapsed model.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from party.motion.features import recover_from_ric
from party.tokenizers import diagnostics, load_tokenizer

from tok_helpers import CONF, tiny_cfg
from recon_fixture import DOWN, RAISED, write_recon_dataset

L_WRIST, L_SHOULDER = 20, 16
RUN = int(OmegaConf.load(CONF / "vqvae" / "paper.yaml").diagnostics.code_run_length)


def recipe_cfg(tmp, prepared, **over):
    """tiny_cfg with the default recipe's loss/optimiser/quantizer settings (cpu.yaml)."""
    cpu = OmegaConf.load(CONF / "vqvae" / "cpu.yaml")
    cfg = tiny_cfg(tmp, prepared)
    for key in ("loss", "optim"):
        cfg.vqvae[key] = OmegaConf.merge(cfg.vqvae[key], cpu.get(key, {}))
    if "quantizer" in cpu.get("model", {}):
        cfg.vqvae.model.quantizer = OmegaConf.merge(cfg.vqvae.model.quantizer, cpu.model.quantizer)
    small = {"vqvae.model.width": 64, "vqvae.model.depth": 1, "vqvae.model.code_dim": 32,
             "vqvae.model.lte.hidden": 32, "vqvae.model.gte.hidden": 32,
             "vqvae.tokenizers.holistic.codebook_size": 64, "vqvae.tokenizers.holistic.code_dim": 32,
             "vqvae.tokenizers.holistic.window": 4,
             "vqvae.train.max_steps": 400, "vqvae.train.batch_size": 16, "vqvae.train.crop": 32,
             "vqvae.train.val_every": 400, "vqvae.train.ckpt_every": 400,
             "vqvae.optim.milestone": 300, "vqvae.train.threads": 2,
             "vqvae.eval.split": "train", **over}   # capacity, not generalisation: score the training clips
    cfg.merge_with(OmegaConf.from_dotlist([f"{k}={v}" for k, v in small.items()]))
    return cfg


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from party.tokenizers.train import train_tokenizer
    tmp = tmp_path_factory.mktemp("recon")
    prepared = write_recon_dataset(tmp)
    cfg = recipe_cfg(tmp, prepared)
    metrics = train_tokenizer(cfg, "holistic", tmp / "tokenizers" / "holistic")
    return cfg, load_tokenizer(tmp / "tokenizers" / "holistic"), metrics


def _decoded_joints(tok, cfg, clip_id):
    import json
    from pathlib import Path
    index = json.loads((Path(cfg.paths.prepared) / "index.json").read_text())
    raw = torch.as_tensor(np.load(Path(index["root"]) / "new_joint_vecs" / f"{clip_id}.npy"))
    rec = tok.detokenize(tok.tokenize(raw))
    return (recover_from_ric(raw[:len(rec)].double(), 22).numpy(),
            recover_from_ric(rec.double(), 22).numpy())


def _wrist_over_shoulder(j):
    return float(np.mean(j[:, L_WRIST, 1] - j[:, L_SHOULDER, 1]))


@pytest.mark.slow
def test_raised_hand_and_arms_down_decode_differently(trained):
    cfg, tok, _ = trained
    gt_up, rec_up = _decoded_joints(tok, cfg, RAISED)
    gt_dn, rec_dn = _decoded_joints(tok, cfg, DOWN)
    gap_gt = _wrist_over_shoulder(gt_up) - _wrist_over_shoulder(gt_dn)
    gap_rec = _wrist_over_shoulder(rec_up) - _wrist_over_shoulder(rec_dn)
    assert gap_gt > 0.3                      # the fixture: the raised wrist is well above
    assert gap_rec > 0.4 * gap_gt, (gap_rec, gap_gt)   # collapsed (paper loss at this budget): ~0.03


@pytest.mark.slow
def test_error_is_a_fraction_of_the_mean_pose_baseline(trained):
    _, _, metrics = trained
    d = metrics["diagnostics"]
    assert d["mpjpe_meanpose_mm"] > 0
    assert d["mpjpe_ratio"] < 0.5, d
    assert d["status"] == "ok"


@pytest.mark.slow
def test_decoded_pose_varies_across_codes(trained):
    _, tok, metrics = trained
    d = metrics["diagnostics"]
    assert d["code_spread_ratio"] > 0.3, d
    assert d["code_spread"] == pytest.approx(diagnostics.code_spread(tok.model, RUN))


def test_verdict_flags_a_collapsed_tokenizer():
    cfg = {"max_baseline_ratio": 0.75, "min_code_spread": 0.1}
    val = {"val/mpjpe_mm": 88.0, "val/mpjpe_meanpose_mm": 98.0, "val/code_usage": 0.4,
           "val/perplexity": 60.0}
    bad = diagnostics.verdict(val, spread=0.05, data_std=1.0, cfg=cfg)
    assert bad["status"] == "collapsed" and len(bad["reasons"]) == 2
    assert "mean-pose baseline" in diagnostics.banner("holistic", bad)
    good = diagnostics.verdict({**val, "val/mpjpe_mm": 30.0}, spread=0.7, data_std=1.0, cfg=cfg)
    assert good["status"] == "ok" and diagnostics.banner("holistic", good) == ""


def test_code_spread_of_a_constant_decoder_is_zero():
    from party.tokenizers.vqvae import VQVAE
    cfg = OmegaConf.to_container(OmegaConf.load(CONF / "vqvae" / "paper.yaml").model)
    cfg.update(width=16, depth=1, code_dim=8, codebook_size=16, window=4)
    cfg["lte"]["hidden"] = cfg["gte"]["hidden"] = 8
    m = VQVAE(20, cfg)
    torch.nn.init.normal_(m.quantizer.codebook)
    assert diagnostics.code_spread(m, RUN) > 0
    last = m.decoder.net[-1]
    torch.nn.init.zeros_(last.weight)
    assert diagnostics.code_spread(m, RUN) == pytest.approx(0.0, abs=1e-7)


def test_collapsed_run_fails_the_stage_after_writing_outputs(tmp_path, monkeypatch):
    """train_vqvae's run(): a collapsed tokenizer (too few steps to leave the mean pose) keeps
    its outputs but fails loudly (on_collapse=error), or only warns (on_collapse=warn)."""
    from party.stages import train_vqvae
    prepared = write_recon_dataset(tmp_path)
    cfg = recipe_cfg(tmp_path, prepared, **{"vqvae.train.max_steps": 2, "vqvae.train.val_every": 2,
                                            "vqvae.train.ckpt_every": 2, "vqvae.train.threads": 1})
    cfg.vqvae.stream = "holistic"
    with pytest.raises(RuntimeError, match="collapsed.*mean-pose baseline"):
        train_vqvae.run(cfg)
    out = tmp_path / "tokenizers" / "holistic"
    assert (out / "model.pt").exists() and (out / "metrics.json").exists()
    cfg.vqvae.diagnostics.on_collapse = "warn"
    assert train_vqvae.run(cfg)["diagnostics"]["status"] == "collapsed"
