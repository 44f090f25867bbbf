"""Prompt / answer-format check, and the rules backend on the paper's examples and on
HumanML3D-style English it was not tuned on a template of."""
from __future__ import annotations

import pytest

from party.text.agreement import part_side
from party.text.backends.rules import RulesBackend
from party.text.prompt import FEW_SHOT, FormatError, build_messages, is_no_movement, parse_answer, prompt_fingerprint

PARTS = ["arms", "legs"]          # conf/part_texts/*.yaml `parts`


def test_messages_hold_the_five_examples_then_the_caption():
    msgs = build_messages("a person claps.", PARTS)
    assert msgs[0]["role"] == "system" and "Arms:" in msgs[0]["content"]
    assert len(msgs) == 12 and msgs[-1]["role"] == "user" and "a person claps." in msgs[-1]["content"]
    for k, (cap, texts) in enumerate(FEW_SHOT):
        assert cap in msgs[1 + 2 * k]["content"]
        assert msgs[2 + 2 * k]["content"] == f"Arms: {texts['arms']}\nLegs: {texts['legs']}"
        assert parse_answer(msgs[2 + 2 * k]["content"], PARTS)   # the examples pass our own check


def test_prompt_of_the_configured_parts_is_the_papers():
    # the fingerprint keys the part-text cache: the prompt built from `parts` is the paper's, unchanged
    assert prompt_fingerprint(PARTS) == "c50d759a186c"
    assert prompt_fingerprint(["legs", "arms"]) != prompt_fingerprint(PARTS)
    legs = build_messages("a person kicks.", ["legs"])
    assert "exactly one line" in legs[0]["content"] and "Arms" not in legs[0]["content"]
    assert legs[2]["content"] == f"Legs: {FEW_SHOT[0][1]['legs']}"
    assert parse_answer("Legs: kick", ["legs"]) == {"legs": "kick"}
    with pytest.raises(FormatError, match="unexpected line"):
        parse_answer("Arms: wave\nLegs: kick", ["legs"])
    with pytest.raises(ValueError, match="examples for"):
        build_messages("x", ["arms", "torso"])


@pytest.mark.parametrize("answer, arms, legs", [
    ("Arms: Both arms swing.\nLegs: The legs walk.", "Both arms swing.", "The legs walk."),
    ("  - **Arms:** Right arm waves.\n\n* **Legs:** No significant movement.", "Right arm waves.",
     "No significant movement"),
    ("<think>hmm</think>\nArms: none\nLegs: Legs kick.", "No significant movement", "Legs kick."),
    ("arms: up\nlegs: down", "up", "down"),
])
def test_parse_valid(answer, arms, legs):
    assert parse_answer(answer, PARTS) == {"arms": arms, "legs": legs}


@pytest.mark.parametrize("answer, msg", [
    ("Arms: x", "Legs"), ("Legs: x", "Arms"), ("Arms:\nLegs: x", "empty"),
    ("Arms: a\nArms: b\nLegs: c", "more than one"), ("Sure!\nArms: a\nLegs: b", "unexpected line"),
    ("", "Arms"),
])
def test_parse_invalid(answer, msg):
    with pytest.raises(FormatError, match=msg):
        parse_answer(answer, PARTS)


def test_extra_lines_switch():
    assert parse_answer("Sure!\nArms: a\nLegs: b", PARTS, allow_extra_lines=True) == {"arms": "a", "legs": "b"}


def _labels(parts):
    return tuple(x for p in PARTS for x in (not is_no_movement(parts[p]), part_side(parts[p])))


def test_rules_match_the_paper_examples():
    rules = RulesBackend()
    for cap, texts in FEW_SHOT:
        assert _labels(rules.parts(cap)) == _labels(texts), cap


def test_rules_write_the_configured_parts():
    from omegaconf import OmegaConf
    cap = FEW_SHOT[1][0]
    both = RulesBackend(OmegaConf.create({"parts": PARTS})).parts(cap)
    assert list(both) == PARTS and both == RulesBackend().parts(cap)
    assert RulesBackend(OmegaConf.create({"parts": ["legs"]})).parts(cap) == {"legs": both["legs"]}
    with pytest.raises(ValueError, match="knows the parts"):
        RulesBackend(OmegaConf.create({"parts": ["torso"]}))


