"""HumanTOMATO's Hierarchical-GPT (party.methods.humantomato.hgpt) and its alignment loss
(SPEC-humantomato §8 items 6, 7, 9, 10): the sequence layout and its 149 positions, slot-typed
heads with END only where a row starts, KV-cached generation equal to recomputation, relaxed codes
decoding as the tokenizer decodes, the StackedDecoder giving the module path's tokens, eta = 0 bit-identical to cross-entropy alone, and with eta > 0
gradients that reach the GPT and never the frozen tokenizer or TMA."""
import hashlib

import pytest
import torch
import yaml

from party.methods.humantomato.align import Aligner, relax
from party.methods.humantomato.hgpt import HGPTSpec, HierarchicalGPT
from party.methods.humantomato.tma import TMA, TMAConfig
from party.methods.humantomato.tma_train import TextFeatures
from party.tokenizers import build_tokenizer

K, D_TEXT = 11, 12
TABLES = yaml.safe_load(open("conf/dataset/parts/t2m.yaml"))["groups"]


def build(seed=0, order="coarse_first", groups=(0, 0, 1), guidance=False, cond_drop=0.0, max_tokens=9):
    torch.manual_seed(seed)
    entry = dict(stream="holistic", dim=16, layers=2, heads=2, mlp_ratio=2, order=order, guidance=guidance)
    spec = HGPTSpec.from_config(dict(dropout=0.0, max_tokens=max_tokens, text_norm="none", cond_drop=cond_drop),
                                entry, groups, len(groups) - 1, K, 4, D_TEXT)
    return HierarchicalGPT(spec).eval()


def batch(B=3, n=5, Q=3, seed=1):
    g = torch.Generator().manual_seed(seed)
    rows = torch.randint(1, n + 1, (B,), generator=g)
    rows[0] = n
    return {"text_emb": torch.randn(B, D_TEXT, generator=g), "codes": {"holistic": torch.randint(0, K, (B, n, Q), generator=g)},
            "lengths": {"holistic": rows}, "caption": [f"a person does thing {i}" for i in range(B)]}


def test_layout_text_codes_end_and_149_positions():
    m = build()
    codes = torch.arange(12).view(1, 4, 3)                 # rows [c0 c1 a0] [c2 c3 a1] ...
    y = m.flatten(codes, torch.tensor([3]))
    assert y.tolist() == [[0, 1, 2, 3, 4, 5, 6, 7, 8, K, K + 1, K + 1, K + 1]]
    f = build(order="fine_first").flatten(codes, torch.tensor([2]))
    assert f.tolist()[0][:7] == [2, 0, 1, 5, 3, 4, K]       # the arms code first in every row
    paper = HGPTSpec.from_config(dict(dropout=0.1, max_tokens=50, text_norm="none", cond_drop=0.0),
                                 dict(stream="h", dim=8, layers=1, heads=1, mlp_ratio=1, order="coarse_first",
                                      guidance=False), [0, 0, 1], 2, 512, 4, 8)
    assert HierarchicalGPT(paper).positions + 1 == 149     # TEXT + 49 rows of 3 codes (inputs) + END (output)


def test_causal_and_end_only_where_a_row_starts():
    m = build()
    b = batch()
    logits, y = m.teacher_forcing(b)
    b2 = {**b, "codes": {"holistic": b["codes"]["holistic"].clone()}}
    b2["codes"]["holistic"][:, 3:] = (b2["codes"]["holistic"][:, 3:] + 1) % K     # change rows 3.. only
    logits2, _ = m.teacher_forcing(b2)
    assert torch.equal(logits[:, :10], logits2[:, :10])        # outputs 0..9 read inputs 0..9 (rows < 3)
    assert not torch.equal(logits, logits2)
    end = logits[..., K]
    pos = torch.arange(logits.shape[1])
    assert torch.isinf(end[:, pos % 3 != 0]).all() and torch.isfinite(end[:, pos % 3 == 0]).all()
    assert torch.isfinite(logits[..., :K]).all()


