"""Generation: KV-cached == full recomputation (tokens, same seed), forced lengths, teacher forcing
sees what generation sees, sampling filters."""
import pytest
import torch

from party.methods.party import schedule as S
from party.generator.sampling import choose, filter_logits

from .tiny_spec import D_TEXT, MODEL, VOCAB, WINDOWS, build


def make(kind, seed=0, **switches):
    return build(kind, seed, {"dropout": 0.1}, **switches)       # dropout on: generation must switch it off


def targets(B, seed):
    g = torch.Generator().manual_seed(seed)
    return {"holistic": torch.randint(1, 19, (B,), generator=g),
            "arms": torch.randint(0, 14, (B,), generator=g), "legs": torch.randint(0, 14, (B,), generator=g)}


def gen(m, c, lengths, sampling, use_cache, seed=7, **kw):
    return m.generate(c, lengths=lengths, sampling=sampling, generator=torch.Generator().manual_seed(seed),
                      use_cache=use_cache, **kw)


@pytest.mark.parametrize("kind", ["party", "holistic", "partwise"])
@pytest.mark.parametrize("sampling", ["greedy", "sample"])
@pytest.mark.parametrize("B,forced", [(1, False), (1, True), (32, True), (32, False)])
def test_cached_generation_equals_full_recomputation(kind, sampling, B, forced):
    m = make(kind)
    c = torch.randn(B, D_TEXT, generator=torch.Generator().manual_seed(B))
    lengths = targets(B, 3) if forced else None
    a = gen(m, c, lengths, sampling, True, top_k=None if sampling == "greedy" else 5)
    b = gen(m, c, lengths, sampling, False, top_k=None if sampling == "greedy" else 5)
    assert set(a) == set(m.spec.streams) == set(b)
    for s in a:
        assert len(a[s]) == B
        assert [x.tolist() for x in a[s]] == [x.tolist() for x in b[s]], s
    if forced:
        assert [len(x) for x in a[m.spec.streams[0]]] == lengths[m.spec.streams[0]].tolist()
    if B == 32 and (forced or sampling == "sample"):   # the batch really mixes lengths
        assert len({len(x) for x in a[m.spec.streams[0]]}) > 3
    assert m.training                              # generate restores the mode


def test_forced_lengths_and_streams_per_kind():
    B = 6
    lengths = targets(B, 5)
    lengths["arms"] = torch.minimum(lengths["arms"], torch.full((B,), 10))
    c = torch.randn(B, D_TEXT)
    out = gen(make("partwise"), c, lengths, "sample", True)
    assert set(out) == {"arms", "legs"}
    for p in ("arms", "legs"):
        assert [len(x) for x in out[p]] == lengths[p].tolist()
        assert all(int(x.max()) < VOCAB[p] for x in out[p] if len(x))
    out = gen(make("party"), c, lengths, "sample", True)
    assert [len(x) for x in out["holistic"]] == lengths["holistic"].tolist()
    T, w_h, w_p = MODEL["pg_window"], WINDOWS["holistic"], WINDOWS["arms"]
    for b in range(B):   # a part stream stops at its END or where the holistic stream ended
        seen = int(S.part_visible(int(lengths["holistic"][b]) + 1, T, w_h, w_p, lengths["arms"][b:b + 1])[0, -1])
        assert len(out["arms"][b]) == min(int(lengths["arms"][b]), seen)
    free = gen(make("holistic"), c, None, "sample", True)
    assert all(len(x) <= MODEL["max_tokens"] for x in free["holistic"])


