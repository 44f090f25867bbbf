"""Synthetic captions: HumanML3D line format, POS tokens, sides named, part texts, mirrors."""
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from party.data.humanml3d import parse_caption_line
from party.data.synthetic import (ARM_ACTIONS, LEG_ACTIONS, make_action, make_captions, make_part_texts,
                                  sample_specs, single_spec)
from party.data.synthetic.captions import caption_lines, mirror_captions, swap_sides
from party.data.synthetic.lexicon import tag

ROOT = Path(__file__).resolve().parents[1]
CFG = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
S = CFG.synthetic
FPS = float(CFG.fps)
POS = {"NOUN", "VERB", "ADP", "DET", "ADJ", "ADV", "NUM", "PRON", "CCONJ", "SCONJ", "PART", "AUX"}
SPECS = sample_specs(CFG, np.random.default_rng(11), n=300)


def caps_of(spec, seed=0):
    return make_captions(spec, np.random.default_rng([seed, spec.index]), S.captions, FPS)


def test_lines_parse_and_tokens_are_humanml3d_style():
    for spec in SPECS:
        caps = caps_of(spec)
        whole = [c for c in caps if c["start"] == c["end"] == 0.0]
        assert len(whole) == S.captions.per_motion and len({c["caption"] for c in whole}) == len(whole)
        for i, line in enumerate(caption_lines(caps).splitlines(), 1):
            cap = parse_caption_line(line, spec.name, i)
            assert cap.tokens and all(t.rsplit("/", 1)[1] in POS for t in cap.tokens)
            words = [t.rsplit("/", 1)[0] for t in cap.tokens]
            assert all(w.isalpha() and w == w.lower() for w in words)


def test_pos_tags_and_lemmas():
    toks = tag("A man kicks with his left leg, then walks backwards in a circle to the right twice.")
    assert toks == ["a/DET", "man/NOUN", "kick/VERB", "with/ADP", "his/DET", "left/ADJ", "leg/NOUN",
                    "then/ADV", "walk/VERB", "backwards/ADV", "in/ADP", "a/DET", "circle/NOUN", "to/ADP",
                    "the/DET", "right/NOUN", "twice/ADV"]
    assert tag("someone does two squats and turns left")[2:5] == ["two/NUM", "squat/NOUN", "and/CCONJ"]
    assert tag("someone turns left")[-1] == "left/ADV"
    with pytest.raises(ValueError, match="lexicon"):
        tag("a person moonwalks")


def test_sequences_have_timed_captions_per_segment():
    seqs = [s for s in SPECS if s.is_sequence]
    assert len(seqs) > 40
    for spec in seqs:
        caps = caps_of(spec)
        timed = [c for c in caps if not (c["start"] == c["end"] == 0.0)]
        assert len(timed) == 2 * S.captions.per_segment
        spans = sorted({(c["start"], c["end"]) for c in timed})
        assert len(spans) == 2 and spans[0][0] == 0.0 and spans[0][1] == spans[1][0]
        # the loaders cut at int(seconds * fps): the boundary frame survives the text round trip
        line = caption_lines(timed).splitlines()[-1]
        start = float(line.split("#")[2])
        assert int(start * FPS) == spec.boundary
        assert spans[1][1] <= (spec.n_frames - 1) / FPS + 1e-9
        assert all(int(round((e - s) * FPS)) >= CFG.min_len for s, e in spans)


SIDED_ARMS = [a for a in ARM_ACTIONS if any(s in ("left", "right") for s in S.arms[a].get("sides", []))]
SIDED_LEGS = [a for a in LEG_ACTIONS if any(s in ("left", "right") for s in S.legs[a].get("sides", []))]


@pytest.mark.parametrize("side", ["left", "right"])
def test_one_sided_actions_name_their_side(side):
    for arms in SIDED_ARMS:
        spec = single_spec(make_action("stand", S.legs, None), make_action(arms, S.arms, None, side=side), FPS)
        for seed in range(4):
            for c in caps_of(spec, seed):
                assert side in c["caption"].split() and f"{side}/ADJ" in c["tokens"], c["caption"]
        pt = make_part_texts(spec)
        assert side in pt["arms"] and pt["legs"] == "No significant movement."
    for legs in SIDED_LEGS:
        spec = single_spec(make_action(legs, S.legs, None, side=side), make_action("rest", S.arms, None), FPS)
        for seed in range(4):
            for c in caps_of(spec, seed):
                assert side in c["caption"].split(), c["caption"]
        pt = make_part_texts(spec)
        assert f"The {side} leg" in pt["legs"] and pt["arms"] == "No significant movement."


def test_part_texts():
    def pt(legs, arms, **kw):
        return make_part_texts(single_spec(make_action(legs, S.legs, None),
                                           make_action(arms, S.arms, None, **kw), FPS))
    assert pt("stand", "rest") == {"arms": "No significant movement.", "legs": "No significant movement."}
    walk = pt("walk_forward", "rest")
    assert walk["arms"] == "Both arms swing back and forth with the gait." and "walk forward" in walk["legs"]
    wave = pt("walk_forward", "wave", side="right")
    assert wave["arms"].startswith("The right arm raises up and waves") and "left arm swings" in wave["arms"]
    for spec in SPECS:
        p = make_part_texts(spec)
        assert set(p) == {"arms", "legs"} and all(t.endswith(".") and t[0].isupper() for t in p.values())
        if spec.kind == "legs_seq":
            assert ", then " in p["legs"]


def test_mirrored_texts_swap_sides():
    for spec in SPECS[:150]:
        caps = caps_of(spec)
        # captions of the mirrored spec are the original captions with left/right swapped
        assert caps_of(spec.mirrored()) == mirror_captions(caps)
        assert make_part_texts(spec.mirrored()) == {k: swap_sides(v) for k, v in make_part_texts(spec).items()}
    assert swap_sides("Waves the left hand, turns right, clockwise.") == \
        "Waves the right hand, turns left, counterclockwise."
    m = mirror_captions([{"caption": "kicks with the left leg", "tokens": tag("kicks with the left leg"),
                          "start": 0.0, "end": 0.0}])[0]
    assert m["caption"] == "kicks with the right leg" and "right/ADJ" in m["tokens"]
