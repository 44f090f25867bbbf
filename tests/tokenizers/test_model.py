"""VQ-VAE pieces on random tensors: shapes, round trips, LTE/GTE, quantizer EMA + reset."""
from __future__ import annotations

import pytest
import torch

from party.tokenizers.encoder import window_strides
from party.tokenizers.lit import lr_factor
from party.tokenizers.quantizer import EMAQuantizer
from party.tokenizers.temporal import (GlobalTemporalEnhancement, LocalTemporalEnhancement,
                                       normalized_adjacency)
from party.tokenizers.vqvae import VQVAE
from party.training import count_params as count_parameters

D = 21


def cfg(window, lte=True, gte=True, tail="crop", **kw):
    c = {"window": window, "codebook_size": 32, "code_dim": 8, "width": 16, "depth": 2,
         "dilation_growth": 3, "tail": tail, "baseline_pool": "conv",
         "lte": {"enabled": lte, "hidden": 8, "layers": 3, "per_position": False},
         "gte": {"enabled": gte, "hidden": 8, "layers": 3, "adjacency": "full", "residual": True},
         "quantizer": {"decay": 0.99, "reset_threshold": 1.0}}
    c.update(kw)
    return c


@pytest.mark.parametrize("window", [1, 4, 8, 12])
@pytest.mark.parametrize("temporal", [False, True])
def test_shapes_and_round_trip(window, temporal):
    torch.manual_seed(0)
    m = VQVAE(D, cfg(window, temporal, temporal))
    T = 5 * window + (window - 1)                 # not a multiple of w: crop drops the tail
    x = torch.randn(3, T, D)
    out = m(x)                                    # training mode (codebook init + EMA)
    assert out["recon"].shape == (3, 5 * window, D)
    assert out["idx"].shape == (3, 5) and out["frame_mask"].all()
    m.eval()
    idx, node_mask = m.encode(x)
    assert idx.shape == (3, 5) and node_mask.all() and idx.min() >= 0 and idx.max() < 32
    rec = m.decode(idx)
    assert rec.shape == (3, 5 * window, D)
    ev = m(x)
    assert torch.equal(ev["idx"], idx)
    assert torch.equal(ev["recon"], rec)          # eval forward == decode(encode(x)), bit for bit
    # decoded codes are the codebook vectors: re-encoding the group features is stable
    assert torch.equal(m.encode(x)[0], idx)


@pytest.mark.parametrize("window", [4, 8, 12])
def test_pad_tail_and_masks(window):
    torch.manual_seed(0)
    m = VQVAE(D, cfg(window, tail="pad")).eval()
    T = 3 * window + 1
    x = torch.randn(2, T, D)
    with torch.no_grad():
        out = m(x)
    assert out["idx"].shape == (2, 4)             # ceil(T / w)
    assert out["frame_mask"].sum(1).tolist() == [T, T]
    # a right-padded batch row: groups past its length are masked (-1), its padding is
    # filled with its own last frame, so the zeros put there by the caller never matter
    short = x[1, :T - window]
    mask = torch.arange(T)[None] < torch.tensor([[T], [T - window]])
    a = torch.stack([x[0], torch.cat([short, torch.zeros(window, D)])])
    b = torch.stack([x[0], torch.cat([short, torch.full((window, D), 7.0)])])
    idx, node_mask = m.encode(a, mask)
    assert node_mask.sum(1).tolist() == [4, 3] and (idx[1, 3:] == -1).all()
    assert torch.equal(m.encode(b, mask)[0], idx)


def test_too_short_for_window_is_an_error():
    m = VQVAE(D, cfg(8))
    with pytest.raises(ValueError, match="shorter than the window"):
        m(torch.randn(1, 7, D))


