"""Closed vocabulary of the caption templates with spaCy-style POS tags (HumanML3D format).

HumanML3D's text processing keeps alphabetic tokens, lower-cases them, lemmatises nouns and
verbs (except ``left``) and writes ``word/POS``. The templates use only the words below, so
tagging is a dictionary lookup plus a few context rules (left/right/back); an unknown word
is a template bug and raises.
"""
from __future__ import annotations

import re

VERBS = (
    "walk", "run", "jog", "sprint", "jump", "leap", "hop", "squat", "kick", "lunge", "sit", "step",
    "turn", "spin", "march", "stand", "move", "stride", "circle", "veer", "curve", "bend", "lower",
    "lift", "raise", "wave", "clap", "swing", "flap", "punch", "throw", "reach", "stretch", "spread",
    "extend", "hold", "put", "place", "rest", "point", "scratch", "rub", "drink", "bring", "take",
    "do", "make", "stay", "remain", "keep", "shuffle", "go", "pump", "wiggle", "pull", "push",
    "land", "support", "alternate", "propel", "shift", "return", "straighten", "come", "brace",
    "follow", "perform", "stomp", "tilt", "sip", "gesture", "sway", "crouch", "sidestep",
)
NOUNS = (
    "person", "man", "woman", "someone", "arm", "hand", "leg", "foot", "hip", "head", "chair", "ball",
    "circle", "direction", "side", "shoulder", "fist", "knee", "punch", "kick", "squat", "lunge",
    "step", "seat", "air", "bird", "mouth", "drink", "place", "position", "front", "body", "time",
    "spot", "gait", "motion", "weight", "ground", "floor", "cup", "throw", "jump", "hop", "pace",
    "wing", "waist", "rhythm", "movement", "stride", "run", "walk", "sitting", "clap", "wave",
    "something", "beat", "lap", "glass", "torso", "back", "left", "right", "shot", "bottom",
    "way", "top",
)
NOUN_PLURALS = {"hands": "hand", "arms": "arm", "legs": "leg", "feet": "foot", "hips": "hip",
                "steps": "step", "squats": "squat", "kicks": "kick", "punches": "punch",
                "lunges": "lunge", "jumps": "jump", "hops": "hop", "times": "time", "knees": "knee",
                "fists": "fist", "shoulders": "shoulder", "sides": "side", "wings": "wing",
                "claps": "clap", "waves": "wave", "throws": "throw", "circles": "circle",
                "movements": "movement", "strides": "stride"}
OTHER = {
    "a": "DET", "an": "DET", "the": "DET", "both": "DET", "each": "DET", "his": "DET", "her": "DET",
    "their": "DET", "its": "DET", "one": "NUM", "two": "NUM", "three": "NUM", "four": "NUM",
    "five": "NUM", "six": "NUM", "once": "ADV", "twice": "ADV", "few": "ADJ", "several": "ADJ",
    "someone": "PRON", "something": "PRON", "they": "PRON", "he": "PRON", "she": "PRON",
    "them": "PRON", "him": "PRON", "itself": "PRON", "is": "AUX",
    "and": "CCONJ", "or": "CCONJ", "then": "ADV", "while": "SCONJ", "as": "SCONJ", "if": "SCONJ",
    "before": "ADP", "after": "ADP", "with": "ADP", "in": "ADP", "on": "ADP", "at": "ADP",
    "to": "ADP", "of": "ADP", "into": "ADP", "onto": "ADP", "above": "ADP", "over": "ADP",
    "from": "ADP", "behind": "ADP", "toward": "ADP", "towards": "ADP", "across": "ADP",
    "like": "ADP", "without": "ADP", "by": "ADP", "up": "ADP", "down": "ADP", "out": "ADP",
    "off": "ADP", "forward": "ADV", "forwards": "ADV", "backward": "ADV", "backwards": "ADV",
    "around": "ADV", "ahead": "ADV", "forth": "ADV", "sideways": "ADV", "together": "ADV",
    "still": "ADV", "slowly": "ADV", "quickly": "ADV", "fast": "ADV", "briskly": "ADV",
    "gradually": "ADV", "repeatedly": "ADV", "again": "ADV", "first": "ADV", "high": "ADV",
    "rapidly": "ADV", "rhythmically": "ADV", "forcefully": "ADV", "gently": "ADV",
    "straight": "ADV", "away": "ADV", "briefly": "ADV", "energetically": "ADV", "overhead": "ADV",
    "clockwise": "ADV", "counterclockwise": "ADV", "anticlockwise": "ADV", "upward": "ADV",
    "upwards": "ADV", "downward": "ADV", "outward": "ADV", "inward": "ADV", "apart": "ADV",
    "leisurely": "ADV", "steadily": "ADV", "continuously": "ADV", "all": "DET",
    "big": "ADJ", "small": "ADJ", "full": "ADJ", "quick": "ADJ", "slow": "ADJ", "deep": "ADJ",
    "overhand": "ADJ", "seated": "ADJ", "significant": "ADJ", "no": "DET",
    "not": "PART", "near": "ADP", "other": "ADJ", "same": "ADJ", "wide": "ADJ", "single": "ADJ",
    "imaginary": "ADJ", "whole": "ADJ", "main": "ADJ", "that": "PRON",
    "lifted": "VERB", "bent": "VERB", "planted": "VERB", "outstretched": "ADJ", "short": "ADJ",
    "upright": "ADJ", "raised": "VERB", "extended": "VERB", "tall": "ADJ", "low": "ADJ",
}
BODY_NOUNS = {"hand", "arm", "leg", "foot", "hip", "shoulder", "fist", "knee", "side", "hands",
              "arms", "legs", "feet", "hips", "shoulders", "fists", "knees", "sides"}
