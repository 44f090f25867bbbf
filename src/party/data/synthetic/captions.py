"""Captions (varied templates, HumanML3D POS tokens) and ground-truth part texts.

A template is a phrase whose verbs are marked ``^verb``; a clause conjugates them to the
third person ("waves") or the gerund ("waving") as the sentence needs. Placeholders:
``{P}`` a determiner for body parts ("the" or the subject's "his/her/their"), ``{side}`` the
action's side, ``{dir}`` a direction, ``{count}`` "once / twice / three times" (or nothing),
``{num}`` "a / two / three". Sides are always named for one-sided actions; "both" is
sometimes left implicit, since it is unambiguous.
"""
from __future__ import annotations

import re

import numpy as np

from party.data.synthetic.legs import GAIT_SWING
from party.data.synthetic.lexicon import gerund, tag, third_person
from party.data.synthetic.spec import ActionSpec, MotionSpec, Trajectory

COUNT = {1: "once", 2: "twice", 3: "three times", 4: "four times", 5: "five times", 6: "six times"}
NUM = {1: "a", 2: "two", 3: "three", 4: "four", 5: "five", 6: "six"}

LEGS = {
    "stand": ["^stand still", "^stand in place", "^stand without moving", "^remain standing still",
              "^stay still"],
    "walk_forward": ["^walk forward", "^walk forwards", "^walk straight ahead", "^walk ahead",
                     "^take a few steps forward", "^move forward at a walk", "^stride forward"],
    "walk_backward": ["^walk backward", "^walk backwards", "^step backward", "^take a few steps backward",
                      "^move backwards", "^walk back"],
    "walk_circle_cw": ["^walk in a circle clockwise", "^walk clockwise in a circle",
                       "^walk around in a clockwise circle", "^walk in a circle to the right",
                       "^circle around clockwise", "^walk in a clockwise circle"],
    "walk_circle_ccw": ["^walk in a circle counterclockwise", "^walk counterclockwise in a circle",
                        "^walk around in a counterclockwise circle", "^walk in a circle to the left",
                        "^circle around counterclockwise", "^walk in a counterclockwise circle"],
    "run": ["^run forward", "^jog forward", "^run ahead", "^run straight ahead", "^jog ahead"],
    "march_in_place": ["^march in place", "^march on the spot", "^step in place lifting {P} knees high",
                       "^march in place with high knees", "^march without moving forward"],
    "turn_around": ["^turn around to the {dir}", "^turn around over {P} {dir} shoulder",
                    "^turn around {clock}", "^spin around to the {dir}", "^turn all the way around to the {dir}"],
    "jump": ["^jump {count}", "^jump up {count}", "^jump in place {count}", "^do {num} jump{s}"],
    "jump_forward": ["^jump forward {count}", "^leap forward {count}", "^jump ahead {count}",
                     "^do {num} jump{s} forward"],
    "hop": ["^hop on {P} {side} leg {count}", "^hop on {P} {side} foot", "^hop on the {side} leg",
            "^jump on {P} {side} foot {count}", "^hop {count} on {P} {side} leg"],
    "squat": ["^squat down {count}", "^do {num} squat{s}", "^squat {count}", "^bend {P} knees into a squat",
              "^crouch down into a squat {count}"],
    "kick": ["^kick with {P} {side} leg {count}", "^kick with {P} {side} foot", "^kick forward with {P} {side} leg",
             "^do {num} kick{s} with {P} {side} leg", "^kick {P} {side} leg forward {count}"],
    "lunge": ["^lunge forward with {P} {side} leg {count}", "^step forward into a lunge with {P} {side} leg",
              "^do {num} lunge{s} with {P} {side} leg forward", "^lunge with {P} {side} foot forward"],
    "sit_down": ["^sit down", "^sit down on a chair", "^sit down on something", "^take a seat",
                 "^lower {P} body into a sitting position"],
    "side_step": ["^step to the {dir} {count}", "^sidestep to the {dir}", "^move sideways to the {dir}",
                  "^shuffle to the {dir}", "^take {num} step{s} to the {dir}", "^step sideways to the {dir}"],
}
VEER = [" and gradually ^turn {dir}", ", veering to the {dir}", ", curving to the {dir}"]
SPEED_ADVERBS = {"slow": ["slowly"], "fast": ["quickly", "fast"]}
SPEED_ACTIONS = {"walk_forward", "walk_backward", "walk_circle_cw", "walk_circle_ccw", "run",
                 "march_in_place", "side_step", "sit_down", "squat"}

