"""The part-text prompt (ParTY Fig. S5 / Sec. E.4.3) and the answer-format check (TextIM §3.3).

The part names (``part_texts.parts``, e.g. ``[arms, legs]``) are parameters: each is asked for
on a line labelled with its capitalised name (``Arms: ...``). The prompt is a chat: an
instruction (system message), the five few-shot examples of the paper as user/assistant turns,
then the caption. An answer is valid when it holds exactly one line per part (``Arms: ...``, or
``Arm: ...``), each non-empty (leading bullets / markdown bold are tolerated; other non-empty
lines are rejected unless ``allow_extra_lines``). ``prompt_fingerprint`` hashes the rendered
prompt so that a changed prompt under an unchanged ``prompt_version`` is caught (see
``PartTextCache``).
"""
from __future__ import annotations

import functools
import hashlib
import json
import re
from collections.abc import Sequence

NO_MOVEMENT = "No significant movement"

_COUNT = ("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine")


def label(part: str) -> str:
    """The answer-line label of a part: ``arms`` -> ``Arms``."""
    return part.capitalize()


def _singular(part: str) -> str:
    return part[:-1] if part.endswith("s") else part


def instruction(parts: Sequence[str]) -> str:
    n = len(parts)
    return (
        "You are an expert in human motion analysis. Given a holistic description of a human motion, "
        f"write {' and '.join(f'what the {p} do' for p in parts)}, as part-level descriptions. Answer with "
        f"exactly {_COUNT[n] if n < len(_COUNT) else n} line{'' if n == 1 else 's'} and nothing else:\n"
        + "".join(f"{label(p)}: <one sentence about the {_singular(p)} movement>\n" for p in parts)
        + f"If a part does not move noticeably, write \"{NO_MOVEMENT}.\" for it. Describe movement "
        "implied by the action too (for example, the arms swing while running). Name the side "
        "(left, right or both) whenever the description gives it."
    )


# Paper Fig. S5: (holistic description, {part: part description})
FEW_SHOT = (
    ("A person waves with their right hand while standing still.",
     {"arms": "Right arm raises up and waves side to side.",
      "legs": "No significant movement."}),
    ("A person runs forward quickly.",
     {"arms": "Both arms swing back and forth rhythmically to support the running motion.",
      "legs": "The legs alternate rapidly, pushing off the ground to propel the body forward in a running motion."}),
    ("A person jumps up and raises both arms above their head.",
     {"arms": "Both arms lift upward and extend above the head.",
      "legs": "The legs push off the ground forcefully to jump, then land back down."}),
    ("A person sits down on a chair.",
     {"arms": "No significant movement.",
      "legs": "The legs bend at the knees and lower the body into a sitting position."}),
    ("A person kicks a ball with their right foot.",
     {"arms": "No significant movement.",
      "legs": "The right leg swings forward to kick, while the left leg supports the body's weight."}),
)


def _check_parts(parts: Sequence[str]) -> list[str]:
    parts = [str(p) for p in parts]
    known = list(FEW_SHOT[0][1])
    unknown = [p for p in parts if p not in known]
    if not parts or unknown or len(set(parts)) != len(parts):
        raise ValueError(f"part_texts.parts={parts}: the Fig. S5 prompt has examples for distinct parts "
                         f"among {known} only")
    return parts


def answer_text(texts: dict, parts: Sequence[str]) -> str:
    """``{part: text}`` as the answer lines the prompt asks for."""
    return "\n".join(f"{label(p)}: {texts[p]}" for p in parts)


def question(caption: str) -> str:
    return f"Holistic Description: \"{caption.strip()}\"\nPart-level Descriptions:"


def build_messages(caption: str, parts: Sequence[str]) -> list[dict]:
    parts = _check_parts(parts)
    msgs = [{"role": "system", "content": instruction(parts)}]
    for cap, texts in FEW_SHOT:
        msgs.append({"role": "user", "content": question(cap)})
        msgs.append({"role": "assistant", "content": answer_text(texts, parts)})
    msgs.append({"role": "user", "content": question(caption)})
    return msgs


def prompt_fingerprint(parts: Sequence[str]) -> str:
    return hashlib.sha1(json.dumps(build_messages("{caption}", parts)).encode()).hexdigest()[:12]


class FormatError(ValueError):
    """The model's answer is not one parseable, non-empty line per part."""


@functools.lru_cache(maxsize=None)
def _line_re(parts: tuple[str, ...]) -> re.Pattern:
    names = "|".join(f"{re.escape(_singular(p))}s?" for p in parts)        # "arms?|legs?"
    return re.compile(rf"^[\s>*\-•·\d.)]*\**\s*({names})\s*\**\s*[:：]\s*\**\s*(.*?)\s*\**\s*$", re.I)


_THINK = re.compile(r"<think>.*?</think>", re.S | re.I)
_NO_MOVE = re.compile(r"^\W*(no|none|no (significant|noticeable|notable)? ?(movement|motion))\W*$", re.I)


def canonical(text: str, no_movement: str = NO_MOVEMENT) -> str:
    """Strip quotes/space; every spelling of 'no movement' becomes ``no_movement``."""
    text = text.strip().strip("\"'“”").strip()
    low = text.lower()
    if _NO_MOVE.match(text) or low.startswith(no_movement.lower()) or low.startswith(NO_MOVEMENT.lower()):
        return no_movement
    return text


def is_no_movement(text: str, no_movement: str = NO_MOVEMENT) -> bool:
    return canonical(text, no_movement) == no_movement


def parse_answer(answer: str, parts: Sequence[str], no_movement: str = NO_MOVEMENT,
                 allow_extra_lines: bool = False) -> dict:
    """``{part: str}`` for every part of ``parts`` from an answer, or ``FormatError`` saying what is wrong."""
    if not isinstance(answer, str):
        raise FormatError(f"answer is {type(answer).__name__}, not text")
    parts = tuple(str(p) for p in parts)
    line_re = _line_re(parts)
    answer = _THINK.sub("", answer)
    found: dict[str, str] = {}
    for line in answer.splitlines():
        if not line.strip():
            continue
        m = line_re.match(line)
        if not m:
            if allow_extra_lines:
                continue
            raise FormatError(f"unexpected line {line.strip()[:80]!r}")
        name = m.group(1).lower()
        part = next(p for p in parts if name in (p.lower(), _singular(p).lower()))
        if part in found:
            raise FormatError(f"more than one {label(part)}: line")
        text = canonical(m.group(2), no_movement)
        if not text:
            raise FormatError(f"empty {label(part)}: line")
        found[part] = text
    missing = [label(p) for p in parts if p not in found]
    if missing:
        raise FormatError(f"no {' / '.join(missing)}: line")
    return {p: found[p] for p in parts}