def test_window_strides_and_param_overhead():
    assert window_strides(4) == [2, 2] and window_strides(8) == [2, 2, 2] and window_strides(12) == [2, 2, 3]
    for w in (4, 8, 12):
        base = VQVAE(D, cfg(w, False, False))
        lte = VQVAE(D, cfg(w, True, False))
        both = VQVAE(D, cfg(w, True, True))
        # the frame-level encoder has exactly the baseline's conv parameters; LTE/GTE add their own
        assert count_parameters(lte) - count_parameters(base) == count_parameters(lte.lte)
        assert count_parameters(both) - count_parameters(lte) == count_parameters(both.gte)
        assert base.encoder.stride == w and lte.encoder.stride == 1


def test_baseline_avg_pool():
    m = VQVAE(D, cfg(12, False, False, baseline_pool="avg"))
    assert m(torch.randn(2, 24, D))["idx"].shape == (2, 2)


def test_lte_weights_sum_to_one_and_ignore_padding():
    torch.manual_seed(0)
    lte = LocalTemporalEnhancement(8, 4, hidden=8)
    f = torch.randn(2, 12, 8)
    mask = torch.ones(2, 12, dtype=torch.bool)
    mask[1, 10:] = False
    out, alpha = lte(f, mask)
    assert out.shape == (2, 3, 8)
    assert torch.allclose(alpha.sum(-1), torch.ones(2, 3))
    assert (alpha[1, 2, 2:] == 0).all()
    f2 = f.clone()
    f2[1, 10:] = 1e3                              # padded frames do not leak into the group feature
    assert torch.allclose(lte(f2, mask)[0], out)
    # output is a convex combination of the group's frames
    g = f.reshape(2, 3, 4, 8)
    assert torch.allclose(out, (alpha.unsqueeze(-1) * g).sum(2))


def test_lte_per_position_switch():
    torch.manual_seed(0)
    lte = LocalTemporalEnhancement(8, 4, hidden=8, per_position=True)
    with torch.no_grad():
        lte.slot.copy_(torch.randn(4, 8))
    f = torch.randn(1, 1, 8).repeat(1, 4, 1)      # identical frames: only the slot can tell them apart
    _, alpha = lte(f)
    assert not torch.allclose(alpha, torch.full_like(alpha, 0.25))
    _, alpha0 = LocalTemporalEnhancement(8, 4, hidden=8)(f)
    assert torch.allclose(alpha0, torch.full_like(alpha0, 0.25))


def test_normalized_adjacency():
    m = torch.tensor([[True, True, True, False]])
    full = normalized_adjacency(m, "full")[0]
    assert torch.allclose(full[:3, :3], torch.full((3, 3), 1 / 3))
    assert full[3, 3] == 1 and full[3, :3].abs().sum() == 0 and full[:3, 3].abs().sum() == 0
    chain = normalized_adjacency(torch.ones(1, 4, dtype=torch.bool), "chain")[0]
    assert torch.allclose(chain, chain.T) and chain[0, 2] == 0 and chain[0, 1] > 0
    assert torch.isclose(chain[0, 1], torch.tensor(1 / (2 * 3) ** 0.5))   # deg 2 and 3 with self-loops
    with pytest.raises(ValueError, match="adjacency"):
        normalized_adjacency(m, "ring")


@pytest.mark.parametrize("adjacency", ["full", "chain"])
def test_gte_masks_padding(adjacency):
    torch.manual_seed(0)
    gte = GlobalTemporalEnhancement(8, 8, 3, adjacency)
    x = torch.randn(1, 5, 8)
    mask = torch.tensor([[True, True, True, False, False]])
    y = gte(x, mask)
    x2 = x.clone()
    x2[0, 3:] = 50.0
    assert torch.allclose(gte(x2, mask)[0, :3], y[0, :3])
    assert torch.allclose(gte(x[:, :3])[0], y[0, :3], atol=1e-6)


def test_gte_full_graph_without_residual_collapses_nodes():
    torch.manual_seed(0)
    x = torch.randn(1, 6, 8)
    bare = GlobalTemporalEnhancement(8, 8, 3, "full", residual=False)(x)
    assert torch.allclose(bare[0], bare[0, :1].expand(6, 8), atol=1e-6)   # why residual defaults on
    res = GlobalTemporalEnhancement(8, 8, 3, "full", residual=True)(x)
    assert not torch.allclose(res[0], res[0, :1].expand(6, 8))


