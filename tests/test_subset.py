"""The interactive subset (party.data.subset, SPEC-textim §1): clips with an interaction in some caption
plus a drawn share of clips without, in the index's own splits, mirrors left out by default."""
import pytest

from party.data.subset import choose_subset


def _clips(n: int):
    out = []
    for k in range(n):
        split = "train" if k % 5 < 3 else ("val" if k % 5 == 3 else "test")
        for name in (f"{k:03d}", f"M{k:03d}"):
            caps = [{"caption": f"{'waves' if k % 3 == 0 else 'walks'} {name}"}, {"caption": f"other {name}"}]
            out.append({"id": name, "motion": name, "split": split, "captions": caps})
    return out


def interactive(c: str) -> bool:
    return c.startswith("waves")


def test_every_interactive_clip_and_the_ratio_of_the_others_without_mirrors():
    clips = _clips(30)
    s = choose_subset(clips, interactive, n_interactive=None, n_non_interactive=None, non_interactive_ratio=0.5,
                      mirror="exclude", seed=1)
    ids = [i for k in ("train", "val", "test") for i in s.get(k, [])]
    inter = [i for i in ids if int(i) % 3 == 0]
    assert not any(i.startswith("M") for i in ids) and s["counts"]["mirrors_excluded"] == 30
    assert len(inter) == 10 and len(ids) - len(inter) == 5 and s["counts"]["non_interactive_available"] == 20
    by_id = {c["id"]: c["split"] for c in clips}
    assert all(by_id[i] == k for k in ("train", "val", "test") for i in s.get(k, []))


def test_the_draw_is_seeded_and_does_not_depend_on_the_order_of_the_index():
    clips = _clips(40)
    kw = dict(n_interactive=5, n_non_interactive=7, non_interactive_ratio=0.5, mirror="keep")
    a = choose_subset(clips, interactive, seed=3, **kw)
    b = choose_subset(list(reversed(clips)), interactive, seed=3, **kw)
    c = choose_subset(clips, interactive, seed=4, **kw)
    flat = lambda s: sorted(i for k in ("train", "val", "test") for i in s.get(k, []))   # noqa: E731
    assert flat(a) == flat(b) and flat(a) != flat(c) and len(flat(a)) == 12
    assert any(i.startswith("M") for i in flat(choose_subset(clips, interactive, seed=3, **{**kw, "n_interactive": None})))


def test_a_bad_mirror_setting_is_refused():
    with pytest.raises(ValueError, match="mirror"):
        choose_subset(_clips(3), interactive, n_interactive=None, n_non_interactive=None, non_interactive_ratio=0.5,
                      mirror="swap", seed=0)