def test_slot_heads_and_group_tables_are_their_own():
    m = build()
    with torch.no_grad():
        m.head[2].zero_()                                   # the arms slot's head
    logits, _ = m.teacher_forcing(batch())
    pos = torch.arange(logits.shape[1])
    assert (logits[:, pos % 3 == 2, :K] == 0).all() and (logits[:, pos % 3 != 2, :K] != 0).any()
    ids = m.embed(torch.tensor([[3, 3, 3]]), 0)            # code 3 as core-a, core-b, arms
    assert not torch.equal(ids[0, 0], ids[0, 2]) and not torch.equal(ids[0, 0], ids[0, 1])


def test_losses_code_logits_and_rows_order():
    m = build(order="fine_first").train()
    b = batch()
    out = m.losses(b)
    assert set(out) >= {"loss", "ce", "acc_holistic"} and "align" not in out
    out["loss"].backward()
    assert all(p.grad is not None for p in m.parameters())
    logits, y = m.teacher_forcing(b)
    onehot = torch.nn.functional.one_hot(y.clamp(max=K), K + 1).float()          # logits that name the targets
    code = m.code_logits(onehot, 5).argmax(-1)
    rows = b["lengths"]["holistic"]
    valid = torch.arange(5)[None] < rows[:, None]
    assert torch.equal(code[valid], b["codes"]["holistic"][valid])                # back in the store's order


@pytest.mark.parametrize("order,guidance,cond_drop,scale", [("coarse_first", False, 0.0, 1.0),
                                                             ("fine_first", True, 0.2, 2.5)])
def test_cached_generation_equals_recomputed(order, guidance, cond_drop, scale):
    m, text = build(order=order, guidance=guidance, cond_drop=cond_drop), torch.randn(4, D_TEXT)
    kw = dict(sampling="sample", temperature=1.0, cond_scale=scale)
    a = m.generate(text, generator=torch.Generator().manual_seed(3), use_cache=True, **kw)["holistic"]
    b = m.generate(text, generator=torch.Generator().manual_seed(3), use_cache=False, **kw)["holistic"]
    c = m.generate(text, generator=torch.Generator().manual_seed(3), use_cache=True, decoder="modules", **kw)["holistic"]
    assert [x.shape for x in a] == [y.shape for y in b] == [y.shape for y in c]
    assert all(torch.equal(x, y) and torch.equal(x, z) for x, y, z in zip(a, b, c))
    assert all(x.shape[1] == 3 and 0 <= x.min() and x.max() < K for x in a if len(x))


def test_target_rows_min_frames_and_no_guidance_ignores_the_scale():
    m = build()
    text = torch.randn(3, D_TEXT)
    out = m.generate(text, lengths={"holistic": torch.tensor([1, 4, 8])}, generator=torch.Generator().manual_seed(0))
    assert [len(r) for r in out["holistic"]] == [1, 4, 8]
    free = m.generate(text.repeat(8, 1), min_frames=20, generator=torch.Generator().manual_seed(1))["holistic"]
    assert all(5 <= len(r) <= 8 for r in free)                 # >= ceil(20 / 4) rows, <= max_tokens - 1
    a = m.generate(text, cond_scale=3.0, generator=torch.Generator().manual_seed(2))["holistic"]
    b = m.generate(text, cond_scale=1.0, generator=torch.Generator().manual_seed(2))["holistic"]
    assert all(torch.equal(x, y) for x, y in zip(a, b))        # guidance: false is the paper's: no CFG
    with pytest.raises(ValueError, match="cond_drop"):
        build(guidance=True).generate(text, cond_scale=2.0)
    with pytest.raises(ValueError, match=r"\[1, 8\]"):
        m.generate(text, lengths={"holistic": torch.tensor([1, 9, 2])})