def test_quantizer_ema_moves_codes_to_cluster_means():
    torch.manual_seed(0)
    q = EMAQuantizer(4, 2, decay=0.9, reset_threshold=0.01)
    centers = torch.tensor([[5.0, 0], [-5, 0], [0, 5], [0, -5]])
    q.train()
    for _ in range(200):
        x = centers.repeat(64, 1) + 0.1 * torch.randn(256, 2)
        out = q(x)
    cb = q.codebook
    for c in centers:
        assert (cb - c).norm(dim=1).min() < 0.1
    assert out["perplexity"] > 3.9 and out["usage"] == 4


def test_quantizer_reset_revives_dead_codes():
    torch.manual_seed(0)
    q = EMAQuantizer(16, 2, decay=0.99, reset_threshold=1.0)
    x0 = torch.randn(512, 2)
    q.train()
    q(x0)                                         # init from data
    with torch.no_grad():                         # kill half the codebook: far away, zero counts
        q.codebook[8:] = 1e4
        q.code_sum[8:] = 0
        q.code_count[8:] = 0
    assert len(torch.unique(q.nearest(x0))) <= 8
    before = int(q.resets_total)
    out = q(torch.randn(512, 2))
    assert out["resets"] >= 8 and int(q.resets_total) - before == out["resets"]
    assert q.codebook.abs().max() < 100           # dead codes now sit on data
    for _ in range(30):
        out = q(torch.randn(512, 2))
    used = torch.unique(q.nearest(torch.randn(4096, 2)))
    assert len(used) == 16                         # every code is in use again
    # without resets (threshold 0) the dead codes would stay dead
    q2 = EMAQuantizer(16, 2, decay=0.99, reset_threshold=0.0)
    q2.train()
    q2(x0)
    with torch.no_grad():
        q2.codebook[8:] = 1e4
        q2.code_sum[8:] = 1e4
        q2.code_count[8:] = 1
    for _ in range(5):
        q2(torch.randn(512, 2))
    assert len(torch.unique(q2.nearest(torch.randn(4096, 2)))) <= 8


def test_quantizer_straight_through_and_eval_exact():
    torch.manual_seed(0)
    q = EMAQuantizer(8, 4)
    x = torch.randn(32, 4, requires_grad=True)
    q.train()
    out = q(x)
    (out["q"].sum() + out["loss_app"]).backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    q.eval()
    cb = q.codebook.clone()
    out = q(x.detach())
    assert torch.equal(out["q"], cb[out["idx"]]) and torch.equal(q.codebook, cb)   # no update in eval


def test_quantizer_is_fp32_under_bf16_autocast():
    """bf16-mixed training (vqvae.trainer.precision): the quantizer's distances, EMA sums and code
    assignment are those of fp32, whatever dtype the encoder hands it; the decoder's output is fp32."""
    torch.manual_seed(0)
    x = torch.randn(2048, 16)
    ref, amp = EMAQuantizer(64, 16), EMAQuantizer(64, 16)
    ref.train(), amp.train()
    torch.manual_seed(1)                          # the same codebook init (random rows of x)
    out_ref = ref(x)
    torch.manual_seed(1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out_amp = amp(x)
    assert torch.equal(out_amp["idx"], out_ref["idx"]) and out_amp["q"].dtype == torch.float32
    assert torch.equal(amp.code_sum, ref.code_sum) and torch.equal(amp.codebook, ref.codebook)
    m = VQVAE(D, cfg(8))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert m(torch.randn(2, 32, D))["recon"].dtype == torch.float32


def test_lr_schedule():
    o = {"lr": 2e-4, "lr_after": 1e-5, "milestone": 200000, "warmup_steps": 0}
    assert lr_factor(0, o) == 1.0 and lr_factor(199999, o) == 1.0
    assert lr_factor(200000, o) == pytest.approx(0.05)
    assert lr_factor(0, {**o, "warmup_steps": 10}) == pytest.approx(0.1)