ARMS_SIDE = {
    "wave": ["^wave with {P} {side} hand", "^wave {P} {side} hand", "^raise {P} {side} hand and ^wave",
             "^wave {P} {side} arm"],
    "raise": ["^raise {P} {side} arm {count}", "^raise {P} {side} hand", "^lift {P} {side} arm up",
              "^raise {P} {side} arm above {P} head", "^put {P} {side} hand up"],
    "punch": ["^punch with {P} {side} hand {count}", "^punch forward with {P} {side} fist",
              "^throw {num} punch{es} with {P} {side} arm", "^punch {count} with {P} {side} fist"],
    "reach_forward": ["^reach forward with {P} {side} hand", "^reach out in front with {P} {side} arm",
                      "^extend {P} {side} arm forward", "^stretch {P} {side} arm out in front"],
    "arms_out": ["^stretch {P} {side} arm out to the side", "^raise {P} {side} arm out to the side",
                 "^extend {P} {side} arm sideways"],
    "throw": ["^throw something with {P} {side} hand", "^throw a ball with {P} {side} arm",
              "^make an overhand throw with {P} {side} arm", "^throw something {count} with {P} {side} hand"],
    "point": ["^point forward with {P} {side} hand", "^point ahead with {P} {side} arm",
              "^point at something with {P} {side} hand", "^point {P} {side} arm forward"],
    "scratch_head": ["^scratch {P} head with {P} {side} hand", "^scratch the top of {P} head with {P} {side} hand",
                     "^rub {P} head with {P} {side} hand", "^bring {P} {side} hand up to scratch {P} head"],
    "drink": ["^drink with {P} {side} hand", "^bring {P} {side} hand to {P} mouth",
              "^take a drink with {P} {side} hand", "^drink from a cup in {P} {side} hand",
              "^raise {P} {side} hand to {P} mouth as if drinking"],
    "hands_on_hips": ["^put {P} {side} hand on {P} hip", "^place {P} {side} hand on the hip",
                      "^rest {P} {side} hand on {P} {side} hip"],
}
ARMS_BOTH = {
    "wave": ["^wave with both hands", "^wave both arms", "^wave both hands in the air", "^raise both hands and ^wave"],
    "raise": ["^raise both arms {count}", "^raise {P} arms above {P} head", "^lift both hands up",
              "^put both hands up", "^raise both hands overhead"],
    "clap": ["^clap", "^clap {P} hands", "^clap {P} hands together", "^clap repeatedly",
             "^clap {P} hands in front of {P} body"],
    "swing": ["^swing {P} arms back and forth", "^swing both arms", "^swing {P} arms",
              "^swing {P} arms forward and back"],
    "flap": ["^flap {P} arms", "^flap {P} arms like a bird", "^flap both arms up and down",
             "^flap {P} arms like wings"],
    "punch": ["^punch with both hands", "^punch forward with alternating fists", "^throw punches with both arms",
              "^punch the air with both fists {count}"],
    "reach_forward": ["^reach forward with both hands", "^extend both arms forward",
                      "^reach out in front with both arms"],
    "arms_out": ["^hold {P} arms out to the sides", "^stretch both arms out", "^spread {P} arms out to the sides",
                 "^raise {P} arms out to the sides", "^extend both arms out sideways"],
    "hands_on_hips": ["^put {P} hands on {P} hips", "^place both hands on {P} hips", "^rest {P} hands on {P} hips",
                      "^put both hands on the hips"],
}
STILL = [" while standing still", " while standing in place", ""]
SWINGING = [", swinging {P} arms", " with {P} arms swinging", ""]
SWAP = {"left": "right", "right": "left", "clockwise": "counterclockwise",
        "counterclockwise": "clockwise", "anticlockwise": "clockwise"}
_SWAP_RE = re.compile(r"\b(left|right|counterclockwise|anticlockwise|clockwise)\b", re.IGNORECASE)


def swap_sides(text: str) -> str:
    """left <-> right, clockwise <-> counterclockwise (case kept for the first letter)."""
    def sub(m):
        w = m.group(0)
        r = SWAP[w.lower()]
        return r.capitalize() if w[0].isupper() else r
    return _SWAP_RE.sub(sub, text)


def swap_token(tok: str) -> str:
    word, pos = tok.rsplit("/", 1)
    return f"{SWAP.get(word, word)}/{pos}"


# ----------------------------------------------------------------------------- rendering
def _conj(template: str, form: str) -> str:
    f = third_person if form == "3sg" else gerund
    return re.sub(r"\^(\w+)", lambda m: f(m.group(1)), template)