def test_spec_checks():
    with pytest.raises(ValueError, match="divisible"):
        HGPTSpec.from_config(dict(dropout=0.0, max_tokens=9, text_norm="none", cond_drop=0.0),
                             dict(stream="h", dim=15, layers=1, heads=2, mlp_ratio=1, order="coarse_first",
                                  guidance=False), [0, 0, 1], 2, K, 4, D_TEXT)
    with pytest.raises(ValueError, match="slot_groups"):
        build(groups=(0, 2))


# ---------------------------------------------------------------------------------------------- L_align

def h2vq_tokenizer(seed=0, rates=(2, 4), table="core_arms"):
    torch.manual_seed(seed)
    mcfg = {"family": "h2vq", "window": 4, "codebook_size": K, "code_dim": 8, "width": 16, "depth": 1,
            "dilation_growth": 3, "tail": "crop", "baseline_pool": "conv",
            "quantizer": {"decay": 0.99, "reset_threshold": 1.0},
            "h2vq": {"table": TABLES[table], "fine": "arms", "rates": {"coarse": rates[0], "fine": rates[1]},
                     "transform": "linear", "fusion_kernel": 3}}
    meta = {"stream": "holistic", "feat_dim": 263, "n_joints": 22, "feat_index": list(range(263)),
            "stream_joints": list(range(22))}
    tok = build_tokenizer(263, mcfg, torch.zeros(263), torch.ones(263), meta)
    with torch.no_grad():
        for q in (tok.model.q_fine, tok.model.q_coarse, *tok.model.q_mid):
            q.codebook.normal_()
    return tok.eval()


def conv_tokenizer(family, levels=1):
    torch.manual_seed(0)
    mcfg = {"family": family, "window": 4, "codebook_size": K, "code_dim": 8, "width": 16, "depth": 1,
            "dilation_growth": 3, "tail": "crop", "baseline_pool": "conv", "lte": {"enabled": False},
            "gte": {"enabled": False}, "quantizer": {"decay": 0.99, "reset_threshold": 1.0},
            "rvq": {"levels": levels, "quantizer_dropout": 0.0}}
    meta = {"stream": "holistic", "feat_dim": 263, "n_joints": 22, "feat_index": list(range(263)),
            "stream_joints": list(range(22))}
    tok = build_tokenizer(263, mcfg, torch.zeros(263), torch.ones(263), meta)
    with torch.no_grad():
        for m in tok.model.modules():
            if hasattr(m, "codebook"):
                m.codebook.normal_()
    return tok.eval()


@pytest.mark.parametrize("make,Q", [(h2vq_tokenizer, 3), (lambda: h2vq_tokenizer(table="core3"), 5),
                                    (lambda: conv_tokenizer("vq"), 1),
                                    (lambda: conv_tokenizer("rvq", 2), 2)])
def test_one_hot_weights_decode_as_the_codes(make, Q):
    tok = make()
    codes = torch.randint(0, K, (2, 5, Q))
    codes[1, 3:] = -1                                          # padded rows: zero weights
    w = torch.nn.functional.one_hot(codes.clamp(min=0), K).float() * (codes >= 0)[..., None]
    want = tok.decode(codes if Q > 1 else codes[..., 0])
    assert torch.allclose(tok.decode_weights(w), want, atol=1e-5)


class StubEncoder:
    """A text encoder's two calls TMA reads, deterministic per caption."""
    id = "stub"

    def _vec(self, c, d, salt):
        g = torch.Generator().manual_seed(int(hashlib.sha1((salt + c).encode()).hexdigest()[:8], 16))
        return torch.randn(d, generator=g)

    def encode_tokens(self, caps):
        return torch.stack([torch.stack([self._vec(f"{c}{i}", 6, "t") for i in range(4)]) for c in caps]), \
            torch.full((len(caps),), 4)

    def encode(self, caps):
        return torch.stack([self._vec(c, 5, "s") for c in caps])


def aligner(eta, how="gumbel_st"):
    torch.manual_seed(5)
    tma = TMA(TMAConfig(motion_dim=263, text_dim=6, latent_dim=16, layers=1, heads=2, ff=32, dropout=0.1,
                        max_len=64, vae=True))
    meta = {"feat_dim": 263, "mean": [0.0] * 263, "std": [1.0] * 263, "max_text_tokens": 8}
    return Aligner(h2vq_tokenizer(), tma, meta, TextFeatures(StubEncoder(), 8), eta, how, 1.0, 0.1, 0.85)