@pytest.mark.parametrize("kind", ["party", "holistic", "partwise"])
def test_teacher_forcing_sees_what_generation_sees(kind):
    """Greedy generation with forced lengths, fed back through the teacher-forcing forward: the argmax
    of every logit (END suppressed before the target) is the generated token."""
    m, B = make(kind), 5
    c = torch.randn(B, D_TEXT, generator=torch.Generator().manual_seed(11))
    lengths = targets(B, 9)
    out = gen(m, c, lengths, "greedy", True)
    n = {s: torch.tensor([len(x) for x in out[s]]) for s in out}
    codes = {s: torch.nn.utils.rnn.pad_sequence(out[s], batch_first=True, padding_value=VOCAB[s] + 1)
             for s in out}
    codes = {s: torch.nn.functional.pad(x, (0, 1), value=VOCAB[s] + 1) for s, x in codes.items()}
    m.eval()
    logits = m({"text_emb": c, "codes": codes, "lengths": n})
    for s, lg in logits.items():
        for b in range(B):
            lb = lg[b, :len(out[s][b])].clone()
            lb[:, VOCAB[s]] = float("-inf")
            assert lb.argmax(-1).tolist() == out[s][b].tolist(), (s, b)


def test_sampling_is_seeded_and_filters():
    logits = torch.randn(64, 10, generator=torch.Generator().manual_seed(0))
    g = lambda s: torch.Generator().manual_seed(s)  # noqa: E731
    a = choose(logits, "sample", 1.0, None, None, g(1))
    assert torch.equal(a, choose(logits, "sample", 1.0, None, None, g(1)))
    assert not torch.equal(a, choose(logits, "sample", 1.0, None, None, g(2)))
    greedy = choose(logits, "greedy", 1.0, None, None, None)
    assert torch.equal(greedy, logits.argmax(-1))
    assert torch.equal(choose(logits, "sample", 1.0, 1, None, g(3)), greedy)
    assert torch.equal(choose(logits, "sample", 1.0, None, 1e-6, g(3)), greedy)
    assert torch.equal(choose(logits, "sample", 1e-4, None, None, g(3)), greedy)
    top3 = choose(logits, "sample", 1.0, 3, None, g(4))
    assert (logits.gather(1, top3[:, None]) >= logits.topk(3).values[:, -1:]).all()
    kept = torch.isfinite(filter_logits(logits, None, 0.5))
    probs = torch.softmax(logits, -1)
    mass_kept = (probs * kept).sum(-1)
    smallest = probs.masked_fill(~kept, 2).min(-1).values
    assert (mass_kept >= 0.5).all() and (mass_kept - smallest < 0.5).all()      # the minimal nucleus
    with pytest.raises(ValueError):
        choose(logits, "beam", 1.0, None, None, None)


class _EndAtOnce(torch.nn.Module):
    """A head whose END logit always wins: free-length generation ends before the first code."""

    def __init__(self, head, end):
        super().__init__()
        self.inner, self.end = head, end

    def forward(self, x):
        y = self.inner(x).clone()
        y[..., self.end] = 1e4
        return y


@pytest.mark.parametrize("kind", ["party", "holistic", "partwise"])
def test_min_frames_floors_free_lengths_only(kind):
    m, B = make(kind), 4
    for s in m.spec.streams:
        m.gpt[s].head = _EndAtOnce(m.gpt[s].head, m.gpt[s].end)
    c = torch.randn(B, D_TEXT, generator=torch.Generator().manual_seed(2))
    first = m.spec.streams[0]
    assert all(len(x) == 0 for x in gen(m, c, None, "sample", True)[first])        # no floor: ends at once
    for cache in (True, False):
        out = gen(m, c, None, "sample", cache, min_frames=40)
        streams = ["arms", "legs"] if kind == "partwise" else [first]   # party's parts stop with the holistic
        for s in streams:
            assert [len(x) for x in out[s]] == [-(-40 // WINDOWS[s])] * B, (s, cache)   # 5 (w 8), 4 (w 12)
    lengths = {s: torch.full((B,), 2) for s in m.spec.streams}                      # a target wins over the floor
    out = gen(m, c, lengths, "sample", True, min_frames=40)
    assert [len(x) for x in out[first]] == [2] * B