def _choose(rng, items):
    return items[int(rng.integers(len(items)))]


class _Voice:
    def __init__(self, rng, cfg):
        subj, poss = _choose(rng, [tuple(s) for s in cfg["subjects"]])
        self.subject, self.poss = subj, poss
        self.use_poss = bool(rng.random() < float(cfg["possessive_prob"]))
        self.cfg = cfg

    @property
    def P(self) -> str:
        return self.poss if self.use_poss else "the"


def _fill(template: str, a: ActionSpec | None, voice: _Voice, rng, traj: Trajectory | None = None) -> str:
    side = a.side if a is not None and a.side in ("left", "right") else ""
    d = ""
    if traj is not None and traj.kind in ("veer_left", "turn_left", "lateral_left", "circle_ccw"):
        d = "left"
    elif traj is not None and traj.kind in ("veer_right", "turn_right", "lateral_right", "circle_cw"):
        d = "right"
    reps = a.reps if a is not None and a.reps else 1
    count = ""
    if "{count}" in template and rng.random() < float(voice.cfg["count_prob"]):
        count = COUNT.get(reps, "")
    out = template.format(P=voice.P, side=side, dir=d, count=count, num=NUM.get(reps, str(reps)),
                          s="s" if reps > 1 else "", es="es" if reps > 1 else "",
                          clock="counterclockwise" if d == "left" else "clockwise")
    return re.sub(r"\s+", " ", out).strip().replace(" ,", ",")


def _speed_word(a: ActionSpec, cfg) -> str | None:
    sw = cfg["speed_words"]
    if a.speed < float(sw["slow"]):
        return "slow"
    if a.speed > float(sw["fast"]):
        return "fast"
    return None


def legs_phrase(a: ActionSpec, traj: Trajectory, voice: _Voice, rng) -> str | None:
    """A marked phrase for the legs action, or None when the legs do nothing (stand)."""
    if a.name == "stand":
        return None
    key = "jump_forward" if a.name == "jump" and a.direction == "forward" else a.name
    p = _fill(_choose(rng, LEGS[key]), a, voice, rng, traj)
    word = _speed_word(a, voice.cfg) if a.name in SPEED_ACTIONS else None
    if word and rng.random() < 0.75:
        p += " " + _choose(rng, SPEED_ADVERBS[word])
    if traj.kind in ("veer_left", "veer_right"):
        v = _fill(_choose(rng, VEER), a, voice, rng, traj)
        p += v if v.startswith(",") else " " + v
    return p


def arms_phrase(a: ActionSpec, voice: _Voice, rng) -> str | None:
    if a.name == "rest":
        return None
    table = ARMS_BOTH if a.side in (None, "both") else ARMS_SIDE
    if a.name not in table:
        raise ValueError(f"no caption template for arms action {a.name!r} with side {a.side!r}")
    return _fill(_choose(rng, table[a.name]), a, voice, rng)


def _clause(L: str | None, A: str | None, legs_name: str, voice: _Voice, rng, allow_front=True) -> str:
    """A 3rd-person clause (no subject) for legs phrase L and arms phrase A."""
    if L and A:
        k = int(rng.integers(4 if allow_front else 3))
        if k == 0:
            return f"{_conj(L, '3sg')} while {_conj(A, 'ing')}"
        if k == 1:
            return f"{_conj(A, '3sg')} while {_conj(L, 'ing')}"
        if k == 2:
            return f"{_conj(L, '3sg')} and {_conj(A, '3sg')}"
        return f"{_conj(L, '3sg')}, {_conj(A, 'ing')}"
    if L:
        extra = _fill(_choose(rng, SWINGING), None, voice, rng) if legs_name in GAIT_SWING else ""
        return _conj(L, "3sg") + (" " + extra if extra and not extra.startswith(",") else extra)
    if A:
        return _conj(A, "3sg") + _choose(rng, STILL)
    return _conj(_choose(rng, LEGS["stand"]), "3sg")


def _sentence(subject: str, clause: str, rng) -> str:
    s = f"{subject} {clause}."
    return s[0].upper() + s[1:] if rng.random() < 0.5 else s


def _segment_caption(spec: MotionSpec, k: int, voice: _Voice, rng) -> str:
    legs, arms, traj = spec.segment_actions(k)
    L = legs_phrase(legs, traj, voice, rng)
    A = arms_phrase(arms, voice, rng)
    if L and A and rng.random() < 0.2:          # fronted: "while walking forward, a person waves ..."
        s = f"while {_conj(L, 'ing')}, {voice.subject} {_conj(A, '3sg')}."
        return s[0].upper() + s[1:] if rng.random() < 0.5 else s
    return _sentence(voice.subject, _clause(L, A, legs.name, voice, rng), rng)


