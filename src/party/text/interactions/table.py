"""The interaction table ``party cache_interactions`` writes (``<interactions.out_dir>/``), read and
checked in one place for every reader (TextIM's training and generation, ``evaluate``'s
interaction block):

    interactions.json   {caption: {"parts": [six-part names], "inter": str | null,
                                   "inter_tokens": [word/POS] | null, "non": str | null,
                                   "fallback": bool, ...}}
    subset.json         {"train" | "val" | "test": [clip ids of the interactive subset],
                         "description": str, ...}

Errors name the file and what is wrong with it; a missing file says which stage writes it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from party.io import read_json
from party.text.interactions.prompt import PARTS

PRODUCER = "party cache_interactions"


@dataclass
class InteractionTable:
    """Per-caption interactions (``rows``: the checked entries of ``interactions.json``) and the
    interactive subset (``splits``, ``description``) of one folder."""
    rows: dict[str, dict]
    splits: dict[str, list[str]]
    description: str
    folder: Path

    def get(self, caption: str) -> dict | None:
        return self.rows.get(caption)

    def clip_ids(self, split: str) -> list[str]:
        if split not in self.splits:
            raise KeyError(f"{self.folder / 'subset.json'}: no split {split!r} (have {', '.join(self.splits)})")
        return list(self.splits[split])


def _check_entry(path: Path, cap: str, e) -> dict:
    if not isinstance(e, dict) or not isinstance(e.get("parts"), list):
        raise ValueError(f"{path}: entry of {cap!r} needs a 'parts' list, got {e!r}")
    bad = [p for p in e["parts"] if p not in PARTS]
    if bad:
        raise ValueError(f"{path}: entry of {cap!r} names unknown parts {bad} (choices: {list(PARTS)})")
    for key in ("inter", "non"):
        if e.get(key) is not None and not isinstance(e[key], str):
            raise ValueError(f"{path}: entry of {cap!r}: {key!r} must be a string or null, got {e[key]!r}")
    toks = e.get("inter_tokens")
    if toks is not None and not (isinstance(toks, list) and all(isinstance(t, str) for t in toks)):
        raise ValueError(f"{path}: entry of {cap!r}: 'inter_tokens' must be a list of strings or null")
    return e


def read_interactions(folder: str | Path) -> InteractionTable:
    """Read and check ``interactions.json`` and ``subset.json`` of ``folder``."""
    folder = Path(folder)
    path = folder / "interactions.json"
    raw = read_json(path, PRODUCER)
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected an object {{caption: entry}}, got {type(raw).__name__}")
    rows = {cap: _check_entry(path, cap, e) for cap, e in raw.items()}
    spath = folder / "subset.json"
    sub = read_json(spath, PRODUCER)
    if not isinstance(sub, dict):
        raise ValueError(f"{spath}: expected an object {{split: [clip ids], description}}, got {type(sub).__name__}")
    splits = {k: v for k, v in sub.items() if isinstance(v, list)}        # other keys (counts, ...) not read
    for k, v in splits.items():
        if not all(isinstance(c, str) for c in v):
            raise ValueError(f"{spath}: {k!r} must be a list of clip ids")
    desc = sub.get("description")
    if not isinstance(desc, str) or not desc.strip():
        raise ValueError(f"{spath}: 'description' must be a non-empty string")
    return InteractionTable(rows, splits, desc.strip(), folder)
