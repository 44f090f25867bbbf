"""The ParCo-like method: the six-part split composes the feature vector exactly, the batched part
GPTs are causal, coordination is what lets one part's tokens reach another part's logits, and
generation (cached, recomputed, guided) is the model's own distribution."""
import numpy as np
import pytest
import torch

from party.methods.parco.model import ParcoGenerator, ParcoSpec
from party.motion.parts import PartLayout

PARTS = ["root", "right_leg", "left_leg", "backbone", "right_arm", "left_arm"]
VOCAB = {"root": 5, "right_leg": 7, "left_leg": 7, "backbone": 6, "right_arm": 7, "left_arm": 7}
D_TEXT = 12


def build(seed=0, coordinate=True, cond_drop=0.0, **kw) -> ParcoGenerator:
    torch.manual_seed(seed)
    cfg = dict(streams=PARTS, dim=16, layers=2, heads=2, coordinate=coordinate, coord_layers=2, coord_hidden=24,
               end_stream="root")
    cfg.update(kw)
    spec = ParcoSpec.from_config(dict(mlp_ratio=2, dropout=0.0, max_tokens=12, text_norm="none", cond_drop=cond_drop),
                                 cfg, VOCAB, {p: 8 for p in PARTS}, D_TEXT)
    model = ParcoGenerator(spec).eval()
    if coordinate:          # the fusion starts at zero: give it weights so that it does something
        for c in model.coord:
            torch.nn.init.normal_(c.mlp[-1].weight, 0.0, 0.2)
    return model


def batch(B=3, L=6, seed=1):
    g = torch.Generator().manual_seed(seed)
    n = torch.randint(2, L + 1, (B,), generator=g)
    codes = {p: torch.randint(0, VOCAB[p], (B, L), generator=g) for p in PARTS}
    return {"text_emb": torch.randn(B, D_TEXT, generator=g), "codes": codes, "lengths": {p: n for p in PARTS}}


def t2m_layout():
    import yaml
    cfg = yaml.safe_load(open("conf/dataset/parts/t2m.yaml"))
    return PartLayout.from_config(cfg, 22), cfg


def test_six_parts_compose_the_263_channels_exactly():
    layout, cfg = t2m_layout()
    assert cfg["part_tokenizers"] == PARTS
    x = np.random.default_rng(0).normal(size=(5, 40, 263)).astype(np.float64)
    pieces = {p: layout.slice(x, p) for p in PARTS}
    assert sum(v.shape[-1] for v in pieces.values()) > 263            # joint 9 in three parts
    np.testing.assert_array_equal(layout.merge(pieces), x)             # no base needed: every channel covered
    covered = np.concatenate([layout.index(p) for p in PARTS])
    assert set(covered.tolist()) == set(range(263))
    # a limb part alone has no root channels; its joints are recovered with the root at the origin
    assert layout.stream_joints("left_arm") == [0, 9, 13, 16, 18, 20]
    assert layout.stream_joints("root") == [0]


def test_part_tokenizers_table_is_checked():
    _, cfg = t2m_layout()
    with pytest.raises(ValueError, match="part_tokenizers"):
        PartLayout.from_config({**cfg, "part_tokenizers": PARTS[:-1]}, 22)
    with pytest.raises(ValueError, match="part_tokenizers"):
        PartLayout.from_config({**cfg, "part_tokenizers": [*PARTS[:-1], "arms"]}, 22)


@pytest.mark.parametrize("coordinate", [True, False])
def test_causal(coordinate):
    m, b = build(coordinate=coordinate), batch()
    ref = m(b)
    j = 3
    b2 = {**b, "codes": {p: c.clone() for p, c in b["codes"].items()}}
    for p in PARTS:
        b2["codes"][p][:, j:] = (b2["codes"][p][:, j:] + 1) % VOCAB[p]
    out = m(b2)
    # inputs at positions > j changed (position k+1 reads code k): outputs 0..j unchanged in every part
    torch.testing.assert_close(out[:, :, :j + 1], ref[:, :, :j + 1])


