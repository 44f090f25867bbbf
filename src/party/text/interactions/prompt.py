"""TextIM's interaction prompt and the check of its answers (SPEC-textim §3, paper §3.3).

A second prompt family beside the part-text prompt (``party.text.prompt``), on the same backends.

- The prompt is a chat: the system message holds the paper's aspects (i)-(iii), the side and
  copy rules of the SPEC and the lead-in of aspect (iv); the six few-shot examples follow as
  user/assistant turns; the last user turn asks for the caption. ``prompt_fingerprint`` hashes
  the rendered prompt (and the retry feedback template), so a prompt edited under an unchanged
  ``PROMPT_VERSION`` is caught by the cache.
- An answer is one line per interaction, ``<part>[, <part>...]: <exact phrase>``, or ``none``.
  ``parse_answer`` checks the format and amends the content: body parts are mapped onto the six
  parts (``map_part``), and each phrase is located in the caption (``locate_phrase``): a
  normalised substring, or else the longest caption span that shares at least ``span_overlap``
  of its tokens with the phrase (and the phrase of its tokens with the span). What fails raises
  ``InteractionFormatError`` with a message that is fed back to the model on the next attempt.
- ``merge`` joins the lines: the parts are the union, ``c_inter`` the phrases (exact caption
  spans) joined with "; " in caption order, and ``c_non`` the caption with every phrase cut out
  (``non_interaction_text``).
"""
from __future__ import annotations

import hashlib
import json
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

PROMPT_VERSION = "textim-v1"

# the six parts, in the order of the channel table (SPEC §2) and of every parts tuple
PARTS = ("pelvis", "torso", "left_arm", "right_arm", "left_leg", "right_leg")
PART_LABEL = {p: p.replace("_", " ") for p in PARTS}            # left_arm -> "left arm"
UNSIDED = ("both", "right")

ASPECTS = (
    "Identify all possible body parts involved in interacting with an object from the given sentence and "
    "extract the exact phrase that describes their action.",
    "An 'interaction' involves any purposeful physical engagement with an object, such as holding, touching, "
    "lifting, carrying, moving, manipulating, or using it in any way.",
    "If no body parts are interacting with an object, respond with 'none'. Choose body parts from: left arm, "
    "right arm, left leg, right leg, torso, pelvis.",
)
RULES = ("If the sentence does not say which side, list both sides.",
         "Copy the phrase word for word from the sentence.")
EXAMPLES_LEAD = "Here are examples of how to format your responses:"
QUESTION = "Provide your answer for the following sentence: \"{caption}\""
FEEDBACK = ("Your answer was not accepted: {error}. Answer again for the same sentence: one line per "
            "interaction, \"<body part>[, <body part>...]: <exact phrase from the sentence>\", or the single "
            "word \"none\".")
SYSTEM = " ".join((*ASPECTS, *RULES, EXAMPLES_LEAD))

# SPEC §3: (caption, answer)
FEW_SHOT = (
    ("a person wipes the table with their left hand.",
     "left arm: wipes the table with their left hand"),
    ("a man picks up a box with both hands and puts it on a shelf.",
     "left arm, right arm: picks up a box with both hands and puts it on a shelf"),
    ("someone walks forward and kicks a ball with the right foot.",
     "right leg: kicks a ball with the right foot"),
    ("a person cleans the table with the right hand while looking at the watch on the left wrist.",
     "right arm: cleans the table with the right hand\nleft arm: looking at the watch on the left wrist"),
    ("a person sits down on a chair.",
     "pelvis: sits down on a chair"),
    ("a person jogs in a circle counterclockwise.",
     "none"),
)


def question(caption: str) -> str:
    return QUESTION.format(caption=caption.strip())


def build_messages(caption: str, system: str = SYSTEM, examples: Sequence[tuple[str, str]] = FEW_SHOT) -> list[dict]:
    """The chat for one caption: system message, few-shot turns, the question."""
    msgs = [{"role": "system", "content": system}]
    for cap, answer in examples:
        msgs.append({"role": "user", "content": question(cap)})
        msgs.append({"role": "assistant", "content": answer})
    msgs.append({"role": "user", "content": question(caption)})
    return msgs


def feedback_messages(answer: str, error: str) -> list[dict]:
    """The turns a retry appends: the rejected answer and the validator's error."""
    return [{"role": "assistant", "content": answer or ""},
            {"role": "user", "content": FEEDBACK.format(error=error)}]


