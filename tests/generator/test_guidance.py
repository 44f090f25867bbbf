"""Classifier-free guidance (generator.model.cond_drop, generator.generate.cond_scale): training on the
null condition, and guided generation = argmax of u + s (l - u) under every stream's teacher forcing."""
import pytest
import torch

from .tiny_spec import D_TEXT, VOCAB, build
from .test_generate import gen, targets


def cfg_model(kind, cond_drop=0.3):
    return build(kind, 0, {"dropout": 0.0, "cond_drop": cond_drop})


@pytest.mark.parametrize("kind", ["party", "holistic", "partwise"])
@pytest.mark.parametrize("scale,part_scale", [(2.5, None), (0.0, None), (1.0, 4.0), (2.0, 3.0)])
def test_guided_generation_is_the_argmax_of_the_guided_logits(kind, scale, part_scale):
    """Greedy guided generation fed back through teacher forcing with the text (l) and with the null
    condition (u): the argmax of u + s (l - u) (END suppressed before the target) is every generated
    token of every stream, s = part_scale in the Arms / Legs streams when given; cached and
    recomputed generation agree."""
    m, B = cfg_model(kind), 4
    c = torch.randn(B, D_TEXT, generator=torch.Generator().manual_seed(5))
    lengths = targets(B, 2)
    kw = {"cond_scale": scale, "part_cond_scale": part_scale}
    out = gen(m, c, lengths, "greedy", True, **kw)
    again = gen(m, c, lengths, "greedy", False, **kw)
    assert {s: [x.tolist() for x in v] for s, v in out.items()} == {s: [x.tolist() for x in v] for s, v in again.items()}
    n = {s: torch.tensor([len(x) for x in out[s]]) for s in out}
    codes = {s: torch.nn.functional.pad(torch.nn.utils.rnn.pad_sequence(out[s], batch_first=True,
                                                                        padding_value=VOCAB[s] + 1), (0, 1),
                                        value=VOCAB[s] + 1) for s in out}
    m.eval()
    with torch.no_grad():
        cond = m({"text_emb": c, "codes": codes, "lengths": n})
        null = m({"text_emb": torch.zeros_like(c), "codes": codes, "lengths": n})
    for s in out:
        assert not torch.allclose(cond[s], null[s]), s          # the text matters: the check can fail
        s_ = part_scale if part_scale is not None and s != "holistic" else scale
        guided = null[s] + s_ * (cond[s] - null[s])
        for b in range(B):
            lb = guided[b, :len(out[s][b])].clone()
            lb[:, VOCAB[s]] = float("-inf")
            assert lb.argmax(-1).tolist() == out[s][b].tolist(), (s, b)


def test_guidance_needs_a_model_trained_on_the_null_condition():
    m = cfg_model("party", cond_drop=0.0)
    with pytest.raises(ValueError, match="cond_drop"):
        gen(m, torch.randn(2, D_TEXT), None, "greedy", True, cond_scale=3.0)
    with pytest.raises(ValueError, match="cond_drop"):
        gen(m, torch.randn(2, D_TEXT), None, "greedy", True, part_cond_scale=3.0)
    with pytest.raises(ValueError, match="cond_drop"):
        build("party", 0, {"cond_drop": 1.0})


def test_training_replaces_dropped_texts_by_the_null_condition():
    """In training mode a cond_drop share of the rows sees zeros as its text; their logits equal the
    null condition's, and the PTG terms are computed on the kept rows only."""
    m, B = cfg_model("party", cond_drop=0.5), 16
    g = torch.Generator().manual_seed(3)
    c = torch.randn(B, D_TEXT, generator=g)
    lengths = targets(B, 4)
    codes = {s: torch.randint(0, VOCAB[s], (B, 20), generator=g) for s in VOCAB}
    batch = {"text_emb": c, "codes": codes, "lengths": lengths,
             "part_emb": {p: torch.randn(B, D_TEXT, generator=g) for p in ("arms", "legs")},
             "no_movement": {p: torch.rand(B, generator=g) < 0.3 for p in ("arms", "legs")}}
    m.train()
    torch.manual_seed(0)
    tf = m._teacher_forcing(batch)
    keep = tf["keep"]
    assert 0 < int(keep.sum()) < B
    m.eval()
    with torch.no_grad():
        ref = m._teacher_forcing({**batch, "text_emb": c * keep[:, None]})
    for s in tf["logits"]:
        assert torch.allclose(tf["logits"][s], ref["logits"][s], atol=1e-6), s
    m.train()
    torch.manual_seed(0)
    out = m.losses(batch)
    assert all(torch.isfinite(out[k]) for k in ("loss", "div", "aux"))
    kept = {k: v[keep] for k, v in batch.items() if k == "text_emb"}
    from party.methods.party.ptg import PartTextGrounding, diversity_loss
    cp, _, c_prime = m.ptg(kept["text_emb"])
    assert torch.allclose(out["div"], diversity_loss(c_prime, kept["text_emb"], m.spec.tau), atol=1e-6)
    aux = PartTextGrounding.aux_loss(cp, {p: e[keep] for p, e in batch["part_emb"].items()},
                                     {p: v[keep] for p, v in batch["no_movement"].items()}, kept["text_emb"])
    assert torch.allclose(out["aux"], aux, atol=1e-6)
    m.eval()
    assert m._teacher_forcing(batch)["keep"] is None            # no dropping outside training