def digest(module) -> str:
    h = hashlib.sha256()
    for k, v in sorted(module.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _steps(model, n=3):
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    model.train()
    for i in range(n):
        opt.zero_grad()
        model.losses(batch(seed=10 + i))["loss"].backward()
        opt.step()
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_eta_zero_trains_bit_identically_to_cross_entropy_alone():
    plain = _steps(build())
    m = build()
    m.aligner = aligner(0.0)
    assert all(torch.equal(plain[k], v) for k, v in _steps(m).items())
    assert set(plain) == set(m.state_dict())                 # the aligner is no part of the saved model


@pytest.mark.parametrize("how", ["gumbel_st", "soft", "argmax_st"])
def test_eta_positive_reaches_the_gpt_and_leaves_the_frozen_models(how):
    m = build()
    m.aligner = a = aligner(0.1, how)
    frozen = digest(a.tokenizer), digest(a.tma)
    m.train()
    out = m.losses(batch())
    assert torch.isfinite(out["align"]) and out["align"] > 0
    out["align"].backward()                                   # L_align alone
    assert m.head.grad is not None and m.head.grad.abs().sum() > 0
    assert m.net.blocks[0].attn.qkv.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in [*a.tokenizer.parameters(), *a.tma.parameters()])
    _steps(m)
    assert (digest(a.tokenizer), digest(a.tma)) == frozen
    assert not a.tma.training and not a.tokenizer.training


def test_relaxations():
    g = torch.randn(4, 7)
    for how in ("gumbel_st", "soft", "argmax_st"):
        w = relax(g, how)
        assert torch.allclose(w.sum(-1), torch.ones(4))
    assert torch.equal(relax(g, "argmax_st").argmax(-1), g.argmax(-1))
    hard = relax(g, "gumbel_st").detach()                    # forward: one code per row
    assert torch.allclose(hard, torch.nn.functional.one_hot(hard.argmax(-1), 7).float(), atol=1e-6)
    with pytest.raises(ValueError, match="relax"):
        relax(g, "nope")


def tma_text_model(seed=0):
    """A GPT whose text token is a frozen TMA's mu_t (text: tma), with that TextPrior attached."""
    from party.methods.humantomato.align import TextPrior
    torch.manual_seed(9)
    tma = TMA(TMAConfig(motion_dim=263, text_dim=6, latent_dim=16, layers=1, heads=2, ff=32, dropout=0.1,
                        max_len=64, vae=True))
    prior = TextPrior(tma, TextFeatures(StubEncoder(), 8))
    torch.manual_seed(seed)
    entry = dict(stream="holistic", dim=16, layers=2, heads=2, mlp_ratio=2, order="coarse_first", guidance=False,
                 text="tma")
    spec = HGPTSpec.from_config(dict(dropout=0.0, max_tokens=9, text_norm="none", cond_drop=0.0),
                                entry, (0, 0, 1), 2, K, 4, prior.dim)
    m = HierarchicalGPT(spec).eval()
    m.text_source = prior
    return m, prior


def test_tma_text_token_reads_the_captions_through_the_frozen_prior():
    m, prior = tma_text_model()
    b = batch()
    mu = prior(b["caption"])
    assert mu.shape == (3, 16)
    assert torch.equal(prior(list(reversed(b["caption"]))), mu.flip(0))          # per caption, cached
    want = prior.tma.encode_text(*[t for t in prior.text.tokens(b["caption"][:1])])
    assert torch.allclose(mu[:1], want, atol=1e-6)
    logits, _ = m.teacher_forcing(b)
    other = {**b, "text_emb": torch.randn_like(b["text_emb"])}                   # the platform vector is unread
    assert torch.equal(m.teacher_forcing(other)[0], logits)
    swapped = {**b, "caption": ["a person jumps high"] + b["caption"][1:]}
    diff = (m.teacher_forcing(swapped)[0] - logits).nan_to_num().abs().sum((1, 2))   # -inf END logits: nan
    assert diff[0] > 0 and diff[1:].eq(0).all()                                   # the caption is read
    frozen = digest(prior.tma)
    m.train()
    m.losses(b)["loss"].backward()
    assert all(p.grad is None for p in prior.tma.parameters()) and digest(prior.tma) == frozen
    assert set(m.state_dict()) == set(build().state_dict())        # the prior is no part of the saved model
    assert m.text.weight.shape == (16, 16)                    # Linear(latent -> dim)