def test_coordination_shares_parts_and_independent_parts_do_not():
    b = batch(L=6)
    b2 = {**b, "codes": dict(b["codes"])}
    b2["codes"]["left_arm"] = (b["codes"]["left_arm"] + 1) % VOCAB["left_arm"]   # one part's tokens only
    n = int(b["lengths"]["root"].min())
    for coordinate in (True, False):
        m = build(coordinate=coordinate)
        with torch.no_grad():
            d = (m(b2) - m(b)).abs()[..., :n + 1, :].nan_to_num(0.0, 0.0, 0.0)
        other = [p for p in range(len(PARTS)) if PARTS[p] != "left_arm"]
        if coordinate:
            assert float(d[other].max()) > 1e-4          # the other parts read left_arm's tokens
        else:
            assert float(d[other].max()) == 0.0          # six independent GPTs
        assert float(d[PARTS.index("left_arm")].max()) > 1e-4


def test_codes_beyond_a_parts_codebook_are_never_predicted():
    m = build()
    logits = m(batch())
    for p, s in enumerate(PARTS):
        assert torch.isinf(logits[p, ..., VOCAB[s]:m.end]).all()
        assert torch.isfinite(logits[p, ..., :VOCAB[s]]).all()


def test_losses_and_accuracies():
    m = build().train()
    out = m.losses(batch())
    assert set(out) >= {"loss", "part", *[f"acc_{p}" for p in PARTS]}
    out["loss"].backward()
    assert all(p.grad is not None for p in m.parameters() if p.requires_grad)


@pytest.mark.parametrize("cond_drop,scale", [(0.0, 1.0), (0.2, 2.5)])
def test_cached_generation_equals_recomputed(cond_drop, scale):
    m, text = build(cond_drop=cond_drop), torch.randn(4, D_TEXT)
    kw = dict(sampling="sample", temperature=1.0, cond_scale=scale)
    a = m.generate(text, generator=torch.Generator().manual_seed(3), use_cache=True, **kw)
    b = m.generate(text, generator=torch.Generator().manual_seed(3), use_cache=False, **kw)
    for p in PARTS:
        for x, y in zip(a[p], b[p]):
            assert torch.equal(x, y)


def test_lengths_are_the_same_in_every_part_and_follow_the_target():
    m = build()
    target = torch.tensor([1, 4, 7])
    out = m.generate(torch.randn(3, D_TEXT), lengths={"root": target}, sampling="sample",
                     generator=torch.Generator().manual_seed(0))
    for p in PARTS:
        assert [len(r) for r in out[p]] == target.tolist()
        assert all(int(r.max()) < VOCAB[p] for r in out[p] if len(r))
    free = m.generate(torch.randn(5, D_TEXT), sampling="sample", generator=torch.Generator().manual_seed(1),
                      min_frames=24)
    n = [len(r) for r in free["root"]]
    assert all(k >= 3 for k in n)                     # ceil(24 / 8) codes before END may come
    assert all([len(r) for r in free[p]] == n for p in PARTS)


def test_guidance_scale_one_is_the_conditional_model():
    m, text = build(cond_drop=0.2), torch.randn(3, D_TEXT)
    a = m.generate(text, sampling="sample", generator=torch.Generator().manual_seed(5), cond_scale=1.0)
    b = m.generate(text, sampling="sample", generator=torch.Generator().manual_seed(5), cond_scale=1.0,
                   use_cache=False)
    assert all(torch.equal(x, y) for p in PARTS for x, y in zip(a[p], b[p]))
    with pytest.raises(ValueError, match="cond_drop"):
        build(cond_drop=0.0).generate(text, cond_scale=2.0)


def test_null_condition_logits_do_not_depend_on_the_caption():
    m, b = build(cond_drop=0.5), batch()
    zero = {**b, "text_emb": torch.zeros_like(b["text_emb"])}
    other = {**zero, "text_emb": torch.zeros_like(b["text_emb"])}
    torch.testing.assert_close(m(zero), m(other))
    assert not torch.allclose(m(b), m(zero))


def test_spec_checks():
    with pytest.raises(ValueError, match="one window"):
        ParcoSpec.from_config(dict(mlp_ratio=2, dropout=0.0, max_tokens=12, text_norm="none", cond_drop=0.0),
                              dict(streams=PARTS, dim=16, layers=1, heads=2, coordinate=True, coord_layers=1,
                                   coord_hidden=8, end_stream="root"),
                              VOCAB, {**{p: 8 for p in PARTS}, "root": 4}, D_TEXT)
    with pytest.raises(ValueError, match="end_stream"):
        build(end_stream="tail")