def prompt_fingerprint(system: str = SYSTEM, examples: Sequence[tuple[str, str]] = FEW_SHOT,
                       feedback: str = FEEDBACK) -> str:
    """12 hex digits of the rendered prompt (with a ``{caption}`` placeholder) and the feedback turn."""
    rendered = {"messages": build_messages("{caption}", system, examples), "feedback": feedback}
    return hashlib.sha1(json.dumps(rendered, sort_keys=True).encode()).hexdigest()[:12]


class InteractionFormatError(ValueError):
    """An answer that fails the format check or the content amendment; the message is the feedback."""


# ------------------------------------------------------------------ part mapping (content amendment)
ARM_WORDS = {"hand", "finger", "palm", "thumb", "wrist", "forearm", "elbow", "upper arm", "shoulder",
             "collarbone", "clavicle", "arm", "fist"}
LEG_WORDS = {"foot", "feet", "toe", "heel", "ankle", "shin", "calf", "calves", "knee", "thigh", "leg"}
TORSO_WORDS = {"head", "neck", "face", "chin", "chest", "back", "spine", "abdomen", "stomach", "torso",
               "upper body", "trunk"}
PELVIS_WORDS = {"waist", "hips", "buttocks", "buttock", "pelvis", "lap", "butt", "hip"}
_PLURAL_IRREGULAR = {"feet": "foot", "calves": "calf"}
_SIDE_WORDS = {"left": "left", "right": "right", "both": "both", "two": "both", "each": "both"}
_FILLER = {"the", "a", "an", "his", "her", "their", "its", "my", "your", "of", "upper_", "side"}


def _noun(words: list[str]) -> tuple[str, bool] | None:
    """(singular body word, plural) of the last body word of ``words``."""
    text = " ".join(words)
    if re.search(r"\bupper (arm|arms)\b", text):
        return "upper arm", text.endswith("arms")
    if re.search(r"\bupper body\b", text):
        return "upper body", False
    for w in reversed(words):
        if w in _PLURAL_IRREGULAR:
            return _PLURAL_IRREGULAR[w], True
        if w in ARM_WORDS | LEG_WORDS | TORSO_WORDS | PELVIS_WORDS:
            return w, w == "hips" or w == "buttocks"
        if w.endswith("s") and w[:-1] in ARM_WORDS | LEG_WORDS | TORSO_WORDS | PELVIS_WORDS:
            return w[:-1], True
    return None


def map_part(text: str, unsided: str = "both") -> tuple[str, ...]:
    """The six-part names a body-part phrase of an answer stands for (case-insensitive, keeping the
    side): ``"left wrist"`` -> (left_arm,), ``"hips"`` -> (pelvis,), ``"hand"`` -> both arms
    (``unsided="both"``) or the right arm (``"right"``); () when it names no known part."""
    if unsided not in UNSIDED:
        raise ValueError(f"interactions.unsided={unsided!r}: choose from {list(UNSIDED)}")
    t = text.lower().replace("_", " ").replace("-", " ")
    t = re.sub(r"\b(left and right|right and left)\b", "both", t)
    words = re.findall(r"[a-z]+", t)
    if not words:
        return ()
    if words in (["torso"], ["pelvis"]):
        return (words[0],)
    sides = {_SIDE_WORDS[w] for w in words if w in _SIDE_WORDS}
    side = "both" if "both" in sides or len(sides) > 1 else next(iter(sides), None)
    found = _noun(words)
    if found is None:
        return ()
    noun, plural = found
    if noun in ("hip", "hips") and side is None:
        return ("pelvis",)
    if noun in ("hip", "hips"):
        limb = "leg"
    elif noun in ARM_WORDS:
        limb = "arm"
    elif noun in LEG_WORDS:
        limb = "leg"
    elif noun in TORSO_WORDS:
        return ("torso",)
    else:
        return ("pelvis",)
    if side is None:
        side = "both" if plural else unsided
    sides_ = ("left", "right") if side == "both" else (side,)
    return tuple(f"{s}_{limb}" for s in sides_)


def sort_parts(parts) -> tuple[str, ...]:
    """Parts in the order of ``PARTS``, each once (a ValueError names an unknown one)."""
    parts = set(parts)
    unknown = parts - set(PARTS)
    if unknown:
        raise ValueError(f"unknown part(s) {sorted(unknown)}: the parts are {list(PARTS)}")
    return tuple(p for p in PARTS if p in parts)


