"""Offline, deterministic part-text extractor: a small English lexicon instead of an LLM.

A caption is split into clauses (punctuation, and/then/while/...), each clause into events that
start at a known verb. An event moves a part when

- the clause names a body part of it (arm/hand/wrist/fist/... -> arms, leg/foot/knee/... -> legs),
  with the side from the modifiers before the noun (left, right, both, two, his <plural>, one); or
- the verb implies the part: locomotion (walk, run, march, ...) moves the legs, and walking-like
  gaits swing both arms in every phase of the motion ("..., then ...") where the arms do nothing
  else (not sideways steps or shuffles); leg actions (jump, kick, squat, sit down, stand up, ...)
  move the legs; arm actions (wave, clap, throw, punch, ...) move the arms when no body part is
  named; whole-body actions (swim, crawl, dance, ...) move both. After a contact verb (touch,
  scratch, grab, ...) a leg noun is touched by a hand, unless it is the instrument ("with the
  foot"); "it"/"them" refers back to the last body part.

Static verbs (stand/stay/remain, "while sitting") and torso verbs (bow, lean, nod, turn the head)
move nothing by themselves. A part with no event is "No significant movement". The text of a
moving part is "<Side> <part> <verb> <rest of the clause>", e.g. "The right arm waves."
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

from party.text.backends.base import PartTextResult
from party.text.prompt import NO_MOVEMENT

# ------------------------------------------------------------------ lexicon
# the parts the lexicon tells apart (nouns, verb classes and texts below); part_texts.parts
# chooses which of them a run writes
LEXICON_PARTS = ("arms", "legs")
ARM_NOUNS = {"arm", "hand", "wrist", "elbow", "fist", "finger", "palm", "forearm", "shoulder", "thumb"}
LEG_NOUNS = {"leg", "foot", "knee", "toe", "heel", "ankle", "thigh", "shin", "calf", "feet", "tiptoe"}
PLURAL = {"feet": "foot", "calves": "calf"}

LOCOMOTION = ("walk run jog sprint march stroll strut stride pace wander hike shuffle limp stagger "
              "trot skip waddle sneak creep tiptoe prance gallop dash hurry rush").split()
# gaits whose arms swing along ("walks", "runs"); sideways or creeping gaits do not
SWING_GAITS = set("walk run jog sprint march stroll strut stride pace wander hike trot dash hurry rush "
                  "gallop".split())
LATERAL = {"sideways", "sidewards", "side", "left", "right"}
# move only with a direction: "moves forward", "goes to the left"
DIRECTED = "move go come travel proceed advance retreat circle".split()
DIRECTIONS = set("forward forwards backward backwards back ahead around sideways sidewards left right "
                 "across toward towards to away diagonally circle straight up down over".split())
LEG_ACTIONS = ("jump hop leap kick squat crouch kneel lunge step stomp sidestep stumble trip balance "
               "sit rise get lie lay fall bounce skate ski pedal cycle spin pivot climb turn "
               "straddle mount dismount land stamp trample").split()
ARM_ACTIONS = ("wave clap throw toss catch punch box jab reach grab grasp pick lift raise lower push "
               "pull point salute scratch wipe stir drink eat hold carry hug shake stretch flap juggle "
               "rub touch brush comb type play row dig sweep hammer knock pour applaud cross fold cover "
               "swat slap strike swing dribble shoot pat signal beckon gesture conduct shrug put place "
               "drop open close wash block flex rotate extend spread hit paint write draw cut "
               "chop shovel mop wring twirl cheer pray stab wield swipe lob pitch serve bang drum strum bring "
               "tie aim fire ring answer clean flail fan wiggle tap press scoop hang grip squeeze "
               "shield").split()
WHOLE_BODY = "swim crawl dance cartwheel somersault tumble wrestle fight exercise jumping_jack".split()
PHRASES = {r"\bjumping jacks?\b": "jumping_jack", r"\bstar jumps?\b": "jumping_jack",
           r"\bskip(s|ping)? rope\b": "jumping_jack", r"\bjump(s|ing)? rope\b": "jumping_jack",
           r"\btakes a seat\b": "sits down", r"\btaking a seat\b": "sitting down",
           r"\btook a seat\b": "sat down", r"\btake a seat\b": "sit down",
           r"\bhas a seat\b": "sits down"}
SHOULDER_PREPS = {"over", "behind", "past", "across"}
NP_PREPS = {"with", "using", "by", "on", "onto", "in", "into"}
TORSO = "bow lean bend twist nod look tilt sway duck crane hunch arch slouch".split()
STATIC = "stand stay remain wait idle pause stop halt freeze".split()
# leg actions whose -ing form after "while"/"is" describes a held pose, not a movement
POSTURES = {"sit", "kneel", "lie", "lay"}
# nouns that make the verb's event a legs event ("lowers the body into a sitting position")
LEG_POSTURE_NOUNS = {"squat", "lunge", "crouch", "sitting", "seat", "kneeling", "split", "splits"}
# which side a part takes when the verb implies it and the caption names none
BOTH_ARMS = set("clap applaud hug carry row cheer pray shrug flap fold cross juggle wring drum "
                "swim crawl dance cartwheel somersault tumble exercise push lift".split())
ONE_LEG = set("kick stomp stamp".split())
# arm verbs whose body-part object is touched, not moved ("touches his toes", "scratches the knee")
CONTACT = set("touch grab grasp hold scratch rub pat slap point reach hit brush wipe tap clean wash "
              "grip squeeze cover".split())
INSTRUMENT_PREPS = {"with", "using", "by"}

IRREGULAR = {
    "ran": "run", "swam": "swim", "sat": "sit", "stood": "stand", "threw": "throw", "thrown": "throw",
    "caught": "catch", "knelt": "kneel", "leapt": "leap", "dug": "dig", "swung": "swing", "held": "hold",
    "got": "get", "gotten": "get", "lay": "lie", "lain": "lie", "lying": "lie", "fell": "fall",
    "fallen": "fall", "rose": "rise", "risen": "rise", "shook": "shake", "shaken": "shake", "went": "go",
    "gone": "go", "came": "come", "struck": "strike", "drew": "draw", "drawn": "draw", "wrote": "write",
    "ate": "eat", "drank": "drink", "hit": "hit", "put": "put", "cut": "cut", "spun": "spin",
    "rang": "ring", "hung": "hang", "strode": "stride", "crept": "creep", "dove": "dive", "shot": "shoot",
    "tore": "tear", "bent": "bend", "climbed": "climb", "laid": "lay", "swept": "sweep", "wrung": "wring",
    "stuck": "stick", "fought": "fight", "brought": "bring", "lit": "light",
}
NOT_VERBS = {"left", "right", "rest", "still", "well", "face", "side"}  # ambiguous words

SUBJECTS = set("a an the person man woman someone somebody figure human character individual guy girl "
               "boy lady he she they it one people subject".split())
POSSESSIVE = {"his": "the", "her": "the", "their": "the", "its": "the", "my": "the", "your": "the"}
SIDE_MOD = {"left": "left", "right": "right", "both": "both", "two": "both", "each": "both",
            "either": "one", "one": "one", "other": "one", "single": "one", "alternate": "both",
            "alternating": "both"}
NOUN_BRIDGE = SIDE_MOD.keys() | POSSESSIVE.keys() | {"the", "a", "an", "of", "and", "upper", "lower", "bent",
                                                     "straight", "outstretched", "extended", "raised"}
SPLIT_WORDS = {"then", "while", "whilst", "as", "before", "after", "when", "until", "afterwards",
               "meanwhile", "finally", "next", "but", "also", "again", "so"}
# clause words that start a new phase of the motion (what follows happens later)
SEQUENCE_WORDS = {"then", "after", "afterwards", "finally", "next", "before", "until", "again"}


def _cvc(w: str) -> bool:
    """Might double its last consonant (step -> stepping, squat -> squatting); over-generating
    forms that never occur ("walkking") is harmless."""
    return len(w) >= 3 and w[-1] not in "aeiouwxy" and w[-2] in "aeiou"


def verb_forms(base: str) -> set[str]:
    forms = {base}
    forms.add(base + "es" if base.endswith(("s", "sh", "ch", "x", "z", "o")) else
              base[:-1] + "ies" if base.endswith("y") and base[-2] not in "aeiou" else base + "s")
    if base.endswith("ie"):
        forms |= {base[:-2] + "ying", base + "d"}
    elif base.endswith("e") and not base.endswith(("ee", "ye", "oe")):
        forms |= {base[:-1] + "ing", base + "d"}
    else:
        forms |= {base + "ing", base[:-1] + "ied" if base.endswith("y") and base[-2] not in "aeiou"
                  else base + "ed"}
        if _cvc(base):
            forms |= {base + base[-1] + "ing", base + base[-1] + "ed"}
    return forms


def _build_forms() -> dict[str, str]:
    table: dict[str, str] = {}
    for group in (LOCOMOTION, DIRECTED, LEG_ACTIONS, ARM_ACTIONS, WHOLE_BODY, TORSO, STATIC):
        for base in group:
            for f in verb_forms(base):
                table.setdefault(f, base)
    for form, base in IRREGULAR.items():
        if base in table:                  # only irregular forms of verbs in the lexicon
            table[form] = base
    for w in NOT_VERBS:
        table.pop(w, None)
    return table


FORMS = _build_forms()
BASE_CLASS = {**{b: "torso" for b in TORSO}, **{b: "static" for b in STATIC},
              **{b: "arms" for b in ARM_ACTIONS}, **{b: "legs" for b in LEG_ACTIONS},
              **{b: "whole" for b in WHOLE_BODY}, **{b: "directed" for b in DIRECTED},
              **{b: "locomotion" for b in LOCOMOTION}}


def third_person(base: str) -> str:
    if base.endswith(("s", "sh", "ch", "x", "z", "o")):
        return base + "es"
    if base.endswith("y") and base[-2] not in "aeiou":
        return base[:-1] + "ies"
    return base + "s"


def gerund(base: str) -> str:
    if base.endswith("ie"):
        return base[:-2] + "ying"
    if base.endswith("e") and not base.endswith(("ee", "ye", "oe")):
        return base[:-1] + "ing"
    if base in {"run", "jog", "hop", "skip", "step", "swim", "sit", "stop", "trot", "spin", "dig", "drop",
                "clap", "flap", "grab", "pat", "tap", "strum", "drum", "stab", "swat", "slap", "chop",
                "mop", "plan", "skip"}:
        return base + base[-1] + "ing"
    return base + "ing"


# ------------------------------------------------------------------ parsing
_WORD = re.compile(r"[a-z]+|[.,;:!?]")


def tokenize(caption: str) -> list[str]:
    """Lower-case words and punctuation; "left and right" -> "both"; "arms and legs" keeps its
    "and" as "and_" so that it does not split the clause."""
    s = caption.lower().replace("-", " ").replace("’", "'")
    s = re.sub(r"'s\b", "", s)
    s = re.sub(r"\bleft and right\b|\bright and left\b", "both", s)
    for pat, rep in PHRASES.items():
        s = re.sub(pat, rep, s)
    s = re.sub(r"\b(arms|hands|legs|feet|knees) and (arms|hands|legs|feet|knees)\b", r"\1 and_ \2", s)
    return re.findall(r"[a-z]+(?:_[a-z]*)?|[.,;:!?]", s)


def _part_of(tok: str) -> tuple[str, bool] | None:
    """(part, plural) for a body-part noun token."""
    if tok in PLURAL:
        return ("legs" if PLURAL[tok] in LEG_NOUNS else "arms"), True
    if tok in ARM_NOUNS:
        return "arms", False
    if tok in LEG_NOUNS:
        return "legs", tok == "feet"
    if tok.endswith("s") and tok[:-1] in ARM_NOUNS:
        return "arms", True
    if tok.endswith("s") and tok[:-1] in LEG_NOUNS:
        return "legs", True
    return None


def _mentions(toks: list[str]) -> list[tuple[str, str | None, int, int]]:
    """Body-part nouns as (part, side, span start, noun index); side from the modifiers right
    before the noun; the span covers modifiers and a leading "with"/"on"/... preposition."""
    out = []
    for j, t in enumerate(toks):
        p = _part_of(t)
        if p is None:
            continue
        part, plural = p
        if t.startswith("shoulder") and j >= 2 and (toks[j - 2] in SHOULDER_PREPS or toks[j - 3:j - 2] == ["over"]):
            continue                      # "turns around over the left shoulder": a direction
        side = None
        k = j - 1
        while k >= 0 and j - k <= 4 and toks[k] in NOUN_BRIDGE:
            if toks[k] in SIDE_MOD:
                s = SIDE_MOD[toks[k]]
                side = s if side in (None, s) else "both"
            k -= 1
        while k >= 0 and j - k <= 3 and toks[k].isalpha() and toks[k] not in FORMS \
                and toks[k] not in PREPOSITIONS and toks[k] not in SPLIT_WORDS and not _part_of(toks[k]):
            k -= 1                        # adjectives: "with high knees"
        if k >= 0 and toks[k] in NP_PREPS:
            k -= 1
        if side is None and plural:
            side = "both"
        out.append((part, side, k + 1, j))
    return out


ALL_PHASES = -1


def _whole_time(clause: list[str]) -> bool:
    """'... the whole time', 'throughout': the clause spans every phase of the motion."""
    text = " ".join(clause)
    return bool(re.search(r"\b(whole|entire) time\b|\bthroughout\b|\ball (the )?while\b|\ball along\b", text))


def _clauses(toks: list[str]) -> list[tuple[int, list[str]]]:
    """(phase, clause) pairs. Split at punctuation and clause words; split at 'and' only when
    what follows has a verb or a body part ('jumps up and down' stays one clause). The phase
    grows at sequence words ('then', 'after', ...): later phases happen later."""
    pieces, cur, phase, phases = [], [], 0, []
    for t in toks:
        if t in ".,;:!?" or t in SPLIT_WORDS:
            if cur:
                pieces.append(cur)
                phases.append(ALL_PHASES if _whole_time(cur) else phase)
            cur = []
            if t in SEQUENCE_WORDS:
                phase += 1
        else:
            cur.append(t)
    if cur:
        pieces.append(cur)
        phases.append(ALL_PHASES if _whole_time(cur) else phase)
    out = []
    for phase, piece in zip(phases, pieces):
        segs, cur = [], []
        for t in piece + ["and"]:
            if t == "and":
                if segs and cur and not any(w in FORMS or _part_of(w) for w in cur):
                    segs[-1] += ["and", *cur]
                elif cur:
                    segs.append(cur)
                cur = []
            else:
                cur.append(t)
        out += [(phase, seg) for seg in segs]
    return out


DETERMINERS = {"a", "an", "the", "his", "her", "their", "its", "some", "another"}
NUMERALS = {"two", "three", "four", "five", "six", "few", "several", "many", "multiple", "more"}
# lexicon words that still name the action after a determiner ("takes a step", "does a kick")
ACTION_NOUNS = set("step kick jump hop leap wave punch squat lunge spin walk run jog sprint swim dance "
                   "cartwheel somersault jumping_jack throw clap bow stretch crawl march skip stride "
                   "turn drink".split())


PREPOSITIONS = {"in", "on", "at", "into", "onto", "of", "from", "for", "with", "by", "over", "under",
                "above", "below", "behind", "near", "across", "through", "upon"}


def _is_verb(toks: list[str], i: int) -> bool:
    t = toks[i]
    if t not in FORMS:
        return False
    base = FORMS[t]
    if base in ("lie", "lay", "get") and (i + 1 >= len(toks) or toks[i + 1] not in ("down", "up", "on", "flat")):
        return False                      # "get" only as get up/down; "lies" as lie down/on
    det = DETERMINERS | NUMERALS
    if i and (toks[i - 1] in det or (i > 1 and toks[i - 2] in det and toks[i - 1] not in FORMS
                                     and toks[i - 1] not in SUBJECTS)):     # "a big step", not "a man steps"
        if base not in ACTION_NOUNS:
            return False                  # "in a circle", "a box", "the ring"
        if any(w in FORMS and w not in det for w in toks[:i - 1]):
            return False                  # "steps forward into a lunge": an object, not a new action
    if i and toks[i - 1] in PREPOSITIONS:
        return False                      # "jogs in place", "hand on the hip"
    return True


# ------------------------------------------------------------------ realisation
def _subject(part: str, side: str | None) -> tuple[str, bool]:
    noun = "arm" if part == "arms" else "leg"
    if side in ("left", "right"):
        return f"The {side} {noun}", False
    if side == "both":
        return f"Both {noun}s", True
    if side == "one":
        return f"One {noun}", False
    return f"The {noun}s", True


DISPLAY = {"jumping_jack": ("do jumping jacks", "does jumping jacks")}


def _predicate(base: str, rest: list[str], plural: bool) -> str:
    if base in DISPLAY:
        verb = DISPLAY[base][0 if plural else 1]
        rest = [w for w in rest if not w.startswith("jumping_jack")]
    else:
        verb = base if plural else third_person(base)
    words = [POSSESSIVE.get(w, w) for w in rest]
    words = ["and" if w == "and_" else w for w in words]
    return " ".join([verb, *words]).strip()


class RulesBackend:
    name = "rules"

    def __init__(self, cfg=None):
        """``cfg``: the part_texts config (``parts``, ``no_movement_text``); None: every part of
        the lexicon, the default no-movement text (the agreement tool)."""
        self.no_movement = str(cfg.get("no_movement_text", NO_MOVEMENT)) if cfg is not None else NO_MOVEMENT
        self.part_names = tuple(str(p) for p in cfg.parts) if cfg is not None else LEXICON_PARTS
        unknown = [p for p in self.part_names if p not in LEXICON_PARTS]
        if unknown or not self.part_names:
            raise ValueError(f"part_texts.parts={list(self.part_names)}: the rules backend knows the parts "
                             f"{list(LEXICON_PARTS)}")
        src = Path(__file__).read_bytes()
        self.fingerprint = hashlib.sha1(src).hexdigest()[:12]
        self.model = f"rules-{self.fingerprint}"          # rule changes invalidate the cache

    def extract(self, caption: str) -> dict:
        """{"arms": [(side, text)], "legs": [...]} events; empty list = no movement."""
        events: dict[str, list] = {p: [] for p in LEXICON_PARTS}
        swings: dict[int, str] = {}                        # phase -> first swinging gait
        arm_phases: set[int] = set()
        ev_phase: list[int] = []                           # phase of each arms event
        last_verb, last_ment = None, None
        phase = 0

        def mark():                                        # phases of the arms events added so far
            for _ in events["arms"][len(ev_phase):]:
                arm_phases.add(phase)
                ev_phase.append(phase)
        for phase_, clause in _clauses(tokenize(caption)):
            mark()
            phase = phase_
            verbs = [i for i in range(len(clause)) if _is_verb(clause, i)]
            if not verbs and last_verb is None:           # "with arms crossed, ...": a held pose
                for part, side, a, j in _mentions(clause):
                    subj, pl = _subject(part, side)
                    events[part].append((side, f"{subj} {'stay' if pl else 'stays'} "
                                         + " ".join(POSSESSIVE.get(w, w) for w in clause[j + 1:])))
                continue
            inherited = not verbs
            if inherited:
                if not _mentions(clause):                  # "and then stops": nothing we know
                    continue
                verbs, clause = [0], [last_verb, *clause]  # "raises the left arm and the right arm"
            starts = verbs + [len(clause)]
            for n, (a, b) in enumerate(zip(starts, starts[1:])):
                lo = 0 if n == 0 else a                    # words before the first verb join it
                seg, base = clause[lo:b], FORMS[clause[a]]
                last_verb = clause[a]
                cls = self._verb_class(clause, a, base)
                ment = _mentions(seg)
                rest = clause[a + 1:b]
                if not ment and last_ment and rest[:1] in (["it"], ["them"]) and cls != "static":
                    # "lifts the left leg and then puts it down": the pronoun is the last body part
                    part, side = last_ment
                    ment = [(part, side, a - lo + 1, a - lo + 1)]
                    cls = "named"
                ment = self._actors(ment, base, seg)
                if ment:
                    last_ment = ment[-1][:2]
                self._events(events, "named" if inherited else cls, base, seg, a - lo, ment)
                if not inherited and self._swings_arms(clause[a + 1:b], base, cls, ment):
                    swings.setdefault(phase, base)
        mark()
        # walking-like gaits swing both arms in the phases where the arms do nothing else
        for phase, base in swings.items():
            if phase not in arm_phases and ALL_PHASES not in arm_phases:
                k = sum(p < phase for p in ev_phase)
                events["arms"].insert(k, ("both", f"Both arms swing back and forth naturally with "
                                                  f"the {gerund(base)} motion"))
                ev_phase.insert(k, phase)
        return events

    @staticmethod
    def _actors(ment, base: str, seg: list[str]):
        """A body part after a contact verb is touched by a hand, unless it is the instrument
        ("touches his toes" -> an arm; "taps with his left foot" -> the left leg)."""
        if base not in CONTACT:
            return ment
        out = []
        for part, side, a, j in ment:
            if part == "legs" and seg[a] not in INSTRUMENT_PREPS:
                part, side, a = "arms", "one", j + 1      # empty span: the object stays in the text
            out.append((part, side, a, j))
        return out

    @staticmethod
    def _swings_arms(rest: list[str], base: str, cls: str, ment) -> bool:
        """Walking-like gaits swing the arms: walk/run/march..., moving/circling forward or back,
        stepping forward/backward/in place; not sideways steps, shuffles or single named-leg steps."""
        lateral = bool(set(rest[:4]) & LATERAL)
        if base in SWING_GAITS:
            return True
        if any(p == "legs" for p, *_ in ment):
            return False                                   # "steps forward with the left foot"
        if cls == "locomotion" and base in DIRECTED:
            return not lateral
        if base == "step":
            ahead = set(rest[:3]) & {"forward", "forwards", "backward", "backwards", "back", "ahead"}
            in_place = "place" in rest[:3] or "spot" in rest[:3]
            return not lateral and bool(ahead or in_place)
        return False

    @staticmethod
    def _verb_class(clause: list[str], a: int, base: str) -> str:
        cls, rest = BASE_CLASS[base], clause[a + 1:]
        named = bool(_mentions(rest[:5]))
        if cls == "directed":                              # "moves backwards" vs "moves his arm up"
            return "locomotion" if set(rest[:2]) & DIRECTIONS or (set(rest[:3]) & DIRECTIONS and not named) \
                else "torso"
        if base == "stand":
            return "legs" if "up" in rest[:2] else "static"       # "stands (back) up"
        if base in POSTURES and clause[a].endswith("ing") and "down" not in rest[:2] \
                and (a == 0 or clause[a - 1] in ("is", "are", "while")):
            return "static"                                # "while sitting", "is kneeling"
        if any(w in LEG_POSTURE_NOUNS and (i == 0 or rest[i - 1] in ("a", "an", "into", "the"))
               for i, w in enumerate(rest[:6])):
            return "legs"                                  # "lowers the body into a sitting position"
        if base == "turn" and (named or any(w in ("head", "torso", "body", "waist", "neck", "upper")
                                            for w in rest[:3])):
            return "torso"                                 # "turns his head"
        return cls

    @staticmethod
    def _events(events, cls, base, seg, v, ment) -> None:
        """Add the events of one verb segment (``seg[v]`` is the verb)."""
        drop = {i for _, _, a, j in ment for i in range(a, j + 1)}
        rest = [w for i, w in enumerate(seg) if i > v and i not in drop]
        named = {p for p, _, _, _ in ment}
        for part, side, a, j in ment:
            subj, pl = _subject(part, side)
            if part == "arms" and cls in ("locomotion", "legs", "static"):  # "walks with hands on hips"
                after = [POSSESSIVE.get(w, w) for w in seg[j + 1:] if _part_of(w) is None]
                if after and BASE_CLASS.get(FORMS.get(after[0], ""), "") == "arms":
                    verb = FORMS[after[0]]                     # "with the arms swinging"
                    events[part].append((side, f"{subj} {_predicate(verb, after[1:], pl)}"))
                else:
                    events[part].append((side, f"{subj} {'stay' if pl else 'stays'} {' '.join(after)}".strip()))
            elif part == "legs" and cls == "static":
                continue                                            # "stands on both feet"
            else:
                events[part].append((side, f"{subj} {_predicate(base, rest, pl)}"))
        implied = {"locomotion": ["legs"], "legs": ["legs"], "whole": ["arms", "legs"],
                   "arms": [] if named else ["arms"]}.get(cls, [])
        for part in implied:
            if part in named:
                continue
            if part == "legs":
                side = "one" if base in ONE_LEG else "both"
            else:
                side = "both" if base in BOTH_ARMS or cls == "whole" else "one"
            subj, pl = _subject(part, side)
            # the predicate stops where another part's phrase starts ("walks forward | with hands on hips")
            cut = min([a for p, _, a, _ in ment if p != part] + [len(seg)])
            own = [w for i, w in enumerate(seg[:cut]) if i > v and i not in drop]
            events[part].append((side, f"{subj} {_predicate(base, own, pl)}"))

    def parts(self, caption: str) -> dict:
        ev = self.extract(caption)
        out = {}
        for part in self.part_names:
            if not ev[part]:
                out[part] = self.no_movement
                continue
            texts = list(dict.fromkeys(t for _, t in ev[part]))
            text = ", then ".join([texts[0], *(t[0].lower() + t[1:] for t in texts[1:])])
            out[part] = text[0].upper() + text[1:] + "."
        return out

    def describe(self, caption: str) -> PartTextResult:
        return PartTextResult(parts=self.parts(caption), calls=1)
