"""TMA (party.methods.humantomato.tma): InfoNCE with the sentence-similarity filter, padding, losses."""
import math

import pytest
import torch
import torch.nn.functional as F

from party.methods.humantomato.tma import TMA, TMAConfig, info_nce, kl, sinusoidal

W = {"lambda_kl": 1e-5, "lambda_e": 1e-5, "lambda_nce": 0.1, "tau": 0.1, "filter_threshold": 0.85}


def test_filtered_pairs_leave_the_denominator():
    """Captions 0 and 2 are the same sentence (similarity 1): neither is the other's negative. The
    loss equals a brute-force loop whose softmax leaves those pairs out, in both directions."""
    g = torch.Generator().manual_seed(0)
    m, t = torch.randn(4, 8, generator=g), torch.randn(4, 8, generator=g)
    sim = torch.eye(4)
    sim[0, 2] = sim[2, 0] = 1.0
    sim[1, 3] = sim[3, 1] = 0.5                      # below the threshold: still a negative
    got = info_nce(m, t, 0.1, sim, 0.85)
    mn, tn = F.normalize(m, dim=-1), F.normalize(t, dim=-1)
    s = mn @ tn.t() / 0.1

    def one_way(s):
        total = 0.0
        for i in range(4):
            keep = [j for j in range(4) if j == i or not sim[i, j] > 0.85]
            total += -(s[i, i] - torch.logsumexp(s[i, keep], 0))
        return total / 4

    want = (one_way(s) + one_way(s.t())) / 2
    assert float(got) == pytest.approx(float(want), rel=1e-6)
    assert float(got) < float(info_nce(m, t, 0.1))   # the unfiltered loss counts the duplicate as a negative


def test_kl_and_positions():
    mu, lv = torch.randn(3, 5), torch.randn(3, 5) * 0.1
    assert float(kl(mu, lv, mu, lv)) == pytest.approx(0.0, abs=1e-6)
    assert float(kl(mu, lv, mu + 1, lv)) > 0
    pe = sinusoidal(10, 6)
    assert pe.shape == (10, 6) and float(pe[0, 1]) == 1.0 and float(pe[3, 0]) == pytest.approx(math.sin(3))


def tiny(seed=0, vae=True):
    torch.manual_seed(seed)
    return TMA(TMAConfig(motion_dim=7, text_dim=5, latent_dim=16, layers=1, heads=2, ff=32, dropout=0.0,
                         max_len=64, vae=vae))


def test_padding_is_ignored():
    m = tiny().eval()
    x, mask = torch.randn(2, 12, 7), torch.ones(2, 12, dtype=torch.bool)
    mask[1, 8:] = False
    y = x.clone()
    y[1, 8:] = 100.0                                 # garbage in the padding
    tok, tmask = torch.randn(2, 6, 5), torch.tensor([[1] * 6, [1] * 3 + [0] * 3], dtype=torch.bool)
    tok2 = tok.clone()
    tok2[1, 3:] = -50.0
    with torch.no_grad():
        assert torch.allclose(m.encode_motion(x, mask), m.encode_motion(y, mask), atol=1e-5)
        assert torch.allclose(m.encode_text(tok, tmask), m.encode_text(tok2, tmask), atol=1e-5)
        assert (m.decoder(m.encode_motion(x, mask), mask)[1, 8:] == 0).all()
    with pytest.raises(ValueError, match="tma.max_len"):
        m.encode_motion(torch.randn(1, 70, 7), torch.ones(1, 70, dtype=torch.bool))


def test_it_learns_to_retrieve():
    """Eight motion-text pairs: a few hundred steps align them (retrieval Top 1 = 1 both ways), and
    every loss term is finite and used."""
    g = torch.Generator().manual_seed(1)
    x, tok = torch.randn(8, 10, 7, generator=g), torch.randn(8, 4, 5, generator=g)
    mask, tmask = torch.ones(8, 10, dtype=torch.bool), torch.ones(8, 4, dtype=torch.bool)
    m = tiny(2)
    opt = torch.optim.AdamW(m.parameters(), lr=3e-3)
    first = None
    for _ in range(300):
        out = m.losses(x, mask, tok, tmask, {**W, "lambda_nce": 1.0})
        first = first if first is not None else {k: float(v.detach()) for k, v in out.items() if k.startswith("l_")}
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
    assert all(math.isfinite(v) for v in first.values()) and first["l_kl"] > 0
    assert float(out["l_nce"].detach()) < 0.2 * first["l_nce"] and float(out["l_rec"].detach()) < first["l_rec"]
    m.eval()
    with torch.no_grad():
        s = F.normalize(m.encode_motion(x, mask), dim=-1) @ F.normalize(m.encode_text(tok, tmask), dim=-1).t()
    assert torch.equal(s.argmax(1), torch.arange(8)) and torch.equal(s.argmax(0), torch.arange(8))


def test_without_vae_no_kl():
    m = tiny(vae=False)
    out = m.losses(torch.randn(2, 5, 7), torch.ones(2, 5, dtype=torch.bool), torch.randn(2, 3, 5),
                   torch.ones(2, 3, dtype=torch.bool), W)
    assert float(out["l_kl"]) == 0.0 and torch.isfinite(out["loss"])