def _sequence_caption(spec: MotionSpec, voice: _Voice, rng) -> str:
    (l1, a1, t1), (l2, a2, t2) = spec.segment_actions(0), spec.segment_actions(1)
    then = _choose(rng, [" and then ", ", then ", " and after that "])
    first = "first " if rng.random() < 0.25 else ""
    if spec.kind == "legs_seq":
        L1, L2 = legs_phrase(l1, t1, voice, rng), legs_phrase(l2, t2, voice, rng)
        A = arms_phrase(a1, voice, rng)
        body = f"{first}{_conj(L1, '3sg')}{then}{_conj(L2, '3sg')}"
        if A:
            body += _choose(rng, [f" while {_conj(A, 'ing')}", f", {_conj(A, 'ing')} the whole time"])
    elif spec.kind == "arms_seq":
        A1, A2 = arms_phrase(a1, voice, rng), arms_phrase(a2, voice, rng)
        L = legs_phrase(l1, t1, voice, rng)
        body = f"{first}{_conj(A1, '3sg')}{then}{_conj(A2, '3sg')}"
        body += f" while {_conj(L, 'ing')}" if L else _choose(rng, STILL)
    else:
        c1 = _clause(legs_phrase(l1, t1, voice, rng), arms_phrase(a1, voice, rng), l1.name, voice, rng, False)
        c2 = _clause(legs_phrase(l2, t2, voice, rng), arms_phrase(a2, voice, rng), l2.name, voice, rng, False)
        body = f"{first}{c1}{then}{c2}"
    return _sentence(voice.subject, body, rng)


def _distinct(make, n: int, tries: int = 12) -> list[str]:
    out: list[str] = []
    for _ in range(tries * n):
        c = make()
        if c not in out:
            out.append(c)
        if len(out) == n:
            break
    while len(out) < n:
        out.append(make())
    return out


def make_captions(spec: MotionSpec, rng: np.random.Generator, caption_cfg, fps: float = 20.0) -> list[dict]:
    """Captions of a motion: ``per_motion`` whole-clip ones (start = end = 0) and, for a
    sequence, ``per_segment`` timed ones per segment (seconds). Each is
    ``{"caption", "tokens": ["word/POS", ...], "start", "end"}``."""
    n = int(caption_cfg["per_motion"])
    if spec.is_sequence:
        whole = _distinct(lambda: _sequence_caption(spec, _Voice(rng, caption_cfg), rng), n)
    else:
        whole = _distinct(lambda: _segment_caption(spec, 0, _Voice(rng, caption_cfg), rng), n)
    out = [{"caption": c, "tokens": tag(c), "start": 0.0, "end": 0.0} for c in whole]
    if spec.is_sequence:
        m = int(caption_cfg["per_segment"])
        for k, (s0, s1) in enumerate(spec.segments()):
            end = min(s1, spec.n_frames - 1)          # features have n_frames - 1 frames
            caps = _distinct(lambda: _segment_caption(spec, k, _Voice(rng, caption_cfg), rng), m)
            out += [{"caption": c, "tokens": tag(c), "start": round(s0 / fps, 2), "end": round(end / fps, 2)}
                    for c in caps]
    return out


def caption_lines(caps: list[dict]) -> str:
    """HumanML3D text file content: ``caption#tok/POS ...#start#end`` per line."""
    lines = []
    for c in caps:
        if "#" in c["caption"]:
            raise ValueError(f"caption contains '#': {c['caption']!r}")
        lines.append(f"{c['caption']}#{' '.join(c['tokens'])}#{c['start']:.1f}#{c['end']:.1f}"
                     if c["start"] == 0.0 and c["end"] == 0.0 else
                     f"{c['caption']}#{' '.join(c['tokens'])}#{c['start']:.2f}#{c['end']:.2f}")
    return "\n".join(lines) + "\n"


def mirror_captions(caps: list[dict]) -> list[dict]:
    return [{**c, "caption": swap_sides(c["caption"]), "tokens": [swap_token(t) for t in c["tokens"]]}
            for c in caps]


# ----------------------------------------------------------------------------- part texts
NONE = "No significant movement."


def _other(side: str) -> str:
    return "right" if side == "left" else "left"


