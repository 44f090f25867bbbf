"""Families vq and rvq (party.tokenizers.rvq): code layout, exact decode, residual levels, bits,
training through train_vqvae with per-level codebook health."""
import math

import pytest
import torch

from party.tokenizers import FAMILIES, Tokenizer, bits_per_frame, build_model
from party.tokenizers.rvq import ConvVQVAE, ResidualQuantizer, RVQVAE

CFG = {"family": "rvq", "window": 4, "codebook_size": 16, "code_dim": 8, "width": 16, "depth": 1,
       "dilation_growth": 3, "tail": "crop", "baseline_pool": "conv",
       "lte": {"enabled": False, "hidden": 8, "layers": 1}, "gte": {"enabled": False, "hidden": 8, "layers": 1,
                                                                     "adjacency": "full"},
       "quantizer": {"decay": 0.99, "reset_threshold": 1.0}, "rvq": {"levels": 3, "quantizer_dropout": 0.0}}


def test_families_registered_and_lte_refused():
    assert FAMILIES["rvq"] is RVQVAE and FAMILIES["vq"] is ConvVQVAE
    with pytest.raises(ValueError, match=r"vqvae\.model\.lte\.enabled=false"):
        build_model(5, {**CFG, "family": "vq", "lte": {**CFG["lte"], "enabled": True}})
    with pytest.raises(ValueError, match="rvq.levels"):
        build_model(5, {**CFG, "rvq": {"levels": 0, "quantizer_dropout": 0.0}})
    with pytest.raises(ValueError, match=r"vqvae\.families\.rvq"):
        build_model(5, {k: v for k, v in CFG.items() if k != "rvq"})


def test_rvq_codes_levels_padding_and_exact_decode():
    torch.manual_seed(0)
    m = build_model(5, CFG)
    x = torch.randn(3, 24, 5)
    m.train()
    m(torch.randn(16, 64, 5))     # initialises every codebook from 256 vectors (more than its 16 codes)
    m.eval()
    mask = torch.ones(3, 24, dtype=torch.bool)
    mask[1, 13:] = False                                # 3 whole groups of 4, then padding
    codes, node = m.encode(x, mask)
    assert codes.shape == (3, 6, 3) and m.levels == 3
    assert (codes[1, 3:] == -1).all() and (codes[1, :3] >= 0).all() and (codes[0] >= 0).all()
    out = m(x)
    assert torch.equal(out["idx"], m.encode(x)[0])
    assert torch.equal(out["recon"], m.decode(out["idx"]).float())  # eval forward = decoding the stored codes
    # each level quantizes what the levels before it left: the residual shrinks level by level
    with torch.no_grad():
        f = m.encoder(x)
    q = m.quantizer
    idx = q.nearest(f)
    partial = [sum(q.quantizers[i].dequantize(idx[..., i]) for i in range(k)) for k in (1, 2, 3)]
    err = [float((f - p).pow(2).mean()) for p in partial]
    assert err[0] > err[1] > err[2]


def test_rvq_gradients_and_dropout():
    torch.manual_seed(1)
    rq = ResidualQuantizer(2, 8, 4, 0.99, 1.0)
    z = torch.randn(20, 4, requires_grad=True)
    out = rq(z)
    assert out["idx"].shape == (20, 2) and len(out["usage"]) == 2
    (out["q"].sum() + out["loss_app"]).backward()
    assert z.grad is not None and z.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="quantizer_dropout"):
        ResidualQuantizer(2, 8, 4, 0.99, 1.0, dropout=1.0)


def test_bits_per_frame():
    m = build_model(5, {**CFG, "codebook_size": 512, "rvq": {"levels": 2, "quantizer_dropout": 0.0}})
    assert bits_per_frame(m) == pytest.approx(4.5)                       # RVQ 512x2 at x4 (SPEC §2.4)
    assert bits_per_frame(build_model(5, {**CFG, "family": "vq", "codebook_size": 512})) == pytest.approx(2.25)
    assert bits_per_frame(build_model(5, {**CFG, "family": "vq", "codebook_size": 4096})) == pytest.approx(3.0)
    m3 = build_model(5, {**CFG, "codebook_size": 512, "rvq": {"levels": 3, "quantizer_dropout": 0.0}})
    assert bits_per_frame(m3) == pytest.approx(3 * math.log2(512) / 4)


def test_rvq_trains_exports_and_extracts(tiny_prepared, tmp_path):
    """train_vqvae with family rvq: a (N, Q) token store, per-level codebook health in metrics.json,
    bits per frame, and a model.pt that loads back as the same family."""
    import json

    from party.stages import extract_tokens
    from party.tokenizers import TokenStore, load_tokenizer
    from party.tokenizers.train import train_tokenizer
    from tok_helpers import tiny_cfg

    cfg = tiny_cfg(tmp_path, tiny_prepared, **{"vqvae.model.family": "rvq", "vqvae.model.lte.enabled": False,
                                               "vqvae.model.gte.enabled": False, "vqvae.families.rvq.levels": 2})
    for s in ("holistic", "arms", "legs"):
        train_tokenizer(cfg, s, tmp_path / "tokenizers" / s)
    m = json.loads((tmp_path / "tokenizers/holistic/metrics.json").read_text())
    assert m["levels"] == 2 and m["bits_per_frame"] == pytest.approx(2 * math.log2(16) / 4)
    assert {"val/code_usage_l0", "val/code_usage_l1", "val/perplexity_l1"} <= set(m)
    tok = load_tokenizer(tmp_path / "tokenizers/holistic")
    assert isinstance(tok, Tokenizer) and tok.family == "rvq" and tok.levels == 2
    extract_tokens.run(cfg)
    store = TokenStore.open(tmp_path / "tokens/holistic")
    assert store.levels == 2 and store.meta["family"] == "rvq" and store.codes.shape[1] == 2


def test_family_settings_join_only_their_streams():
    """vqvae.families.rvq joins the model config of rvq streams only: a temporal_vq stream's config
    (its resume key and export) does not carry it."""
    from omegaconf import OmegaConf

    from party.tokenizers.config import stream_config
    vq = OmegaConf.create({"model": {"family": "temporal_vq", "window": 8}, "families": {"rvq": {"levels": 3}},
                           "tokenizers": {"a": {}, "b": {"family": "rvq"}}, "train": {}, "loss": {}, "optim": {}})
    assert "rvq" not in stream_config(vq, "a")["model"]
    assert stream_config(vq, "b")["model"]["rvq"] == {"levels": 3}
