"""The cycle schedule (SPEC §3 Decision): hand-computed examples, a simulated generation loop,
monotonicity and caps for T = 1..5."""
import pytest
import torch

from party.methods.party import schedule as S


def test_worked_example_w8_w12_T3():
    T, w_h, w_p = 3, 8, 12
    assert [S.parts_generated(i, T, w_h, w_p) for i in range(4)] == [5, 7, 9, 11]
    j = torch.arange(9)
    assert S.cycle_of(j, T).tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert S.holistic_time(j, T, w_h, w_p).tolist() == [5, 6, 7, 10, 11, 12, 15, 16, 17]
    assert S.part_cycle(j, T, w_h, w_p).tolist() == [0, 0, 0, 0, 0, 1, 1, 2, 2]
    assert S.part_time(j, T, w_h, w_p).tolist() == [0, 1, 2, 3, 4, 8, 9, 13, 14]
    vis = S.part_visible(9, T, w_h, w_p, torch.tensor([100, 5, 0]))
    assert vis[0].tolist() == [5, 5, 5, 7, 7, 7, 9, 9, 9]
    assert vis[1].tolist() == [5, 5, 5, 6, 6, 6, 6, 6, 6]         # END (token 5) arrives in cycle 1
    assert vis[2].tolist() == [1] * 9                              # an empty part stream: just END


def test_hand_example_with_empty_cycles():
    """w_h 4, w_p 12, T 1: a cycle spans 4 frames, so some cycles generate no part token."""
    T, w_h, w_p = 1, 4, 12
    assert [S.parts_generated(i, T, w_h, w_p) for i in range(7)] == [2, 2, 2, 3, 3, 3, 4]
    assert S.part_cycle(torch.arange(4), T, w_h, w_p).tolist() == [0, 0, 3, 6]
    # events: parts 0, 1 | hol 0 | hol 1 | hol 2 | part 2 | hol 3 | hol 4 | hol 5 | part 3 | hol 6
    assert S.part_time(torch.arange(4), T, w_h, w_p).tolist() == [0, 1, 5, 9]
    assert S.holistic_time(torch.arange(7), T, w_h, w_p).tolist() == [2, 3, 4, 6, 7, 8, 10]


def simulate(T, w_h, w_p, n_h):
    """The generation loop in plain Python: cycle i generates parts up to Q_i, then T holistic tokens."""
    events, k, i = [], 0, 0
    while True:
        while k < S.parts_generated(i, T, w_h, w_p):
            events.append(("p", k))
            k += 1
        for j in range(i * T, (i + 1) * T):
            events.append(("h", j))
            if j == n_h:
                return {e: t for t, e in enumerate(events)}
        i += 1


@pytest.mark.parametrize("T", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("w_h,w_p", [(8, 12), (4, 12), (12, 8), (8, 8), (4, 4)])
def test_times_are_the_generation_order(T, w_h, w_p):
    n_h = 30
    order = simulate(T, w_h, w_p, n_h)
    hs = sorted(j for s, j in order if s == "h")
    ps = sorted(k for s, k in order if s == "p")
    assert S.holistic_time(torch.tensor(hs), T, w_h, w_p).tolist() == [order["h", j] for j in hs]
    assert S.part_time(torch.tensor(ps), T, w_h, w_p).tolist() == [order["p", k] for k in ps]
    # visibility by time == "generated before": exactly the first Q_{j//T} part tokens
    ht = S.holistic_time(torch.tensor(hs), T, w_h, w_p)
    pt = S.part_time(torch.tensor(ps), T, w_h, w_p)
    seen = (pt[None, :] <= ht[:, None]).sum(1)
    vis = S.part_visible(len(hs), T, w_h, w_p, torch.tensor([10 ** 6]))[0]
    assert seen.tolist() == vis.tolist()


@pytest.mark.parametrize("T", [1, 2, 3, 4, 5])
def test_visible_monotone_capped_and_covering(T):
    for w_h, w_p in [(8, 12), (4, 12), (12, 8), (8, 8)]:
        n_p = torch.arange(0, 25)
        vis = S.part_visible(200, T, w_h, w_p, n_p)
        assert (vis[:, 1:] >= vis[:, :-1]).all()                          # monotone in j
        assert (vis <= n_p[:, None] + 1).all() and (vis >= 1).all()       # capped at n_p + 1 (codes + END)
        assert (vis[:, -1] == n_p + 1).all()                             # long enough: everything, END included
        for i in range(10):
            q = S.parts_generated(i, T, w_h, w_p)
            frames = (i + 1) * T * w_h
            assert (q - T) * w_p >= frames > (q - T - 1) * w_p           # covers the cycle's span, minimally
            assert q >= S.parts_generated(max(i - 1, 0), T, w_h, w_p)


def test_part_times_pad_is_never_and_membership():
    T, w_h, w_p, pad = 3, 8, 12, 9
    tok = torch.tensor([[1, 2, 3, 4, 9, 9], [1, 2, 3, 4, 5, 6]])
    t = S.part_times(tok, pad, T, w_h, w_p)
    assert t[0].tolist()[:4] == [0, 1, 2, 3] and t[0, 4:].eq(S.NEVER).all()
    assert S.part_times(tok[:, 5:], pad, T, w_h, w_p, start=5)[1].tolist() == [8]
    mem = S.cycle_membership(9, 9, T, w_h, w_p)
    assert mem.sum(1).tolist() == [5, 5, 5, 2, 2, 2, 2, 2, 2]
    assert mem[3].nonzero().flatten().tolist() == [5, 6]
