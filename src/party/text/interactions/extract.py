"""TextIM's interaction extraction (SPEC-textim §3): which of six parts interact with an object in a
caption, the exact phrase of each interaction (c_inter) and the rest of the caption (c_non).

Backends (``interactions.backend``), all answering in the prompt's line format and checked by the
same validator (``interaction_prompt.parse_answer``):

- ``openai``: any OpenAI-compatible chat server (GPT-3.5 in the paper), through the HTTP client of
  the part-text backend (``party.text.backends.openai``: retries on 429/5xx/timeouts, the API key
  read from the environment variable ``api_key_env`` and never stored). Per caption
  (``extract_with_retries``): attempt 1 at ``temperature``; an answer that fails the check is
  asked again with the validator's error appended as a user turn, ``max_attempts`` tries in all;
  after the last failure the answer is ``none``, marked ``fallback``.
- ``rules``: an offline lexicon extractor (``rules_answer``) built on the part-text rules' lexicon:
  arm/leg nouns with their side words, contact and action verbs, split into the caption's clauses.
- ``oracle``: the synthetic dataset's ground truth (``oracle_answer``): every arms action (side
  left/right: that arm; both: both arms) and every legs action that names a side (hop, kick,
  lunge) marks its limb; its phrase is the caption span of the action's caption template.

Answers are kept in ``InteractionCache`` (SQLite, like ``PartTextCache``), and
``fill_interactions`` asks only for captions the cache lacks, so a rerun makes no requests.
``part_mask`` turns parts into the binary channel mask m (SPEC §2).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from party.text.interactions.prompt import (PART_LABEL, PARTS, PROMPT_VERSION, UNSIDED,
                                                     InteractionFormatError, answer_text, build_messages,
                                                     feedback_messages, merge, parse_answer, prompt_fingerprint,
                                                     sort_parts)
from party.sqlite import SQLiteCache, select_in
from party.text.backends import rules as R
from party.text.backends.base import BackendError, PartTextResult
from party.text.backends.openai import TransientError

log = logging.getLogger(__name__)
BACKENDS = ("openai", "rules", "oracle")


# ------------------------------------------------------------------ config
@dataclass(frozen=True)
class InteractionsConfig:
    """``interactions.*`` (SPEC §3). API keys never go here: ``api_key_env`` names the variable."""
    backend: str = "rules"                       # openai | rules | oracle
    model: str = "gpt-3.5-turbo"                 # the paper's LLM (openai backend)
    base_url: str = "https://api.openai.com/v1"  # OpenAI-compatible /v1 address
    api_key_env: str = "OPENAI_API_KEY"
    prompt_version: str = PROMPT_VERSION
    temperature: float = 0.0                     # attempt 1 (and the retries) at this temperature
    max_attempts: int = 3                        # paper: three attempts, then 'none'
    unsided: str = "both"                        # a limb with no side: both sides | right
    span_overlap: float = 0.6                    # phrase amendment: shared-token share of a caption span
    max_fallback_rate: float = 0.2
    concurrency: int = 8                         # requests in flight
    cache_path: str = "cache/interactions.sqlite"
    timeout_s: float = 60.0                      # per request
    max_tokens: int = 256
    max_retries: int = 5                         # re-sends on 429/5xx/timeouts (per request)
    backoff_base_s: float = 1.0
    backoff_max_s: float = 60.0
    backoff_jitter: float = 0.1
    retry_after_max_s: float = 300.0
    allow_insecure_http: bool = False
    max_consecutive_failures: int = 20           # stop when this many captions in a row get no answer
    seed: int = 0                                # backoff jitter
    oracle_root: str | None = None               # oracle: the synthetic dataset folder (specs.jsonl, texts/)

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"interactions.backend={self.backend!r}: choose from {list(BACKENDS)}")
        if self.unsided not in UNSIDED:
            raise ValueError(f"interactions.unsided={self.unsided!r}: choose from {list(UNSIDED)}")
        if not 0.0 < float(self.span_overlap) <= 1.0:
            raise ValueError(f"interactions.span_overlap={self.span_overlap}: must be in (0, 1]")
        if int(self.max_attempts) < 1:
            raise ValueError(f"interactions.max_attempts={self.max_attempts}: must be at least 1")
        if not 0.0 <= float(self.max_fallback_rate) <= 1.0:
            raise ValueError(f"interactions.max_fallback_rate={self.max_fallback_rate}: must be in [0, 1]")
        if int(self.concurrency) < 1:
            raise ValueError(f"interactions.concurrency={self.concurrency}: must be at least 1")

    @classmethod
    def from_cfg(cls, cfg: Mapping | None) -> "InteractionsConfig":
        """From a mapping or an OmegaConf node (``cfg.interactions``); unknown keys are an error."""
        if cfg is None:
            return cls()
        if isinstance(cfg, cls):
            return cfg
        try:
            from omegaconf import OmegaConf
            if OmegaConf.is_config(cfg):
                cfg = OmegaConf.to_container(cfg, resolve=True)
        except ImportError:                                   # pragma: no cover
            pass
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(cfg) - names)
        if unknown:
            raise ValueError(f"interactions: unknown keys {unknown}; known: {sorted(names)}")
        return cls(**dict(cfg))

    @property
    def validator(self) -> str:
        """The answer-check settings an answer depends on (part of the cache key)."""
        return f"unsided={self.unsided};span_overlap={float(self.span_overlap):g};attempts={int(self.max_attempts)}"


# ------------------------------------------------------------------ result
@dataclass
class InteractionResult:
    """What one caption gives: ``parts`` in ``PARTS`` order, ``c_inter`` (None for ``none``),
    ``c_non`` (None: the null condition), the phrases (exact caption spans) and bookkeeping."""
    parts: tuple[str, ...] = ()
    c_inter: str | None = None
    c_non: str | None = None
    phrases: tuple[str, ...] = ()
    fallback: bool = False         # True: 'none' because no answer passed the check (or no answer came)
    reason: str = ""               # why it fell back ("format: ...", "request: ...")
    attempts: int = 0              # answers asked for (openai: up to max_attempts)
    raw: str = ""                  # the last raw answer
    calls: int = 0                 # HTTP requests (transport retries included)
    format_failures: int = 0
    amended: int = 0               # phrases replaced by a caption span
    cacheable: bool = True         # False: no answer came (transient); asked again next run
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """The per-caption record of the interaction table (``party.methods.textim.data``)."""
        return {"parts": list(self.parts), "inter": self.c_inter, "non": self.c_non, "phrases": list(self.phrases),
                "fallback": self.fallback, "reason": self.reason, "attempts": self.attempts}


def result_from_answer(answer: str, caption: str, cfg: InteractionsConfig) -> InteractionResult:
    """Check an answer and merge its lines (``InteractionFormatError`` when it fails)."""
    its = parse_answer(answer, caption, cfg.unsided, float(cfg.span_overlap))
    parts, c_inter, c_non = merge(its, caption)
    phrases = tuple(dict.fromkeys(it.phrase for it in sorted(its, key=lambda it: it.span.start)))
    return InteractionResult(parts=parts, c_inter=c_inter, c_non=c_non, phrases=phrases, raw=answer,
                             amended=sum(it.span.amended for it in its))


def fallback_result(caption: str, reason: str, **kw) -> InteractionResult:
    return InteractionResult(parts=(), c_inter=None, c_non=caption.strip(), fallback=True, reason=reason, **kw)


Chat = Callable[[list, float], str]


def extract_with_retries(caption: str, chat: Chat, cfg: InteractionsConfig) -> InteractionResult:
    """Ask ``chat(messages, temperature)`` up to ``cfg.max_attempts`` times; each failed answer and the
    validator's error are appended to the chat before the next try; then ``none`` with fallback.
    ``TransientError`` from ``chat`` (no answer after the transport's retries) gives a fallback that is
    not cached."""
    messages = build_messages(caption)
    errors: list[str] = []
    raw = ""
    for attempt in range(1, int(cfg.max_attempts) + 1):
        try:
            raw = chat(messages, float(cfg.temperature))
        except TransientError as e:
            return fallback_result(caption, f"request: {e}", attempts=attempt, raw=raw,
                                   format_failures=len(errors), cacheable=False)
        try:
            res = result_from_answer(raw, caption, cfg)
        except InteractionFormatError as e:
            errors.append(str(e))
            messages = messages + feedback_messages(raw, str(e))
            continue
        res.attempts, res.format_failures = attempt, len(errors)
        return res
    return fallback_result(caption, f"format: {errors[-1]}", attempts=int(cfg.max_attempts), raw=raw,
                           format_failures=len(errors))


# ------------------------------------------------------------------ openai backend
def _rename(e: Exception) -> str:
    return str(e).replace("part_texts.", "interactions.")


class OpenAIInteractionBackend:
    """The interaction prompt on an OpenAI-compatible server, over the part-text backend's HTTP
    client (``OpenAIBackend.request``: transport retries, key handling, redirect refusal)."""
    name = "openai"

    def __init__(self, cfg: InteractionsConfig, stop: threading.Event | None = None):
        from omegaconf import OmegaConf

        from party.text.backends.openai import OpenAIBackend
        self.cfg = cfg
        self.model = str(cfg.model)
        self.fingerprint = prompt_fingerprint()
        http_cfg = OmegaConf.create({
            "model": self.model, "base_url": cfg.base_url, "api_key_env": cfg.api_key_env,
            "allow_insecure_http": bool(cfg.allow_insecure_http), "seed": int(cfg.seed),
            "timeout_s": float(cfg.timeout_s), "max_retries": int(cfg.max_retries),
            "backoff_base_s": float(cfg.backoff_base_s), "backoff_max_s": float(cfg.backoff_max_s),
            "backoff_jitter": float(cfg.backoff_jitter), "retry_after_max_s": float(cfg.retry_after_max_s),
            "temperature": float(cfg.temperature), "max_tokens": int(cfg.max_tokens),
            # unused by the calls made here; required by the part-text backend's constructor
            "parts": ["arms", "legs"], "no_movement_text": "none", "max_format_attempts": 1,
            "allow_extra_lines": False})
        try:
            self._http = OpenAIBackend(http_cfg, stop)
        except BackendError as e:
            raise BackendError(_rename(e)) from None
        self.stop = self._http.stop

    def chat(self, messages: list, temperature: float, counter: PartTextResult | None = None) -> str:
        """One chat completion (retried by the HTTP client on transient failures)."""
        body = json.dumps({"model": self.model, "messages": messages, "temperature": float(temperature),
                           "max_tokens": int(self.cfg.max_tokens)}).encode()
        try:
            return self._http.request(body, counter if counter is not None else PartTextResult(parts={}))
        except BackendError as e:
            raise BackendError(_rename(e)) from None

    def extract(self, caption: str) -> InteractionResult:
        counter = PartTextResult(parts={})
        res = extract_with_retries(caption, lambda m, t: self.chat(m, t, counter), self.cfg)
        res.calls = counter.calls
        res.extra["transport_retries"] = counter.retries
        return res


# ------------------------------------------------------------------ rules backend
_TOKEN = re.compile(r"[A-Za-z]+(?:['’][A-Za-z]+)?|[0-9]+|[.,;:!?]")
ARM_NOUNS = set(R.ARM_NOUNS) | {"collarbone", "clavicle"}
LEG_NOUNS = set(R.LEG_NOUNS) - {"tiptoe"}
TORSO_NOUNS = {"head", "neck", "face", "chin", "chest", "back", "spine", "abdomen", "stomach", "torso"}
PELVIS_NOUNS = {"waist", "buttocks", "buttock", "pelvis", "lap", "butt"}
DETERMINERS = {"the", "his", "her", "their", "its", "a", "an", "my", "your"}
INSTRUMENT_PREPS = set(R.INSTRUMENT_PREPS) | {"in"}        # "with the left hand", "a cup in the right hand"
OBJECT_PREPS = {"on", "onto", "to", "against", "at", "over", "behind", "across", "around", "into", "from",
                "towards", "toward", "near", "above", "below", "under", "of"}
NP_PREPS = set(R.NP_PREPS) | OBJECT_PREPS | {"using", "by"}
LEG_OBJECT_VERBS = {"kick", "stomp", "stamp", "push", "press", "trample"}
BODY_PRESS_VERBS = {"lean", "rest", "press", "push"}
SEATS = {"chair", "bench", "stool", "sofa", "couch", "seat", "bed", "box", "table", "ledge", "step", "steps",
         "stairs", "toilet", "floor", "ground", "armchair", "bed"}
SEAT_VERBS = {"sit"}
LEADING_FILLER = {"first", "and", "then", "that", "also", "finally", "next", "afterwards", "so"}
GAITS = set(R.SWING_GAITS) | {"march", "move", "go", "step", "circle"}      # gaits whose arms may swing along
# verbs that may share a clause with a gait's arm swing ("gradually turns left with the arms swinging")
GAIT_COMPANIONS = {"swing", "turn", "lift", "move"}


@dataclass
class _Tok:
    word: str
    start: int
    end: int

    @property
    def punct(self) -> bool:
        return not self.word[0].isalnum()


def _tokens(caption: str) -> list[_Tok]:
    out = []
    for m in _TOKEN.finditer(caption):
        w = m.group().lower().replace("’", "'")
        w = w[:-2] if w.endswith("'s") else w.replace("'", "")
        out.append(_Tok(w, m.start(), m.end()))
    return out


def _body(w: str) -> tuple[str, bool] | None:
    """(kind, plural) of a body noun: kind arm | leg | torso | pelvis | hip."""
    if w in R.PLURAL:
        return ("leg" if R.PLURAL[w] in LEG_NOUNS else "arm"), True
    if w in ("hip", "hips"):
        return "hip", w == "hips"
    for kind, nouns in (("arm", ARM_NOUNS), ("leg", LEG_NOUNS)):
        if w in nouns:
            return kind, w == "feet"
        if w.endswith("s") and w[:-1] in nouns:
            return kind, True
    if w in TORSO_NOUNS:
        return "torso", False
    if w in PELVIS_NOUNS:
        return "pelvis", w == "buttocks"
    return None


def _named_body(ws: list[str], j: int) -> bool:
    """Is ``ws[j]`` a body part? Torso and pelvis nouns only after a determiner ("forward and back")."""
    b = _body(ws[j])
    return b is not None and (b[0] not in ("torso", "pelvis") or (j > 0 and ws[j - 1] in DETERMINERS))


@dataclass
class _Mention:
    kind: str                 # arm | leg | torso | pelvis
    side: str | None          # left | right | both | one | None
    plural: bool
    prep: str | None          # the preposition before the noun phrase


def _mentions(ws: list[str]) -> list[_Mention]:
    out = []
    for j, w in enumerate(ws):
        b = _body(w)
        if b is None:
            continue
        kind, plural = b
        if w.startswith("shoulder") and (j >= 1 and ws[j - 1] in R.SHOULDER_PREPS
                                         or j >= 2 and ws[j - 2] in R.SHOULDER_PREPS
                                         or j >= 3 and ws[j - 3] in R.SHOULDER_PREPS):
            continue                                  # "turns around over his left shoulder": a direction
        side, k = None, j - 1
        while k >= 0 and j - k <= 4 and ws[k] in R.NOUN_BRIDGE:
            if ws[k] in R.SIDE_MOD:
                s = R.SIDE_MOD[ws[k]]
                side = s if side in (None, s) else "both"
            k -= 1
        if kind in ("torso", "pelvis") and (j == 0 or ws[j - 1] not in DETERMINERS):
            continue                                  # "walks back", "heads off", "runs a lap"
        while k >= 0 and j - k <= 3 and ws[k].isalpha() and ws[k] not in R.FORMS and ws[k] not in NP_PREPS \
                and ws[k] not in R.SPLIT_WORDS and _body(ws[k]) is None:
            k -= 1                                    # adjectives: "with high knees"
        prep = ws[k] if k >= 0 and ws[k] in NP_PREPS else None
        if kind == "hip":
            kind = "leg" if side in ("left", "right") else "pelvis"
        if side is None and plural and kind in ("arm", "leg"):
            side = "both"
        out.append(_Mention(kind, side, plural, prep))
    return out


def _limb_label(kind: str, side: str | None) -> str:
    if side in ("left", "right"):
        return f"{side} {kind}"
    if side == "both":
        return f"{kind}s"
    return kind                                       # unsided: interactions.unsided decides


@dataclass
class _Segment:
    idx: list[int]             # token indices (words only)
    boundary: str              # what precedes it: "" (start), ",", "and", "while", "then", ...
    labels: list[str] = field(default_factory=list)
    start: int = 0             # phrase: first token index (into idx)
    gait: bool = False
    arm_verbs_only: bool = False
    mentions: int = 0
    verbs: int = 0


def _boundary(seen: list[str]) -> str:
    """A clause's boundary: its first clause word, "," when only punctuation, "" at the start."""
    words = [w for w in seen if w[0].isalnum()]
    return words[0] if words else ("," if seen else "")


def _split(toks: list[_Tok]) -> list[_Segment]:
    """Clauses: split at punctuation and clause words (then, while, as, ...; not 'as if'), and at 'and'
    when what follows has a verb or a body part of its own ('jumps up and down' stays one)."""
    pieces: list[tuple[str, list[int]]] = []
    cur: list[int] = []
    seen: list[str] = []                              # the boundary tokens since the last clause
    i = 0
    while i < len(toks):
        w = toks[i].word
        nxt = toks[i + 1].word if i + 1 < len(toks) else ""
        if toks[i].punct or (w in R.SPLIT_WORDS and not (w == "as" and nxt in ("if", "though"))):
            if cur:
                pieces.append((_boundary(seen), cur))
                seen = []
            cur = []
            seen.append(w)
            if w == "after" and nxt == "that":
                i += 1
        else:
            cur.append(i)
        i += 1
    if cur:
        pieces.append((_boundary(seen), cur))
    out: list[_Segment] = []
    for boundary, piece in pieces:
        segs: list[tuple[str, list[int]]] = []
        cur = []
        for i in piece + [-1]:
            if i == -1 or toks[i].word == "and":
                words = [toks[k].word for k in cur]
                prev = toks[segs[-1][1][-1]].word if segs else ""
                lead = next((w for w in words if w not in R.NOUN_BRIDGE), "")
                coordinated = bool(words) and not any(w in R.FORMS for w in words) and _body(lead) is not None \
                    and (_body(prev) is not None or prev in R.SIDE_MOD)        # "the left hand and the right foot"
                if segs and cur and (coordinated or not any(w in R.FORMS or _named_body(words, j)
                                                             for j, w in enumerate(words))):
                    segs[-1][1].extend([k for k in range(segs[-1][1][-1] + 1, cur[0])] + cur)
                elif cur:
                    segs.append(("and" if segs else boundary, cur))
                cur = []
            else:
                cur.append(i)
        out += [_Segment(idx, b) for b, idx in segs]
    return out


def _analyse(seg: _Segment, toks: list[_Tok], prev: _Segment | None) -> None:
    ws = [toks[i].word for i in seg.idx]
    verbs = [i for i in range(len(ws)) if R._is_verb(ws, i)]
    bases = [R.FORMS[ws[i]] for i in verbs]
    classes = [R.RulesBackend._verb_class(ws, i, b) for i, b in zip(verbs, bases)]
    ment = _mentions(ws)
    seg.mentions, seg.verbs = len(ment), len(verbs)
    contact = any(b in R.CONTACT for b in bases)
    seg.gait = any(c in ("locomotion", "legs") and b in GAITS for b, c in zip(bases, classes)) or (
        bool(bases) and all(b == "turn" for b in bases) and seg.boundary in (",", "and")
        and prev is not None and prev.gait)                      # "walks forward and gradually turns left"
    seg.arm_verbs_only = bool(verbs) and all(c == "arms" for c in classes)
    labels: list[str] = []
    arms = [m for m in ment if m.kind == "arm"]
    if arms and contact and any(m.prep in INSTRUMENT_PREPS for m in arms):
        arms = [m for m in arms if m.prep in INSTRUMENT_PREPS]     # the instrument acts, the rest is touched
    if arms:
        both_only = all(m.side == "both" and m.plural for m in arms)
        swing_at = [j for j, w in enumerate(ws) if R.FORMS.get(w) == "swing"]
        body_at = [j for j in range(len(ws)) if _named_body(ws, j)]
        others_ok = all(c in ("locomotion", "legs") or b in GAIT_COMPANIONS for b, c in zip(bases, classes))
        prev_gait = prev is not None and prev.gait
        # "walks forward with the arms swinging", "..., veering to the right with the arms swinging"
        swing_with_gait = both_only and others_ok and bool(swing_at) and (
            seg.gait or (prev_gait and swing_at[0] > body_at[0] and seg.boundary in (",", "and")))
        # "walks forward, swinging his arms"
        swing_after_gait = (both_only and bases == ["swing"] and ws[verbs[0]].endswith("ing")
                            and body_at[-1] == len(ws) - 1 and seg.boundary == "," and prev_gait)
        if not (swing_with_gait or swing_after_gait):      # "walks forward, swinging his arms": the gait's swing
            labels += [_limb_label("arm", m.side) for m in arms]
    for m in ment:
        if m.kind == "leg":
            if m.prep in OBJECT_PREPS and (arms or contact):
                continue                                  # "rests his hand on his left hip": touched
            if contact and m.prep not in INSTRUMENT_PREPS:
                if not arms:
                    labels.append("arm")                  # "touches his toes": a hand does it
                continue
            if m.side in ("left", "right", "one"):
                labels.append(_limb_label("leg", m.side))
            elif any(b in LEG_OBJECT_VERBS for b in bases):
                labels.append(_limb_label("leg", m.side))
        elif m.kind in ("torso", "pelvis"):
            if m.prep in R.INSTRUMENT_PREPS:
                labels.append(m.kind)                     # "pushes the door with his back"
            elif m.prep is None and not arms and not contact and any(b in BODY_PRESS_VERBS for b in bases):
                labels.append(m.kind)                     # "leans his back against the wall"
    if any(b in SEAT_VERBS for b in bases):
        v = verbs[bases.index(next(b for b in bases if b in SEAT_VERBS))]
        rest = ws[v + 1:]
        for k, w in enumerate(rest):
            if w in ("on", "onto", "in", "into", "at") and any(x in SEATS for x in rest[k + 1:k + 4]):
                labels.append("pelvis")                   # "sits down on a chair"
                break
    if not ment:
        for b, c in zip(bases, classes):
            if c == "arms":
                labels.append("arms" if b in R.BOTH_ARMS else "arm")
                break
        if any(b in R.ONE_LEG for b in bases):
            labels.append("leg")                          # "kicks a ball"
    seg.labels = list(dict.fromkeys(labels))
    k = 0
    while k < len(ws) and (ws[k] in R.SUBJECTS or ws[k] in LEADING_FILLER) and k not in verbs:
        k += 1
    seg.start = k if k < len(ws) else 0


def rules_answer(caption: str) -> str:
    """The rules' answer to the interaction prompt for ``caption`` (answer-line format)."""
    toks = _tokens(caption)
    segs = _split(toks)
    kept: list[_Segment] = []
    prev = None
    for seg in segs:
        _analyse(seg, toks, prev)
        if (prev is not None and kept and kept[-1] is prev and seg.boundary == "and" and not seg.mentions
                and seg.arm_verbs_only and any("arm" in lb for lb in prev.labels)):
            # "raises his left hand and waves", "picks up a box ... and puts it on a shelf"
            prev.idx = prev.idx + seg.idx
            continue
        if seg.labels:
            kept.append(seg)
        if seg.verbs or seg.mentions or prev is None:
            prev = seg                                 # "curving to the right" keeps the gait's context
    lines = []
    for seg in kept:
        a, b = toks[seg.idx[seg.start]].start, toks[seg.idx[-1]].end
        lines.append((seg.labels, caption[a:b]))
    return answer_text(lines)


def _source_hash(*paths: str | Path, extra: bytes = b"") -> str:
    h = hashlib.sha1()
    for p in paths:
        h.update(Path(p).read_bytes())
    h.update(extra)
    return h.hexdigest()[:12]


class RulesInteractionBackend:
    """Offline lexicon extractor; its answers pass the same check as an LLM's (one attempt)."""
    name = "rules"

    def __init__(self, cfg: InteractionsConfig | None = None):
        self.cfg = cfg or InteractionsConfig(backend="rules")
        self.fingerprint = _source_hash(__file__, R.__file__)
        self.model = f"rules-{self.fingerprint}"                  # rule changes invalidate the cache

    def answer(self, caption: str) -> str:
        return rules_answer(caption)

    def extract(self, caption: str) -> InteractionResult:
        raw = self.answer(caption)
        try:
            res = result_from_answer(raw, caption, self.cfg)
        except InteractionFormatError as e:
            return fallback_result(caption, f"format: {e}", attempts=1, raw=raw, format_failures=1)
        res.attempts = 1
        return res


# ------------------------------------------------------------------ oracle backend (synthetic dataset)
_DETS = r"(?:the|his|her|their|its)"


def _template_regex(template: str, side: str | None) -> re.Pattern:
    """A caption template of ``party.data.synthetic.captions`` as a regex (verbs in 3rd person or gerund)."""
    from party.data.synthetic.lexicon import gerund, third_person
    out = []
    for m in re.finditer(r"(\s*)(\^(\w+)|\{(\w+)\}|[^\s^{]+)", template):
        ws, _, verb, ph = m.group(1), m.group(2), m.group(3), m.group(4)
        sep = r"\s+" if ws else ""
        if verb:
            out.append(sep + "(?:" + "|".join(re.escape(f) for f in {verb, third_person(verb), gerund(verb)}) + ")")
        elif ph == "count":
            out.append(rf"(?:{sep or ''}(?:once|twice|[a-z]+\s+times))?")
        elif ph == "P":
            out.append(sep + _DETS)
        elif ph == "side":
            out.append(sep + (re.escape(side) if side else "[a-z]+"))
        elif ph in ("s", "es"):
            out.append(f"(?:{ph})?")
        elif ph is not None:
            out.append(sep + "[a-z]+")
        else:
            out.append(sep + re.escape(m.group(2)))
    return re.compile(r"\b" + "".join(out) + r"\b", re.I)


def _spec_dict(spec) -> dict:
    return spec.to_dict() if hasattr(spec, "to_dict") else dict(spec)


def oracle_actions(spec, segment: int | None = None) -> list[tuple[str, dict, tuple[str, ...]]]:
    """(legs|arms, action, parts) of the spec's actions that mark parts (of ``segment``; None: all)."""
    d = _spec_dict(spec)
    n_seg = 1 if d.get("boundary") is None else 2
    out, seen = [], set()
    for k in (range(n_seg) if segment is None else [segment]):
        for group in ("legs", "arms"):
            acts = d[group]
            i = min(k, len(acts) - 1)
            if (group, i) in seen:
                continue
            seen.add((group, i))
            a = acts[i]
            side = a.get("side")
            if group == "arms" and a["name"] != "rest":
                parts = (f"{side}_arm",) if side in ("left", "right") else ("left_arm", "right_arm")
            elif group == "legs" and side in ("left", "right"):
                parts = (f"{side}_leg",)
            else:
                continue
            out.append((group, a, parts))
    return out


def _templates(group: str, action: dict) -> list[str]:
    from party.data.synthetic.captions import ARMS_BOTH, ARMS_SIDE, LEGS
    if group == "arms":
        table = ARMS_BOTH if action.get("side") in (None, "both") else ARMS_SIDE
    else:
        table = LEGS
    if action["name"] not in table:
        raise ValueError(f"oracle: no caption template for the {group} action {action['name']!r}")
    return table[action["name"]]


def oracle_answer(caption: str, spec, segment: int | None = None, strict: bool = True) -> str:
    """The synthetic ground truth as an answer: one line per mention of each part-marking action of
    ``spec`` in ``caption`` (its caption templates, longest matches first, without overlaps).
    ``strict``: every such action of ``segment`` (None: of the whole motion) must be found, else a
    ValueError names it."""
    lines = []
    for group, action, parts in oracle_actions(spec, segment):
        side = action.get("side") if action.get("side") in ("left", "right") else None
        found = sorted({(m.start(), m.end()) for t in _templates(group, action)
                        for m in _template_regex(t, side).finditer(caption)}, key=lambda s: (s[0] - s[1], s[0]))
        spans: list[tuple[int, int]] = []
        for a, b in found:                                 # longest first, no overlaps: each mention once
            if all(b <= a2 or a >= b2 for a2, b2 in spans):
                spans.append((a, b))
        if not spans:
            if strict:
                name = _spec_dict(spec).get("name", "?")
                raise ValueError(f"oracle: caption {caption!r} does not mention the {group} action "
                                 f"{action['name']!r} (side {action.get('side')}) of motion {name!r}")
            continue
        for a, b in sorted(spans):
            lines.append(([PART_LABEL[p] for p in parts], caption[a:b]))
    return answer_text(lines)


class OracleInteractionBackend:
    """Ground-truth interactions of synthetic captions, from the specs of the motions they describe.
    ``entries``: (caption, spec, segment) triples, segment None for a whole-clip caption."""
    name = "oracle"

    def __init__(self, cfg: InteractionsConfig | None, entries: Iterable[tuple[str, object, int | None]],
                 source: str = "memory", digest: bytes = b""):
        self.cfg = cfg or InteractionsConfig(backend="oracle")
        self.source = source
        self.lookup: dict[str, list[tuple[object, int | None]]] = {}
        for caption, spec, segment in entries:
            self.lookup.setdefault(caption, []).append((spec, segment))
        self.fingerprint = _source_hash(__file__, extra=digest)
        self.model = f"oracle-{self.fingerprint}"

    @classmethod
    def from_dataset(cls, cfg: InteractionsConfig | None, root: str | Path) -> "OracleInteractionBackend":
        """The synthetic dataset at ``root`` (``specs.jsonl`` and ``texts/<name>.txt``)."""
        from party.data.humanml3d import parse_caption_line
        from party.data.synthetic.checks import load_specs
        root = Path(root)
        specs = load_specs(root)
        entries = []
        for name, spec in specs.items():
            path = root / "texts" / f"{name}.txt"
            if not path.is_file():
                raise FileNotFoundError(f"{path}: motion {name!r} of {root / 'specs.jsonl'} has no caption file")
            for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if not line.strip():
                    continue
                c = parse_caption_line(line, path, i)
                segment = None if c.start == 0.0 and c.end == 0.0 else (0 if c.start == 0.0 else 1)
                entries.append((c.caption, spec, segment))
        digest = (root / "specs.jsonl").read_bytes()
        return cls(cfg, entries, source=str(root), digest=hashlib.sha1(digest).digest())

    def answer(self, caption: str) -> str:
        hits = self.lookup.get(caption)
        if not hits:
            raise KeyError(f"oracle: caption {caption!r} is not a caption of the synthetic dataset {self.source}")
        answers = {}
        for spec, segment in hits:
            a = oracle_answer(caption, spec, segment)
            answers.setdefault(a, _spec_dict(spec).get("name", "?"))
        if len(answers) > 1:
            raise ValueError(f"oracle: caption {caption!r} describes motions with different interactions "
                             f"({answers}) in {self.source}")
        return next(iter(answers))

    def extract(self, caption: str) -> InteractionResult:
        raw = self.answer(caption)
        try:
            res = result_from_answer(raw, caption, self.cfg)
        except InteractionFormatError as e:
            raise ValueError(f"oracle: its own answer {raw!r} for caption {caption!r} fails the check: {e}") from None
        res.attempts = 1
        return res


def build_interaction_backend(cfg: InteractionsConfig | Mapping, stop: threading.Event | None = None):
    """The backend of ``interactions.backend``: an object with ``name``, ``model``, ``fingerprint`` and
    ``extract(caption) -> InteractionResult`` (thread-safe)."""
    cfg = InteractionsConfig.from_cfg(cfg)
    if cfg.backend == "openai":
        return OpenAIInteractionBackend(cfg, stop)
    if cfg.backend == "rules":
        return RulesInteractionBackend(cfg)
    if not cfg.oracle_root:
        raise ValueError("interactions.backend=oracle needs interactions.oracle_root (the synthetic dataset "
                         "folder with specs.jsonl and texts/)")
    return OracleInteractionBackend.from_dataset(cfg, cfg.oracle_root)


# ------------------------------------------------------------------ cache
class InteractionCache(SQLiteCache):
    """Interaction answers, keyed by (backend, model, prompt_version, validator settings, caption); one
    commit per answer (WAL), so an interrupted fill keeps what arrived."""
    kind = "interaction cache"
    hint = " (every caption is then asked again: the answers cost LLM calls)"
    schema = (
        "CREATE TABLE IF NOT EXISTS interactions (backend TEXT NOT NULL, model TEXT NOT NULL, "
        "prompt_version TEXT NOT NULL, validator TEXT NOT NULL, caption TEXT NOT NULL, parts TEXT NOT NULL, "
        "c_inter TEXT, c_non TEXT, phrases TEXT NOT NULL, fallback INTEGER NOT NULL, reason TEXT, "
        "attempts INTEGER, raw TEXT, created REAL, "
        "PRIMARY KEY (backend, model, prompt_version, validator, caption))",
        "CREATE TABLE IF NOT EXISTS interaction_prompts (backend TEXT NOT NULL, model TEXT NOT NULL, "
        "prompt_version TEXT NOT NULL, fingerprint TEXT NOT NULL, PRIMARY KEY (backend, model, prompt_version))",
    )

    def check_prompt(self, backend: str, model: str, prompt_version: str, fingerprint: str) -> None:
        """Refuse a prompt whose text changed while ``prompt_version`` did not."""
        row = self.db.execute("SELECT fingerprint FROM interaction_prompts WHERE backend=? AND model=? AND "
                              "prompt_version=?", (backend, model, prompt_version)).fetchone()
        if row is None:
            with self.db:
                self.db.execute("INSERT INTO interaction_prompts VALUES (?,?,?,?)",
                                (backend, model, prompt_version, fingerprint))
        elif row[0] != fingerprint:
            raise ValueError(f"{self.path}: the interaction prompt for prompt_version={prompt_version!r} changed "
                             f"(fingerprint {row[0]} -> {fingerprint}); set a new interactions.prompt_version")

    def get_many(self, backend: str, model: str, prompt_version: str, validator: str,
                 captions: Sequence[str]) -> dict[str, InteractionResult]:
        out = {}
        q = ("SELECT caption, parts, c_inter, c_non, phrases, fallback, reason, attempts, raw FROM interactions "
             "WHERE backend=? AND model=? AND prompt_version=? AND validator=? AND caption IN ({})")
        for cap, parts, ci, cn, phrases, fb, reason, attempts, raw in select_in(
                self.db, q, [backend, model, prompt_version, validator], list(captions), 400):
            try:
                out[cap] = InteractionResult(parts=sort_parts(json.loads(parts)), c_inter=ci, c_non=cn,
                                             phrases=tuple(json.loads(phrases)), fallback=bool(fb),
                                             reason=reason or "", attempts=int(attempts or 0), raw=raw or "")
            except (ValueError, TypeError):
                pass                                       # unreadable row: asked again
        return out

    def put(self, backend: str, model: str, prompt_version: str, validator: str, caption: str,
            res: InteractionResult) -> None:
        with self.db:
            self.db.execute("INSERT OR REPLACE INTO interactions VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                            (backend, model, prompt_version, validator, caption, json.dumps(list(res.parts)),
                             res.c_inter, res.c_non, json.dumps(list(res.phrases)), int(res.fallback), res.reason,
                             res.attempts, res.raw, time.time()))

    def count(self) -> int:
        return self.db.execute("SELECT COUNT(*) FROM interactions").fetchone()[0]


