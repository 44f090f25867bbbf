"""PartyGenerator: spec, causality and the cycle schedule in teacher forcing, losses, switches,
PTG losses against SPEC's formulas, HPF cache == full, and a tiny model that overfits."""
import dataclasses
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from party.generator import KVCache
from party.methods.party.model import GeneratorSpec
from party.methods.party import schedule as S
from party.methods.party.hpf import HolisticPartFusion
from party.generator.layers import Transformer
from party.methods.party.ptg import PartTextGrounding, diversity_loss

from .tiny_spec import D_TEXT, LOSS, METHODS, MODEL, VOCAB, WINDOWS, build

REPO = Path(__file__).resolve().parents[2]


def make(kind="party", seed=0, model=None, **switches):
    return build(kind, seed, model, **switches).eval()


def make_batch(B=4, L_h=12, L_p=9, seed=1):
    g = torch.Generator().manual_seed(seed)
    n_h = torch.tensor([12, 7, 3, 10][:B])
    n_p = {"arms": torch.tensor([9, 4, 2, 6][:B]), "legs": torch.tensor([8, 5, 0, 9][:B])}
    codes = {"holistic": torch.randint(0, VOCAB["holistic"], (B, L_h), generator=g)}
    for p in ("arms", "legs"):
        codes[p] = torch.randint(0, VOCAB[p], (B, L_p), generator=g)
    for s, n in [("holistic", n_h), *n_p.items()]:                     # PAD-filled beyond the lengths
        codes[s] = torch.where(torch.arange(codes[s].shape[1])[None] < n[:, None], codes[s], VOCAB[s] + 1)
    return {"text_emb": torch.randn(B, D_TEXT, generator=g),
            "part_emb": {p: torch.randn(B, D_TEXT, generator=g) for p in ("arms", "legs")},
            "no_movement": {"arms": torch.tensor([True, False, False, True][:B]),
                            "legs": torch.tensor([False, False, True, False][:B])},
            "codes": codes, "lengths": {"holistic": n_h, **n_p}}


def with_codes(batch, stream, codes):
    b = dict(batch)
    b["codes"] = {**batch["codes"], stream: codes}
    return b


# ---------------------------------------------------------------------- spec
def test_spec_from_paper_config_has_no_defaults():
    cfg = OmegaConf.load(REPO / "conf/generator/paper.yaml")
    for name, meth in cfg.methods.items():
        if meth.family != "party":                 # the trivial baseline has no model (party.methods.random_codes)
            continue
        spec = GeneratorSpec.from_config(cfg.model, cfg.loss, meth, VOCAB, WINDOWS, 512)
        assert spec.kind == meth.kind and spec.dim == cfg.model.dim and spec.pg_window == cfg.model.pg_window
        assert spec.streams == {"party": ["holistic", "arms", "legs"], "holistic": ["holistic"],
                                "partwise": ["arms", "legs"]}[spec.kind]
    assert all(f.default is dataclasses.MISSING for f in dataclasses.fields(GeneratorSpec))
    model = {k: v for k, v in MODEL.items() if k != "pg_window"}
    with pytest.raises(KeyError):
        GeneratorSpec.from_config(model, LOSS, METHODS["party"], VOCAB, WINDOWS, D_TEXT)
    with pytest.raises(ValueError):
        make("holistic", pg=True)
    with pytest.raises(ValueError):
        make("party", ptg=False)                                           # aux without PTG


# ---------------------------------------------------------------------- causality
@pytest.mark.parametrize("kind", ["party", "holistic", "partwise"])
def test_changing_tokens_from_t_leaves_earlier_logits(kind):
    m, batch = make(kind), make_batch()
    base = m(batch)
    for s, lg in base.items():
        for t in (0, 2, 5):
            codes = batch["codes"][s].clone()
            codes[:, t:] = (codes[:, t:] + 1) % VOCAB[s]
            new = m(with_codes(batch, s, codes))[s]
            assert torch.equal(new[:, :t + 1], lg[:, :t + 1]), (s, t)       # logit j predicts code j
            assert not torch.allclose(new[:, t + 1:], lg[:, t + 1:]), (s, t)  # ... and later ones do change