def arms_part_text(a: ActionSpec, legs: ActionSpec) -> str:
    gait = legs.name in GAIT_SWING
    gait_words = {"run": "the running motion", "march_in_place": "the marching steps"}.get(legs.name, "the gait")
    if a.name == "rest":
        if not gait:
            return NONE
        if legs.name == "run":
            return "Both arms swing back and forth, bent at the elbows, with the running motion."
        return f"Both arms swing back and forth with {gait_words}."
    both = a.side in (None, "both")
    S = "Both arms" if both else f"The {a.side} arm"
    H = "Both hands" if both else f"The {a.side} hand"
    pl = both
    texts = {
        "wave": f"{S} raise{'' if pl else 's'} up and wave{'' if pl else 's'} side to side",
        "raise": f"{S} lift{'' if pl else 's'} upward and extend{'' if pl else 's'} above the head",
        "clap": "Both hands come together repeatedly in front of the chest to clap",
        "swing": "Both arms swing widely back and forth",
        "flap": "Both arms extend out to the sides and flap up and down",
        "punch": ("Both arms punch forward in turn from a guard position" if pl else
                  f"The {a.side} arm punches forward from a guard position"),
        "reach_forward": f"{S} extend{'' if pl else 's'} forward to reach out in front",
        "arms_out": ("Both arms stretch out to the sides at shoulder height" if pl else
                     f"The {a.side} arm stretches out to the side at shoulder height"),
        "throw": f"The {a.side} arm draws back over the shoulder and whips forward to throw",
        "point": f"The {a.side} arm extends forward to point",
        "scratch_head": f"The {a.side} hand rises to the head and scratches it",
        "drink": f"The {a.side} hand brings a drink up to the mouth",
        "hands_on_hips": (f"{H} rest on the hips with the elbows out" if pl else
                          f"{H} rests on the hip with the elbow out"),
    }
    t = texts[a.name]
    if gait and not both and a.name not in ("clap", "swing", "flap"):
        t += f", while the {_other(a.side)} arm swings with {gait_words}"
    return t + "."


def legs_part_text(a: ActionSpec, traj: Trajectory) -> str:
    side = a.side or ""
    d = {"veer_left": "left", "veer_right": "right"}.get(traj.kind)
    turn = "left" if traj.kind == "turn_left" else "right"
    texts = {
        "stand": NONE,
        "walk_forward": "The legs alternate steps to walk forward" + (f", curving to the {d}" if d else "") + ".",
        "walk_backward": "The legs step backward one after the other.",
        "walk_circle_cw": "The legs walk forward while the body turns clockwise along a circle.",
        "walk_circle_ccw": "The legs walk forward while the body turns counterclockwise along a circle.",
        "run": "The legs alternate rapidly, pushing off the ground to run forward"
               + (f", curving to the {d}" if d else "") + ".",
        "march_in_place": "The legs march in place, lifting the knees high.",
        "turn_around": f"The legs step in place while the body turns around to the {turn}.",
        "jump": ("The legs bend and push off to jump forward, then land." if a.direction == "forward"
                 else "The legs bend and push off the ground to jump, then land back down."),
        "hop": f"The {side} leg hops repeatedly while the {_other(side) if side else 'other'} leg stays lifted.",
        "squat": "The legs bend at the knees and hips to squat down, then straighten.",
        "kick": f"The {side} leg swings forward to kick, while the {_other(side) if side else 'other'} leg "
                "supports the body's weight.",
        "lunge": f"The {side} leg steps forward into a lunge, then steps back.",
        "sit_down": "The legs bend at the knees and lower the body into a sitting position.",
        "side_step": f"The legs step sideways to the {a.direction}.",
    }
    return texts[a.name]


def _join(texts: list[str], part: str) -> str:
    if len(texts) == 1 or texts[0] == texts[1]:
        return texts[0]
    if all(t == NONE for t in texts):
        return NONE
    t1 = f"The {part} stay still." if texts[0] == NONE else texts[0]
    t2 = f"The {part} stay still." if texts[1] == NONE else texts[1]
    return f"{t1[:-1]}, then {t2[0].lower()}{t2[1:]}"


def make_part_texts(spec: MotionSpec) -> dict[str, str]:
    """Ground-truth ``{"arms": ..., "legs": ...}`` (SPEC §4 style; one sentence per part)."""
    n = len(spec.segments())
    arms = [arms_part_text(spec.segment_actions(k)[1], spec.segment_actions(k)[0]) for k in range(n)]
    legs = [legs_part_text(spec.segment_actions(k)[0], spec.segment_actions(k)[2]) for k in range(n)]
    return {"arms": _join(arms, "arms"), "legs": _join(legs, "legs")}