class FallbackRateError(BackendError):
    """More captions than ``interactions.max_fallback_rate`` fell back to 'none'."""


def check_fallback_rate(stats: dict, max_rate: float, cache_path: str | Path | None = None) -> float:
    """The fallback rate of a fill; ``FallbackRateError`` naming the rate and the limit when above it."""
    n = max(1, int(stats["captions"]))
    rate = stats["fallbacks"] / n
    if rate > float(max_rate):
        example = next(iter(stats["fallback_captions"].items()), None)
        where = f"; the answers are cached in {cache_path}" if cache_path else ""
        raise FallbackRateError(
            f"interactions: {stats['fallbacks']} of {stats['captions']} captions ({rate:.1%}) fell back to 'none' "
            f"(e.g. {example}), above interactions.max_fallback_rate={float(max_rate):g}{where}: fix the "
            f"server or the prompt (and set a new interactions.prompt_version), or raise "
            f"interactions.max_fallback_rate")
    return rate


def fill_interactions(captions: Sequence[str], backend, cache: InteractionCache, cfg: InteractionsConfig | Mapping,
                      progress: bool = True, check: bool = True) -> tuple[dict[str, InteractionResult], dict]:
    """Interactions of every caption: the cache first, then ``backend`` for the rest, ``cfg.concurrency``
    at a time (only this thread writes the cache). Returns (caption -> result, stats). ``check``:
    raise when captions got no answer (not cached: a rerun resumes) or the fallback rate is above
    ``max_fallback_rate``."""
    cfg = InteractionsConfig.from_cfg(cfg)
    captions = list(dict.fromkeys(captions))
    pv, val = str(cfg.prompt_version), cfg.validator
    cache.check_prompt(backend.name, backend.model, pv, backend.fingerprint)
    cached = cache.get_many(backend.name, backend.model, pv, val, captions)
    results: dict[str, InteractionResult] = dict(cached)
    fallbacks = {c: r.reason for c, r in cached.items() if r.fallback}
    todo = [c for c in captions if c not in cached]
    stats = {"captions": len(captions), "hits": len(cached), "misses": len(todo), "calls": 0, "attempts": 0,
             "format_failures": 0, "amended": 0, "fallbacks_new": 0, "request_failures": 0}
    request_failed: dict[str, str] = {}
    t0 = time.time()
    streak = 0
    limit = int(cfg.max_consecutive_failures) or None

    def record(cap: str, res: InteractionResult) -> None:
        nonlocal streak
        stats["calls"] += res.calls
        stats["attempts"] += res.attempts
        stats["format_failures"] += res.format_failures
        stats["amended"] += res.amended
        results[cap] = res
        if res.cacheable:
            streak = 0
            if res.fallback:
                fallbacks[cap] = res.reason
                stats["fallbacks_new"] += 1
            cache.put(backend.name, backend.model, pv, val, cap, res)
        else:
            streak += 1
            stats["request_failures"] += 1
            request_failed[cap] = res.reason
            if limit and streak >= limit:
                raise BackendError(f"{streak} captions in a row got no answer (last: {res.reason}); is the server "
                                   f"at {cfg.base_url} up?")

    workers = max(1, int(cfg.concurrency))
    bar = tqdm(total=len(todo), desc=f"interactions ({backend.name})", disable=not progress or not todo)
    stop: threading.Event = getattr(backend, "stop", None) or threading.Event()
    try:
        if workers == 1 or len(todo) <= 1:
            for cap in todo:
                record(cap, backend.extract(cap))
                bar.update()
        else:
            pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="interactions")
            try:
                queue = iter(todo)
                future_cap = {}
                for cap in queue:                          # at most 2x workers queued
                    future_cap[pool.submit(backend.extract, cap)] = cap
                    if len(future_cap) >= 2 * workers:
                        break
                pending = set(future_cap)
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        record(future_cap.pop(f), f.result())
                        bar.update()
                        nxt = next(queue, None)
                        if nxt is not None:
                            nf = pool.submit(backend.extract, nxt)
                            future_cap[nf] = nxt
                            pending.add(nf)
            except BaseException:
                stop.set()
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown(wait=True)
    finally:
        bar.close()
    stats["fallbacks"] = len(fallbacks)
    stats["seconds"] = round(time.time() - t0, 3)
    stats["backend"], stats["model"], stats["prompt_version"] = backend.name, backend.model, pv
    stats["validator"], stats["prompt_fingerprint"] = val, backend.fingerprint
    stats["fallback_captions"] = fallbacks
    stats["request_failed_captions"] = request_failed
    if check:
        if request_failed:
            raise BackendError(f"interactions: {len(request_failed)} captions got no answer after "
                               f"{cfg.max_retries} retries (e.g. {next(iter(request_failed.items()))}); the "
                               f"other answers are cached in {cache.path}: rerun to resume")
        check_fallback_rate(stats, cfg.max_fallback_rate, cache.path)
    return results, stats


# ------------------------------------------------------------------ mask
def part_mask(parts: Iterable[str], group_idx: Mapping[str, np.ndarray], dim: int = 263) -> np.ndarray:
    """The binary channel mask m (``dim`` bools) of the union of ``parts``; ``group_idx`` is
    ``party.motion.parts.group_index(22, dataset.parts.groups.textim6)``."""
    m = np.zeros(int(dim), dtype=bool)
    for p in parts:
        if p not in group_idx:
            raise ValueError(f"part {p!r} is not a group of the mask table (groups: {list(group_idx)})")
        idx = np.asarray(group_idx[p])
        if idx.size and int(idx.max()) >= dim:
            raise ValueError(f"part {p!r}: channel {int(idx.max())} is outside the {dim}-d feature vector")
        m[idx] = True
    return m


__all__ = ["PARTS", "InteractionsConfig", "InteractionResult", "InteractionCache", "FallbackRateError",
           "OpenAIInteractionBackend", "RulesInteractionBackend", "OracleInteractionBackend",
           "build_interaction_backend", "check_fallback_rate", "extract_with_retries", "fill_interactions",
           "oracle_actions", "oracle_answer", "part_mask", "result_from_answer", "rules_answer"]