@pytest.mark.parametrize("switches", [dict(), dict(hpf=False), dict(pg=False)], ids=["pg+hpf", "pg", "hpf"])
def test_holistic_sees_exactly_the_scheduled_part_tokens(switches):
    m, batch = make("party", **switches), make_batch()
    T, w_h, w_p = MODEL["pg_window"], WINDOWS["holistic"], WINDOWS["arms"]
    base = m(batch)["holistic"]
    n_h = batch["lengths"]["holistic"]
    for p in ("arms", "legs"):
        n_p = batch["lengths"][p]
        vis = S.part_visible(base.shape[1], T, w_h, w_p, n_p)                  # (B, L_h + 1)
        for k in range(batch["codes"][p].shape[1]):
            codes = batch["codes"][p].clone()
            codes[:, k] = (codes[:, k] + 1) % VOCAB[p]
            new = m(with_codes(batch, p, codes))["holistic"]
            for b in range(len(n_h)):
                if k >= n_p[b]:                                             # PAD there: nothing may change
                    assert torch.equal(new[b], base[b])
                    continue
                pos = torch.arange(int(n_h[b]) + 1)
                hidden, shown = pos[vis[b, pos] <= k], pos[vis[b, pos] > k]
                assert torch.equal(new[b, hidden], base[b, hidden]), (p, k, b)
                if len(shown):
                    assert (new[b, shown] - base[b, shown]).abs().amax(-1).min() > 1e-6, (p, k, b)


def test_without_pg_and_hpf_the_parts_do_not_reach_the_holistic_stream():
    m, batch = make("party", pg=False, hpf=False), make_batch()
    codes = (batch["codes"]["arms"] + 1) % VOCAB["arms"]
    assert torch.equal(m(with_codes(batch, "arms", codes))["holistic"], m(batch)["holistic"])


# ---------------------------------------------------------------------- losses
def test_losses_end_target_pad_ignored():
    m, batch = make("party"), make_batch()
    out, logits = m.losses(batch), m(batch)
    for k in ("loss", "hol", "part", "div", "aux"):
        assert out[k].dim() == 0 and torch.isfinite(out[k])
    # direct computation: targets codes[:n], END (= K) at n; nothing after n counts
    ce = {}
    for s, lg in logits.items():
        assert lg.shape[-1] == VOCAB[s] + 1 and lg.shape[1] == batch["codes"][s].shape[1] + 1
        terms = []
        for b, n in enumerate(batch["lengths"][s].tolist()):
            tgt = torch.cat([batch["codes"][s][b, :n], torch.tensor([VOCAB[s]])])
            terms.append(-torch.log_softmax(lg[b, :n + 1], -1).gather(1, tgt[:, None]).squeeze(1))
        ce[s] = torch.cat(terms).mean()
    assert torch.allclose(out["hol"], ce["holistic"], atol=1e-6)
    assert torch.allclose(out["part"], ce["arms"] + ce["legs"], atol=1e-6)
    assert torch.allclose(out["loss"], out["hol"] + out["part"] + 0.1 * out["div"] + 0.1 * out["aux"])
    # whatever sits in the PAD region is ignored
    junk = with_codes(batch, "holistic", torch.where(batch["codes"]["holistic"] == VOCAB["holistic"] + 1,
                                                     0, batch["codes"]["holistic"]))
    assert torch.equal(m.losses(junk)["loss"], out["loss"])
    assert set(out["gates"]) == {"arms", "legs"} and out["gates"]["arms"].shape == (4, MODEL["ptg_k"])
    assert not out["gates"]["arms"].requires_grad
    for s in VOCAB:
        assert 0 <= float(out[f"acc_{s}"]) <= 1


def test_switches_remove_terms_and_modules():
    full = make("party")
    pc, out = full.param_counts(), full.losses(make_batch())
    assert all(pc[k] > 0 for k in ("ptg", "holistic", "arms", "legs", "pg", "hpf"))
    for off, key in [("pg", "pg"), ("hpf", "hpf")]:
        less = make("party", **{off: False}).param_counts()
        assert less[key] == 0 and less["total"] == pc["total"] - pc[key]
    no_ptg = make("party", ptg=False, aux=False)
    o = no_ptg.losses(make_batch())
    assert no_ptg.param_counts()["ptg"] == 0 and float(o["div"]) == 0 and float(o["aux"]) == 0
    assert o["gates"] == {}
    no_aux = make("party", aux=False).losses(make_batch())
    assert float(no_aux["aux"]) == 0 and torch.allclose(no_aux["loss"], out["loss"] - 0.1 * out["aux"])
    hol = make("holistic")
    o = hol.losses(make_batch())
    assert float(o["part"]) == float(o["div"]) == float(o["aux"]) == 0 and "acc_arms" not in o
    assert hol.param_counts()["arms"] == 0 and hol.param_counts()["total"] == hol.param_counts()["holistic"]
    pw = make("partwise")
    o = pw.losses(make_batch())
    assert float(o["hol"]) == 0 and o["part"].item() > 0 and o["div"].item() > 0
    assert pw.param_counts()["holistic"] == 0 and "holistic" not in pw(make_batch())