# ------------------------------------------------------------------ phrases in the caption
_WORD = re.compile(r"[A-Za-z0-9]+(?:['’][A-Za-z]+)*")


@dataclass(frozen=True)
class Token:
    norm: str
    start: int
    end: int


def caption_tokens(caption: str) -> list[Token]:
    """Words of ``caption`` with their character spans, lower case, apostrophes dropped."""
    return [Token(m.group().lower().replace("'", "").replace("’", ""), m.start(), m.end())
            for m in _WORD.finditer(caption)]


def normalise(text: str) -> list[str]:
    """Case, whitespace and punctuation removed: the word list the phrase check compares."""
    return [t.norm for t in caption_tokens(text)]


def _stem(w: str) -> str:
    for suffix in ("ing", "ed", "es", "s"):
        if w.endswith(suffix) and len(w) - len(suffix) >= 3:
            w = w[:-len(suffix)]
            break
    return w[:-1] if w.endswith("e") and len(w) > 3 else w


@dataclass(frozen=True)
class Span:
    start: int            # character offsets in the caption
    end: int
    amended: bool = False


def locate_phrase(phrase: str, caption: str, span_overlap: float = 0.6,
                  toks: list[Token] | None = None) -> Span:
    """Where ``phrase`` is in ``caption``: the normalised phrase as a run of caption words, else a
    caption span of which at least ``span_overlap`` of the words are phrase words and at least
    ``span_overlap`` of the phrase words are in the span (light stemming: kicks/kicking/kick): of
    those, the best Dice overlap with the phrase, then the longest (the longest alone would grow
    into neighbouring words while the share stays above the threshold);
    ``InteractionFormatError`` when there is none."""
    toks = caption_tokens(caption) if toks is None else toks
    words = normalise(phrase)
    if not words:
        raise InteractionFormatError(f"the phrase {phrase!r} is empty")
    cap = [t.norm for t in toks]
    n, k = len(cap), len(words)
    for i in range(n - k + 1):
        if cap[i:i + k] == words:
            return Span(toks[i].start, toks[i + k - 1].end)
    want = Counter(_stem(w) for w in words)
    stems = [_stem(w) for w in cap]
    best = None
    for i in range(n):
        have: Counter = Counter()
        for j in range(i, n):
            have[stems[j]] += 1
            shared = sum((have & want).values())
            length = j - i + 1
            if shared >= span_overlap * length and shared >= span_overlap * k:
                score = (2 * shared / (length + k), length)       # Dice overlap, then the longer span
                if best is None or score > best[2]:
                    best = (i, j, score)
    if best is None:
        raise InteractionFormatError(f"the phrase {phrase!r} is not in the sentence; copy the phrase word for "
                                     f"word from the sentence")
    return Span(toks[best[0]].start, toks[best[1]].end, amended=True)


# ------------------------------------------------------------------ answers
@dataclass(frozen=True)
class Interaction:
    parts: tuple[str, ...]
    phrase: str           # the caption's own text of the span
    span: Span


_THINK = re.compile(r"<think>.*?</think>", re.S | re.I)
_BULLET = re.compile(r"^[\s>*\-•·]*(?:\d+[.)]\s+)?\**\s*")
_NONE = re.compile(r"^\W*none\W*$", re.I)


def parse_answer(answer: str, caption: str, unsided: str = "both", span_overlap: float = 0.6) -> list[Interaction]:
    """The interactions of an answer ([] for ``none``), or ``InteractionFormatError`` saying what is wrong."""
    if not isinstance(answer, str):
        raise InteractionFormatError(f"the answer is {type(answer).__name__}, not text")
    lines = [ln.strip() for ln in _THINK.sub("", answer).splitlines()]
    lines = [_BULLET.sub("", ln).strip() for ln in lines if ln]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise InteractionFormatError("the answer is empty")
    if any(_NONE.match(ln) for ln in lines):
        if len(lines) > 1:
            raise InteractionFormatError("'none' must be the whole answer, without other lines")
        return []
    toks = caption_tokens(caption)
    out = []
    for ln in lines:
        head, sep, phrase = ln.partition(":")
        if not sep or not phrase.strip():
            raise InteractionFormatError(f"the line {ln[:100]!r} is not '<body part>[, <body part>...]: "
                                         f"<exact phrase>'")
        names = re.split(r",|;|/|&|\band\b|\bplus\b", re.sub(r"\b(left and right|right and left)\b", "both",
                                                                 head.strip(" *\"'").lower()))
        parts = set()
        for name in names:
            parts.update(map_part(name, unsided))
        if not parts:
            raise InteractionFormatError(f"the line {ln[:100]!r} names no body part from: left arm, right arm, "
                                         f"left leg, right leg, torso, pelvis")
        phrase = phrase.strip().strip("*").strip().strip("\"'“”").strip()
        span = locate_phrase(phrase, caption, span_overlap, toks)
        out.append(Interaction(sort_parts(parts), caption[span.start:span.end], span))
    return out


