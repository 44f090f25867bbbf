"""The part-text prompt (ParTY Fig. S5 / Sec. E.4.3) and the answer-format check (TextIM §3.3).

The prompt is a chat: an instruction (system message), the five few-shot examples of the paper
as user/assistant turns, then the caption. An answer is valid when it holds exactly one
``Arms: ...`` line and one ``Legs: ...`` line, both non-empty (leading bullets / markdown bold
are tolerated; other non-empty lines are rejected unless ``allow_extra_lines``).
``prompt_fingerprint`` hashes the rendered prompt so that a changed prompt under an unchanged
``prompt_version`` is caught (see ``PartTextCache``).
"""
from __future__ import annotations

import hashlib
import json
import re

NO_MOVEMENT = "No significant movement"

PART_LABELS = {"arms": "Arms", "legs": "Legs"}

INSTRUCTION = (
    "You are an expert in human motion analysis. Given a holistic description of a human motion, "
    "write what the arms do and what the legs do, as part-level descriptions. Answer with exactly "
    "two lines and nothing else:\n"
    "Arms: <one sentence about the arm movement>\n"
    "Legs: <one sentence about the leg movement>\n"
    f"If a part does not move noticeably, write \"{NO_MOVEMENT}.\" for it. Describe movement "
    "implied by the action too (for example, the arms swing while running). Name the side "
    "(left, right or both) whenever the description gives it."
)

# Paper Fig. S5: (holistic description, arms, legs)
FEW_SHOT = (
    ("A person waves with their right hand while standing still.",
     "Right arm raises up and waves side to side.",
     "No significant movement."),
    ("A person runs forward quickly.",
     "Both arms swing back and forth rhythmically to support the running motion.",
     "The legs alternate rapidly, pushing off the ground to propel the body forward in a running motion."),
    ("A person jumps up and raises both arms above their head.",
     "Both arms lift upward and extend above the head.",
     "The legs push off the ground forcefully to jump, then land back down."),
    ("A person sits down on a chair.",
     "No significant movement.",
     "The legs bend at the knees and lower the body into a sitting position."),
    ("A person kicks a ball with their right foot.",
     "No significant movement.",
     "The right leg swings forward to kick, while the left leg supports the body's weight."),
)


def question(caption: str) -> str:
    return f"Holistic Description: \"{caption.strip()}\"\nPart-level Descriptions:"


def build_messages(caption: str) -> list[dict]:
    msgs = [{"role": "system", "content": INSTRUCTION}]
    for cap, arms, legs in FEW_SHOT:
        msgs.append({"role": "user", "content": question(cap)})
        msgs.append({"role": "assistant", "content": f"Arms: {arms}\nLegs: {legs}"})
    msgs.append({"role": "user", "content": question(caption)})
    return msgs


def prompt_fingerprint() -> str:
    return hashlib.sha1(json.dumps(build_messages("{caption}")).encode()).hexdigest()[:12]


class FormatError(ValueError):
    """The model's answer is not two parseable, non-empty Arms/Legs lines."""


_LINE = re.compile(r"^[\s>*\-•·\d.)]*\**\s*(arms?|legs?)\s*\**\s*[:：]\s*\**\s*(.*?)\s*\**\s*$", re.I)
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


def parse_answer(answer: str, no_movement: str = NO_MOVEMENT, allow_extra_lines: bool = False) -> dict:
    """``{"arms": str, "legs": str}`` from an answer, or ``FormatError`` saying what is wrong."""
    if not isinstance(answer, str):
        raise FormatError(f"answer is {type(answer).__name__}, not text")
    answer = _THINK.sub("", answer)
    found: dict[str, str] = {}
    for line in answer.splitlines():
        if not line.strip():
            continue
        m = _LINE.match(line)
        if not m:
            if allow_extra_lines:
                continue
            raise FormatError(f"unexpected line {line.strip()[:80]!r}")
        part = "arms" if m.group(1).lower().startswith("arm") else "legs"
        if part in found:
            raise FormatError(f"more than one {PART_LABELS[part]}: line")
        text = canonical(m.group(2), no_movement)
        if not text:
            raise FormatError(f"empty {PART_LABELS[part]}: line")
        found[part] = text
    missing = [PART_LABELS[p] for p in PART_LABELS if p not in found]
    if missing:
        raise FormatError(f"no {' / '.join(missing)}: line")
    return found