def test_tma_text_method_needs_the_captions():
    from party.methods.humantomato.family import HGPTMethod
    from party.generator.generate import generate_batches
    m, prior = tma_text_model()
    meth = HGPTMethod(m, {"method": "humantomato"}, ["holistic"], 9)
    assert meth.reads_captions
    with pytest.raises(ValueError, match="texts"):
        generate_batches(meth, torch.zeros(3, D_TEXT).numpy(), None, _gcfg(), False)
    caps = ["a person waves", "a person kicks", "a person sits"]
    a = meth.codes(torch.zeros(3, D_TEXT), None, _gcfg(), torch.Generator().manual_seed(0), texts=caps)
    b = meth.codes(torch.randn(3, D_TEXT), None, _gcfg(), torch.Generator().manual_seed(0), texts=caps)
    assert all(torch.equal(x, y) for x, y in zip(a["holistic"], b["holistic"]))   # the captions decide
    with pytest.raises(ValueError, match="captions"):
        meth.codes(torch.zeros(3, D_TEXT), None, _gcfg(), torch.Generator().manual_seed(0))


def _gcfg():
    from omegaconf import OmegaConf
    return OmegaConf.create(dict(sampling="sample", temperature=1.0, top_k=None, top_p=None, use_cache=True,
                                 cond_scale=1.0, part_cond_scale=None, min_frames=None, batch_size=2, seed=0))


def test_core3_rows_read_write_and_align():
    """An H²VQ over core3 (torso x2, legs x2, arms): the GPT reads its slot layout (three codebooks,
    the arms slot last), generates five-code rows with each slot in its own book, and L_align
    decodes its relaxed rows with gradients reaching the GPT."""
    from party.methods.humantomato.family import slot_layout
    tok = h2vq_tokenizer(table="core3")
    groups, fine = slot_layout(tok)
    assert (groups, fine) == ([0, 0, 2, 2, 1], 4)
    torch.manual_seed(0)
    entry = dict(stream="holistic", dim=16, layers=2, heads=2, mlp_ratio=2, order="fine_first", guidance=False)
    m = HierarchicalGPT(HGPTSpec.from_config(dict(dropout=0.0, max_tokens=9, text_norm="none", cond_drop=0.0),
                                             entry, groups, fine, K, 4, D_TEXT))
    assert m.spec.groups == 3 and m.spec.perm == [4, 0, 1, 2, 3]
    rows = m.generate(torch.randn(3, D_TEXT), generator=torch.Generator().manual_seed(1))["holistic"]
    assert all(r.shape[1] == 5 and 0 <= r.min() and r.max() < K for r in rows if len(r))
    torch.manual_seed(5)
    tma = TMA(TMAConfig(motion_dim=263, text_dim=6, latent_dim=16, layers=1, heads=2, ff=32, dropout=0.1,
                        max_len=64, vae=True))
    meta = {"feat_dim": 263, "mean": [0.0] * 263, "std": [1.0] * 263, "max_text_tokens": 8}
    m.aligner = Aligner(tok, tma, meta, TextFeatures(StubEncoder(), 8), 0.1, "gumbel_st", 1.0, 0.1, 0.85)
    m.train()
    out = m.losses(batch(Q=5))
    out["loss"].backward()
    assert torch.isfinite(out["align"]) and m.head.grad.abs().sum() > 0