def test_diversity_loss_equals_spec_formula():
    g = torch.Generator().manual_seed(3)
    c, cp, tau = torch.randn(5, 8, generator=g), torch.randn(5, 4, 8, generator=g), 0.05
    s = torch.nn.functional.cosine_similarity
    total = 0.0
    for b in range(5):
        for n in range(4):
            pos = torch.exp(s(cp[b, n], c[b], dim=0) / tau)
            neg = sum(torch.exp(s(cp[b, n], cp[b, m], dim=0) / tau) for m in range(4) if m != n)
            total += -torch.log(pos / (pos + neg))
    assert torch.allclose(diversity_loss(cp, c, tau), total / 20, rtol=1e-5)
    # and the model's "div" is that loss on its own c'
    m, batch = make("party"), make_batch()
    _, _, c_prime = m.ptg(batch["text_emb"])
    assert torch.allclose(m.losses(batch)["div"], diversity_loss(c_prime, batch["text_emb"], LOSS["tau"]))


def test_losses_stay_fp32_under_bf16_autocast():
    """bf16-mixed training (generator.trainer.precision): the diversity loss (cosines / tau = 0.05)
    is the fp32 one, the cross-entropies and the total come out fp32 and close to fp32's."""
    g = torch.Generator().manual_seed(3)
    c, cp = torch.randn(5, 8, generator=g), torch.randn(5, 4, 8, generator=g)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        d16 = diversity_loss(cp.bfloat16(), c, 0.05)
    assert d16.dtype == torch.float32 and torch.equal(d16, diversity_loss(cp.bfloat16().float(), c, 0.05))
    m, batch = make("party"), make_batch()
    m.eval()
    ref = m.losses(batch)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = m.losses(batch)
    for k in ("hol", "part", "loss"):
        assert out[k].dtype == torch.float32 and abs(float(out[k]) - float(ref[k])) < 0.02 * float(ref[k])


def test_aux_loss_uses_caption_where_no_movement():
    m, batch = make("party"), make_batch()
    c = batch["text_emb"]
    c_parts, gates, _ = m.ptg(c)
    for p in gates:
        assert torch.allclose(gates[p].sum(-1), torch.ones(4))
    expect = 0
    for p in ("arms", "legs"):
        rows = [(c_parts[p][b] - (c[b] if batch["no_movement"][p][b] else batch["part_emb"][p][b])).abs().mean()
                for b in range(4)]
        expect = expect + torch.stack(rows).mean()
    assert torch.allclose(PartTextGrounding.aux_loss(c_parts, batch["part_emb"], batch["no_movement"], c), expect)
    assert torch.allclose(m.losses(batch)["aux"], expect)
    # the part-text embedding of a "No significant movement" row is never read
    pe = {p: e.clone() for p, e in batch["part_emb"].items()}
    pe["arms"][0] += 5.0                                                   # arms row 0 is no_movement
    assert torch.equal(m.losses({**batch, "part_emb": pe})["aux"], m.losses(batch)["aux"])
    pe["arms"][1] += 5.0                                                   # row 1 is not
    assert not torch.equal(m.losses({**batch, "part_emb": pe})["aux"], m.losses(batch)["aux"])


# ---------------------------------------------------------------------- modules
def test_kv_cache():
    cache = KVCache(2, 3, 2, 5, 4, torch.float32, "cpu")
    k = torch.randn(3, 2, 2, 4)
    ka, va = cache.update(0, k, k + 1)
    assert ka.shape == (3, 2, 2, 4) and torch.equal(va, k + 1) and cache.length == 2
    ka, _ = cache.update(0, k[:, :, :1], k[:, :, :1])
    assert ka.shape[2] == 3 and torch.equal(cache.get(0)[0], ka)
    with pytest.raises(ValueError):
        cache.update(0, torch.randn(3, 2, 3, 4), torch.randn(3, 2, 3, 4))
    cache.reset()
    assert cache.length == 0 and cache.get(1)[0].shape[2] == 0


