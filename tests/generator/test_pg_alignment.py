"""Part Guidance aligned with its cycle (``generator.model.pg_align: overlap``, ``pg_lookahead``) and
guidance of the whole body (``generator.model.null_condition: whole_body``), SPEC §3 Decision."""
import pytest
import torch

from party.methods.party import schedule as S
from party.methods.party.model import _sequences

from .test_generate import gen
from .test_model import make_batch, with_codes
from .tiny_spec import D_TEXT, VOCAB, WINDOWS, build

PAPER = {"pg_lookahead": 0, "pg_align": "overlap"}


def test_overlap_membership_worked_example():
    """w_h 8, w_p 12, T 3: cycle i spans frames [24i, 24i + 24); the part tokens overlapping it are
    floor(2i) .. ceil(2i + 2) - 1 = 2i, 2i + 1; the old rule (generated, a = T) gave 2i + 3, 2i + 4."""
    T, w_h, w_p = 3, 8, 12
    ov = S.cycle_membership(9, 12, T, w_h, w_p, lookahead=0, align="overlap")
    assert [row.nonzero().flatten().tolist() for row in ov[::T]] == [[0, 1], [2, 3], [4, 5]]
    gen_ = S.cycle_membership(9, 12, T, w_h, w_p, align="generated")
    assert [row.nonzero().flatten().tolist() for row in gen_[::T]] == [[0, 1, 2, 3, 4], [5, 6], [7, 8]]
    assert [S.parts_generated(i, T, w_h, w_p, 0) for i in range(3)] == [2, 4, 6]
    # a part token straddling two cycles (w_p 12, cycle span 8: T 1) belongs to both
    st = S.cycle_membership(3, 3, 1, 8, 12, lookahead=0, align="overlap")
    assert st.tolist() == [[True, False, False], [True, True, False], [False, True, False]]   # [0,8) [8,16) [16,24)
    with pytest.raises(ValueError, match="pg_align|alignment"):
        S.cycle_membership(3, 3, 1, 8, 12, align="ahead")