_DOUBLE = {"run", "sit", "step", "hop", "jog", "squat", "clap", "flap", "put", "spin", "stop",
           "skip", "sidestep"}


def third_person(verb: str) -> str:
    if verb == "do":
        return "does"
    if verb == "go":
        return "goes"
    if re.search(r"(s|sh|ch|x|z)$", verb):
        return verb + "es"
    if re.search(r"[^aeiou]y$", verb):
        return verb[:-1] + "ies"
    return verb + "s"


def gerund(verb: str) -> str:
    if verb in _DOUBLE:
        return verb + verb[-1] + "ing"
    if verb.endswith("ie"):
        return verb[:-2] + "ying"
    if verb.endswith("e") and not verb.endswith(("ee", "ye", "oe")):
        return verb[:-1] + "ing"
    return verb + "ing"


def _build_surface() -> dict[str, tuple[str, str]]:
    """surface word -> (token word, POS)."""
    out: dict[str, tuple[str, str]] = {}
    for w, pos in OTHER.items():
        out[w] = (w, pos)
    for n in NOUNS:
        out.setdefault(n, (n, "NOUN"))
    for pl, sg in NOUN_PLURALS.items():
        out[pl] = (sg, "NOUN")
    for v in VERBS:
        for form in (v, third_person(v), gerund(v)):
            out[form] = (v, "VERB")
    for form, lemma in (("sat", "sit"), ("took", "take"), ("threw", "throw"), ("held", "hold"),
                        ("brought", "bring"), ("stood", "stand"), ("ran", "run"), ("swung", "swing"),
                        ("does", "do"), ("doing", "do"), ("made", "make")):
        out[form] = (lemma, "VERB")
    # words that are nouns in the lexicon but verbs in a caption get context rules below
    out["left"] = ("left", "ADJ")
    out["right"] = ("right", "ADJ")
    out["back"] = ("back", "ADV")
    return out


SURFACE = _build_surface()
# a bare or -s form after these is a noun ("a kick", "two squats", "in place", "throws punches")
NOUN_CONTEXT = {"a", "an", "the", "his", "her", "their", "its", "one", "two", "three", "four", "five",
                "six", "few", "several", "big", "small", "quick", "single", "full", "deep", "high",
                "overhand", "short", "wide", "imaginary", "slow", "in", "on", "into", "at", "of", "from",
                "throws", "throwing", "throw", "does", "doing", "do", "makes", "making", "make", "takes",
                "taking", "take", "clockwise", "counterclockwise", "anticlockwise"}
_SPLIT = re.compile(r"[A-Za-z]+|[^A-Za-z\s]")


def words(text: str) -> list[str]:
    """HumanML3D tokenisation: hyphens removed, then alphabetic tokens only, lower case."""
    return [w.lower() for w in _SPLIT.findall(text.replace("-", "")) if w.isalpha()]


def tag(text: str) -> list[str]:
    """``word/POS`` tokens for a caption made from the template vocabulary."""
    ws = words(text)
    out = []
    for i, w in enumerate(ws):
        if w not in SURFACE:
            raise ValueError(f"caption word {w!r} is not in the synthetic lexicon (caption: {text!r})")
        tok, pos = SURFACE[w]
        nxt = ws[i + 1] if i + 1 < len(ws) else None
        prev = ws[i - 1] if i > 0 else None
        if w in ("left", "right"):
            if nxt in BODY_NOUNS:
                pos = "ADJ"
            elif prev in ("the", "his", "her", "their", "its"):
                pos = "NOUN"
            else:
                pos = "ADV"
        elif w == "back":
            pos = "NOUN" if prev in ("the", "his", "her", "their", "its") else "ADV"
        elif w == "high":
            pos = "ADJ" if nxt is not None and SURFACE.get(nxt, ("", ""))[1] == "NOUN" else "ADV"
        elif w in ("walk", "run", "jump", "hop", "kick", "punch", "squat", "lunge", "step", "throw",
                   "drink", "clap", "wave", "circle", "seat", "place", "rest", "stride", "point",
                   "turn"):
            # bare form: a noun after a determiner / number / adjective, else a verb
            if prev in NOUN_CONTEXT:
                pos = "NOUN"
            else:
                pos = "VERB"
        elif w in ("walks", "runs", "jumps", "hops", "kicks", "punches", "squats", "lunges", "steps",
                   "throws", "claps", "waves", "circles", "strides"):
            if prev in NOUN_CONTEXT:
                pos = "NOUN"
            else:
                pos = "VERB"
                tok = {"punches": "punch", "lunges": "lunge", "throws": "throw", "squats": "squat",
                       "claps": "clap", "waves": "wave", "circles": "circle", "strides": "stride"}.get(
                    w, w[:-1])
        if pos in ("NOUN", "VERB") and w != "left":
            out.append(f"{tok}/{pos}")
        else:
            out.append(f"{w}/{pos}")
    return out