def test_transformer_incremental_equals_full():
    torch.manual_seed(0)
    tr = Transformer(16, 2, 4, 2, 0.0, 10).eval()
    x = torch.randn(3, 9, 16)
    full = tr(x)
    cache = tr.new_cache(3, x.dtype, x.device)
    steps = [tr(x[:, :4], 0, cache=cache)] + [tr(x[:, j:j + 1], j, cache=cache) for j in range(4, 9)]
    assert torch.allclose(torch.cat(steps, 1), full, atol=1e-5)


def test_hpf_incremental_equals_full_and_maps_respect_the_schedule():
    torch.manual_seed(0)
    T, w_h, w_p, B = 3, 8, 12, 2
    hpf = HolisticPartFusion(16, 2, 8, 0.0, ["arms", "legs"], 21).eval()
    h = torch.randn(B, 10, 16)
    tok = {"arms": torch.tensor([[1, 2, 3, 4, 5, 6, 0, 9, 9, 9, 9]] * B),
           "legs": torch.tensor([[1, 2, 3, 9, 9, 9, 9, 9, 9, 9, 9], [1, 2, 3, 4, 5, 6, 7, 8, 0, 1, 2]])}
    e = {p: torch.randn(B, 11, 16) for p in tok}
    parts = {p: (e[p], S.part_times(tok[p], 9, T, w_h, w_p)) for p in tok}
    h_time = S.holistic_times(B, 10, T, w_h, w_p)
    full, maps = hpf(h, h_time, parts, need_weights=True)
    cache, outs, k = hpf.start(B, h.dtype, h.device), [], 0
    for i in range(4):
        q = min(S.parts_generated(i, T, w_h, w_p), 11)
        hpf.add_parts(cache, {p: (e[p][:, k:q], parts[p][1][:, k:q]) for p in tok}, k)
        k = q
        for j in range(i * T, min((i + 1) * T, 10)):
            outs.append(hpf.step(cache, h[:, j:j + 1], j, h_time[:, j:j + 1]))
    assert torch.allclose(torch.cat(outs, 1), full, atol=1e-5)
    vis = S.part_visible(10, T, w_h, w_p, torch.tensor([2, 10]))           # legs of sample 0: 3 elements
    w = maps["legs"]                                                        # (B, heads, L_h, L_p)
    for b in range(B):
        for j in range(10):
            assert (w[b, :, j, vis[b, j]:] == 0).all() and (w[b, :, j, :vis[b, j]] > 0).all()
            assert torch.allclose(w[b, :, j].sum(-1), torch.ones(2))


def test_attention_maps_from_the_model():
    m, batch = make("party"), make_batch()
    maps = m.attention_maps(batch)
    assert maps["arms"].shape == (4, MODEL["hpf_heads"], 13, 10) and maps["self"].shape[-1] == 13 + 1 + 10 + 1 + 10
    with pytest.raises(ValueError):
        make("party", hpf=False).attention_maps(batch)


# ---------------------------------------------------------------------- training
def test_tiny_model_overfits_fixed_sequences():
    m = make("party", model=dict(dim=32, part_layers=1, holistic_layers=1)).train()
    batch = make_batch()
    opt = torch.optim.AdamW(m.parameters(), lr=3e-3)
    first = None
    for _ in range(100):
        out = m.losses(batch)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        first = first if first is not None else out["loss"].item()
    with torch.no_grad():
        last = m.losses(batch)
    assert float(last["loss"]) < 0.25 * first, (first, float(last["loss"]))
    assert float(last["acc_holistic"]) > 0.9 and float(last["acc_arms"]) > 0.9


def test_input_codes_replace_the_inputs_not_the_targets():
    m, batch = make("party"), make_batch()
    same = m.losses({**batch, "input_codes": batch["codes"]})
    assert torch.equal(same["loss"], m.losses(batch)["loss"])
    noisy = {s: torch.where(c < VOCAB[s], (c + 1) % VOCAB[s], c) for s, c in batch["codes"].items()}
    lg = m({**batch, "input_codes": noisy})
    fed = batch
    for s in noisy:
        fed = with_codes(fed, s, noisy[s])
    assert torch.equal(lg["holistic"], m(fed)["holistic"])                # the inputs are the noisy codes ...
    terms = []
    for b, n in enumerate(batch["lengths"]["holistic"].tolist()):         # ... the targets the clean ones
        tgt = torch.cat([batch["codes"]["holistic"][b, :n], torch.tensor([VOCAB["holistic"]])])
        terms.append(-torch.log_softmax(lg["holistic"][b, :n + 1], -1).gather(1, tgt[:, None]).squeeze(1))
    assert torch.allclose(m.losses({**batch, "input_codes": noisy})["hol"], torch.cat(terms).mean(), atol=1e-6)