@pytest.mark.parametrize("switches", [dict(), dict(hpf=False), dict(pg=False)], ids=["pg+hpf", "pg", "hpf"])
def test_a_part_token_beyond_the_lookahead_changes_nothing_in_the_cycle(switches):
    """With the paper's schedule a part token past cycle i's frames (and its look-ahead) changes no
    holistic logit of cycle i, through PG or HPF; one inside them changes them."""
    m = build("party", 0, PAPER, **switches).eval()
    batch = make_batch()
    T, w_h, w_p = m.spec.pg_window, WINDOWS["holistic"], WINDOWS["arms"]
    base = m(batch)["holistic"]
    n_h, n_p = batch["lengths"]["holistic"], batch["lengths"]["arms"]
    checked = {"hidden": 0, "shown": 0}
    for k in range(batch["codes"]["arms"].shape[1]):
        codes = batch["codes"]["arms"].clone()
        codes[:, k] = (codes[:, k] + 1) % VOCAB["arms"]
        new = m(with_codes(batch, "arms", codes))["holistic"]
        for b in range(len(n_h)):
            if k >= n_p[b]:
                continue
            for i in range(int(n_h[b]) // T + 1):
                pos = torch.arange(i * T, min((i + 1) * T, int(n_h[b]) + 1))
                changed = bool((new[b, pos] - base[b, pos]).abs().amax() > 1e-6)
                if k >= S.parts_generated(i, T, w_h, w_p, 0):           # after the cycle's frames
                    assert not changed, (k, b, i)
                    checked["hidden"] += 1
                elif k * w_p < (i + 1) * T * w_h and (k + 1) * w_p > i * T * w_h:   # within them
                    assert changed, (k, b, i)
                    checked["shown"] += 1
    assert checked["hidden"] > 10 and checked["shown"] > 10


def test_pg_of_a_cycle_sums_only_its_overlapping_part_tokens():
    """PG alone (no HPF): a part token first moves the logits of the first cycle whose frames it
    overlaps (later cycles move too, through the holistic transformer's attention to earlier
    positions), none before it."""
    m = build("party", 0, PAPER, hpf=False).eval()
    batch = make_batch()
    T, w_h, w_p = m.spec.pg_window, WINDOWS["holistic"], WINDOWS["arms"]
    base = m(batch)["holistic"]
    b = 0                                                    # 12 holistic, 9 arms codes
    for k in range(int(batch["lengths"]["arms"][b])):
        codes = batch["codes"]["arms"].clone()
        codes[b, k] = (codes[b, k] + 1) % VOCAB["arms"]
        new = m(with_codes(batch, "arms", codes))["holistic"][b]
        moved = {j // T for j in range(new.shape[0]) if (new[j] - base[b, j]).abs().amax() > 1e-6}
        first = min(i for i in range(new.shape[0]) if k * w_p < (i + 1) * T * w_h and (k + 1) * w_p > i * T * w_h)
        if first * T < new.shape[0]:
            assert min(moved) == first, (k, moved, first)


@pytest.mark.parametrize("model", [PAPER, {**PAPER, "pg_lookahead": 2}, {}], ids=["paper", "ahead2", "generated"])
@pytest.mark.parametrize("sampling", ["greedy", "sample"])
def test_cached_generation_equals_recomputation_for_each_schedule(model, sampling):
    m = build("party", 0, {**model, "cond_drop": 0.2, "null_condition": "whole_body", "dropout": 0.1})
    c = torch.randn(6, D_TEXT, generator=torch.Generator().manual_seed(4))
    for kw in ({}, {"cond_scale": 2.0}, {"cond_scale": 1.5, "part_cond_scale": 3.0}):
        a = gen(m, c, None, sampling, True, **kw)
        b = gen(m, c, None, sampling, False, **kw)
        for s in a:
            assert [x.tolist() for x in a[s]] == [x.tolist() for x in b[s]], (s, kw)


def _null_holistic_logits(m, batch, rows):
    """Teacher forcing of ``rows`` on the null condition, as guided generation feeds them: caption
    zero, the part tokens through ``null_parts``."""
    keep = torch.zeros(len(rows), dtype=torch.bool)
    gh = m.gpt["holistic"]
    inp, _ = _sequences(batch["codes"]["holistic"], batch["lengths"]["holistic"], gh.end, gh.pad)
    parts = {}
    for p in m.parts:
        g = m.gpt[p]
        parts[p] = _sequences(batch["codes"][p], batch["lengths"][p], g.end, g.pad)[1]
    return m._holistic_logits(torch.zeros_like(batch["text_emb"]), inp, m.null_parts(parts, keep))[0]


def test_whole_body_null_condition_does_not_see_the_parts():
    """The unconditional holistic logits depend on the caption through no stream: with
    ``whole_body`` two different part sequences give the same null logits; with ``text`` they do not."""
    batch = make_batch()
    other = with_codes(batch, "arms", (batch["codes"]["arms"] + 1) % VOCAB["arms"])
    other = with_codes(other, "legs", (other["codes"]["legs"] + 2) % VOCAB["legs"])
    rows = range(len(batch["lengths"]["holistic"]))
    whole = build("party", 0, {**PAPER, "cond_drop": 0.2, "null_condition": "whole_body"}).eval()
    assert torch.equal(_null_holistic_logits(whole, batch, rows), _null_holistic_logits(whole, other, rows))
    text = build("party", 0, {**PAPER, "cond_drop": 0.2, "null_condition": "text"}).eval()
    assert not torch.allclose(_null_holistic_logits(text, batch, rows), _null_holistic_logits(text, other, rows))


def test_guided_generation_null_rows_ignore_the_caption():
    """In guided generation the holistic stream's unconditional logits (rows B..2B-1) are the same for
    two different captions at the first holistic step (whole_body), and differ under ``text``."""
    from party.methods.party import model as M
    seen = {}
    orig = M._Generation._pick

    def pick(self, s, logits, k):
        if s == "holistic" and k == 0:
            seen.setdefault("u", []).append(logits[self.B:].clone())
        return orig(self, s, logits, k)

    c1 = torch.randn(3, D_TEXT, generator=torch.Generator().manual_seed(1))
    c2 = torch.randn(3, D_TEXT, generator=torch.Generator().manual_seed(2))
    for null, same in (("whole_body", True), ("text", False)):
        m = build("party", 0, {**PAPER, "cond_drop": 0.2, "null_condition": null})
        seen.clear()
        M._Generation._pick = pick
        try:
            for c in (c1, c2):
                gen(m, c, None, "greedy", True, cond_scale=2.0)
        finally:
            M._Generation._pick = orig
        u1, u2 = seen["u"]
        assert torch.allclose(u1, u2, atol=1e-6) == same, null


def test_a_dropped_training_row_sees_no_parts():
    """Training with the whole-body null condition: the holistic logits of the rows whose text is
    dropped do not depend on the (ground-truth) part tokens; the kept rows' do."""
    m = build("party", 0, {**PAPER, "cond_drop": 0.5, "null_condition": "whole_body", "dropout": 0.0}).train()
    batch = make_batch()
    other = with_codes(batch, "arms", (batch["codes"]["arms"] + 1) % VOCAB["arms"])

    def kept(seed):                                  # the rows a seed keeps: _teacher_forcing's first draw
        torch.manual_seed(seed)
        return int((torch.rand(4) >= 0.5).sum())

    seed = next(s for s in range(100) if 0 < kept(s) < 4)

    def run(b):
        torch.manual_seed(seed)                      # the same rows dropped in both calls, some kept
        return m._teacher_forcing(b)

    a, o = run(batch), run(other)
    keep = a["keep"]
    assert keep is not None and bool(keep.any()) and bool((~keep).any())
    assert torch.equal(a["logits"]["holistic"][~keep], o["logits"]["holistic"][~keep])
    assert not torch.allclose(a["logits"]["holistic"][keep], o["logits"]["holistic"][keep])


# ---------------------------------------------------------------------- exposure to generated parts

@pytest.mark.parametrize("embed", ["shared", "detached", "separate"])
def test_part_embed_decides_what_the_holistic_loss_trains(embed):
    """``part_embed``: with ``shared`` L_hol reaches the part transformers' token tables (the paper's
    z), with ``detached`` / ``separate`` it does not (``separate``: PG / HPF train tables of their own)."""
    m = build("party", 0, {**PAPER, "part_embed": embed}).train()
    out = m.losses(make_batch())
    out["hol"].backward()
    grad = m.gpt["arms"].tok.weight.grad
    reached = grad is not None and float(grad.abs().sum()) > 0
    assert reached == (embed == "shared")
    assert (m.ctx_tok is not None) == (embed == "separate")
    if embed == "separate":
        assert float(m.ctx_tok["arms"].weight.grad.abs().sum()) > 0


def test_context_codes_change_what_the_holistic_stream_reads_only():
    m = build("party", 0, PAPER).eval()
    batch = make_batch()
    ctx = {p: (batch["codes"][p] + 1) % VOCAB[p] for p in ("arms", "legs")}
    ctx = {p: torch.where(batch["codes"][p] < VOCAB[p], c, batch["codes"][p]) for p, c in ctx.items()}   # PAD kept
    base, new = m(batch), m({**batch, "context_codes": ctx})
    assert torch.equal(base["arms"], new["arms"]) and torch.equal(base["legs"], new["legs"])
    assert not torch.allclose(base["holistic"], new["holistic"])


def test_part_context_corruption_in_the_training_step():
    """``corruption.part_context_prob`` > 0: the Lightning module adds corrupted ``context_codes`` for
    the parts (the streams' own inputs stay clean unless ``corruption.enabled``)."""
    from party.generator.lit import GeneratorLit
    m = build("party", 0, PAPER)
    lit = GeneratorLit(m, {"lr": 1e-3, "lr_after": 1e-3, "milestone": 10, "betas": [0.5, 0.99], "weight_decay": 0.0},
                       {"enabled": False, "prob": 0.5, "part_context_prob": 0.9}, VOCAB, seed=0)
    batch = make_batch()
    out = lit._inputs(batch)
    assert "input_codes" not in out and set(out["context_codes"]) == {"arms", "legs"}
    changed = sum(int((out["context_codes"][p] != batch["codes"][p]).sum()) for p in ("arms", "legs"))
    assert changed > 0
    for p in ("arms", "legs"):                     # PAD beyond the lengths stays PAD
        pad = batch["codes"][p] == VOCAB[p] + 1
        assert torch.equal(out["context_codes"][p][pad], batch["codes"][p][pad])
    off = GeneratorLit(m, lit.optim_cfg, {"enabled": False, "prob": 0.5, "part_context_prob": 0.0}, VOCAB, seed=0)
    assert off._inputs(batch) is batch


def test_a_model_saved_before_the_switches_loads_with_the_schedule_it_was_trained_with(tmp_path):
    import dataclasses

    from party.methods.party import PartyFamily
    m = build("party", 0, {"pg_lookahead": 3, "pg_align": "generated", "null_condition": "text"})
    from party.methods.store import load_weights, save_weights
    PartyFamily.save(m, tmp_path / "model.pt", {"method": "party"})
    obj = load_weights(tmp_path / "model.pt", "party.generator/1", "cpu")
    old = {k: v for k, v in obj["spec"].items() if k not in ("pg_lookahead", "pg_align", "null_condition", "part_embed")}
    save_weights(tmp_path / "model.pt", "party.generator/1", old, obj["meta"], obj["state_dict"])
    back = PartyFamily.load(tmp_path).model
    assert dataclasses.asdict(back.spec) == dataclasses.asdict(m.spec)