# ------------------------------------------------------------------ merging
CONNECTORS = ("and then", "and after that", "after that", "and", "then", "while", "whilst", "as", "before",
              "after")
_CONN_END = re.compile(r"(?:[\s,;:.!?\-]|\b(?:" + "|".join(c.replace(" ", r"\s+") for c in CONNECTORS)
                       + r")\b)+$", re.I)
_CONN_START = re.compile(r"^(?:[\s,;:.!?\-]|\b(?:" + "|".join(c.replace(" ", r"\s+") for c in CONNECTORS)
                         + r")\b)+", re.I)
_EDGE = " \t\n,;:.!?\"'-"
FUNCTION_WORDS = set(
    "a an the this that these those his her their its my your our he she they it him them one someone's "
    "and or but nor so then while whilst as before after when until if because "
    "with without to of in on at by for from into onto over under up down is are was were be being been has "
    "have had do does did".split())


def content_words(text: str) -> int:
    return sum(1 for w in normalise(text) if w not in FUNCTION_WORDS)


def merge_spans(spans: Sequence[Span]) -> list[tuple[int, int]]:
    """Overlapping or touching character spans joined, in caption order."""
    out: list[list[int]] = []
    for s in sorted(spans, key=lambda s: (s.start, s.end)):
        if out and s.start <= out[-1][1]:
            out[-1][1] = max(out[-1][1], s.end)
        else:
            out.append([s.start, s.end])
    return [(a, b) for a, b in out]


def non_interaction_text(caption: str, spans: Sequence[Span], min_content_words: int = 2) -> str | None:
    """The caption with every span removed; conjunctions left dangling at a cut (and, then, while,
    as, before, after) and edge punctuation stripped; None (the null condition) when fewer than
    ``min_content_words`` content words remain."""
    cuts = merge_spans(spans)
    if not cuts:
        return caption.strip()
    bounds = [0, *[x for c in cuts for x in c], len(caption)]
    pieces = []
    for k in range(0, len(bounds), 2):
        text = caption[bounds[k]:bounds[k + 1]]
        left_cut, right_cut = k > 0, k + 2 < len(bounds)
        joined = False
        if left_cut:
            m = _CONN_START.match(text)
            joined = bool(m and m.group().strip())
            text = _CONN_START.sub("", text)
        if right_cut:
            text = _CONN_END.sub("", text)
        text = text.strip(_EDGE)
        if text:
            pieces.append((text, joined))
    out = ""
    for text, joined in pieces:
        if not out:
            out = text
        else:
            out += (", " if joined and len(normalise(out)) >= 3 else " ") + text
    out = out.strip(_EDGE)
    return out if content_words(out) >= min_content_words else None


def merge(interactions: Sequence[Interaction], caption: str) -> tuple[tuple[str, ...], str | None, str | None]:
    """(parts, c_inter, c_non) of a caption's interactions; ((), None, caption) for ``none``."""
    if not interactions:
        return (), None, caption.strip()
    parts = sort_parts(p for it in interactions for p in it.parts)
    cuts = merge_spans([it.span for it in interactions])
    c_inter = "; ".join(caption[a:b] for a, b in cuts)
    return parts, c_inter, non_interaction_text(caption, [it.span for it in interactions])


def answer_text(interactions: Sequence[tuple[Sequence[str], str]]) -> str:
    """Answer lines for (part labels, phrase) pairs; ``none`` when there are none. Pairs with the
    same phrase share one line."""
    by_phrase: dict[str, list[str]] = {}
    for labels, phrase in interactions:
        cur = by_phrase.setdefault(phrase, [])
        cur += [lb for lb in labels if lb not in cur]
    if not by_phrase:
        return "none"
    return "\n".join(f"{', '.join(labels)}: {phrase}" for phrase, labels in by_phrase.items())