# (caption, arms moves, arms side, legs move, legs side); side None = not named / not moving
GENERAL = [
    ("a person walks forward.", True, "both", True, "both"),
    ("the man jogs in a circle.", True, "both", True, "both"),
    ("someone is running and then stops.", True, "both", True, "both"),
    ("a person walks forward while holding a cup in the right hand.", True, "right", True, "both"),
    ("a person walks with their hands on their hips.", True, "both", True, "both"),
    ("a person raises their left arm above their head.", True, "left", False, None),
    ("a man waves hello with both hands.", True, "both", False, None),
    ("a person claps.", True, "both", False, None),
    ("a person throws a ball with the right hand.", True, "right", False, None),
    ("the person punches forward with the left fist.", True, "left", False, None),
    ("a person kicks with the left leg.", False, None, True, "left"),
    ("a man lifts his right knee up to his chest.", False, None, True, "right"),
    ("the person steps forward with the right foot.", False, None, True, "right"),
    ("a person hops on the left foot.", False, None, True, "left"),
    ("a person squats down and stands back up.", False, None, True, "both"),
    ("a person stands up from a chair.", False, None, True, "both"),
    ("a person sits down.", False, None, True, "both"),
    ("a person jumps forward.", False, None, True, "both"),
    ("a person bows.", False, None, False, None),
    ("a person stands still.", False, None, False, None),
    ("a person turns their head to the left.", False, None, False, None),
    ("while sitting, the person waves the right hand.", True, "right", False, None),
    ("a person stands and stretches both arms out to the sides.", True, "both", False, None),
    ("a person swims.", True, "both", True, "both"),
    ("a person crawls on the floor.", True, "both", True, "both"),
    ("a person does jumping jacks.", True, "both", True, "both"),
    ("a person raises the left arm, then the right arm.", True, "left", False, None),
    ("person picks something up with the left hand and puts it down.", True, "left", False, None),
    ("a person moves backwards.", True, "both", True, "both"),
    ("the figure turns around to the right.", False, None, True, "both"),
    ("a person shuffles to the left.", False, None, True, "both"),    # sideways: no arm swing
    ("a man stomps his right foot.", False, None, True, "right"),
    ("a person kneels on the left knee.", False, None, True, "left"),
    ("someone marches in place swinging the arms.", True, "both", True, "both"),
    ("a person walks up the stairs holding the rail with the left hand.", True, "left", True, "both"),
]


@pytest.mark.parametrize("cap, am, aside, lm, lside", GENERAL)
def test_rules_general_english(cap, am, aside, lm, lside):
    parts = RulesBackend().parts(cap)
    assert _labels(parts) == (am, aside, lm, lside), parts


def test_rules_is_deterministic_and_cache_key_tracks_the_code():
    a, b = RulesBackend(), RulesBackend()
    assert a.model == b.model and a.model.startswith("rules-")
    caps = [c for c, *_ in GENERAL]
    assert [a.parts(c) for c in caps] == [b.parts(c) for c in caps]


def test_rules_never_fail_on_odd_input():
    import random
    from party.text.backends.rules import ARM_NOUNS, FORMS, LEG_NOUNS, SPLIT_WORDS
    vocab = sorted(FORMS) + sorted(ARM_NOUNS | LEG_NOUNS) + sorted(SPLIT_WORDS) + \
        ["left", "right", "both", "his", "the", "a", "it", ",", ".", "and", "with", "to", "up", "over"]
    rng = random.Random(0)
    rules = RulesBackend()
    odd = ["", "...", "LEFT RIGHT", "a person", "and and then", "with the left", "it it it"]
    odd += [" ".join(rng.choice(vocab) for _ in range(rng.randint(1, 25))) for _ in range(500)]
    for cap in odd:
        parts = rules.parts(cap)
        assert set(parts) == {"arms", "legs"} and all(isinstance(v, str) and v for v in parts.values()), cap
