"""Interaction extraction (SPEC-textim §3): which of six body parts interact with an object in a
caption, the exact phrase of that interaction (c_inter) and the rest of the caption (c_non).

- ``prompt``: the LLM prompt, its fingerprint and the check of an answer (part mapping, phrase check,
  merging, c_non);
- ``extract``: the backends (``openai``-compatible, ``rules``, ``oracle`` for the synthetic set), the
  retries, the durable SQLite cache and the fill loop;
- here: ``extract_index`` (every caption of a prepared index, as the stage ``cache_interactions``
  writes them) and ``build_extractor`` (one caption at a time, for generation from free text).

``interactions.*`` (conf/interactions/) holds ``InteractionsConfig``'s keys and the stage's own
(``index_path``, ``out_dir``, ``subset``, ``generate_backend``).
"""
from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Mapping, Sequence

from party.text.interactions.extract import (InteractionCache, InteractionsConfig, build_interaction_backend,
                                             fill_interactions)

_WORD = re.compile(r"[a-z0-9]+(?:'[a-z]+)?")


def extractor_config(icfg: Mapping, oracle_root: str | None = None) -> InteractionsConfig:
    """``InteractionsConfig`` of ``interactions.*`` (the stage's own keys left out); the oracle reads the
    dataset at ``oracle_root`` unless ``interactions.oracle_root`` names one."""
    names = {f.name for f in dataclasses.fields(InteractionsConfig)}
    kw = {k: v for k, v in dict(icfg).items() if k in names}
    if kw.get("backend") == "oracle" and not kw.get("oracle_root"):
        kw["oracle_root"] = oracle_root
    return InteractionsConfig.from_cfg(kw)


def phrase_tokens(caption: str, phrases: Sequence[str], tokens: Sequence[str] | None) -> list[str] | None:
    """The ``word/POS`` tokens of ``phrases`` (exact caption spans, up to case and punctuation) sliced from
    the caption's ``tokens`` (one per word, lemmatised, punctuation dropped: HumanML3D's), in order; None
    when the caption's words do not pair one to one with its tokens or a phrase is not a run of words."""
    if not tokens or not phrases:
        return None
    words = [w.lower() for w in _WORD.findall(caption.lower())]
    if len(words) != len(tokens):
        return None
    out: list[str] = []
    for ph in phrases:
        want = _WORD.findall(ph.lower())
        n = len(want)
        hit = next((i for i in range(len(words) - n + 1) if n and words[i:i + n] == want), None)
        if hit is None:
            return None
        out += list(tokens[hit:hit + n])
    return out


def extract_index(index, icfg: Mapping, progress: bool = True) -> tuple[dict, dict]:
    """The interactions of every caption of a prepared ``index``: ({caption: {"parts", "inter",
    "inter_tokens", "non", "phrases", "fallback", "reason", "attempts"}}, the fill's stats). Raises when
    captions got no answer or the fallback rate is above ``interactions.max_fallback_rate`` (the answers
    stay cached)."""
    cfg = extractor_config(icfg, str(index.root))
    captions = index.captions()
    if not captions:
        raise ValueError(f"{index.path}: the index has no captions")
    tokens = {}
    for clip in index.clips():
        for c in clip["captions"]:
            tokens.setdefault(c["caption"], c.get("tokens"))
    backend = build_interaction_backend(cfg)
    cache = InteractionCache(cfg.cache_path)
    try:
        results, stats = fill_interactions(captions, backend, cache, cfg, progress=progress)
    finally:
        cache.close()
    records = {}
    for cap in captions:
        r = results[cap]
        records[cap] = {**r.to_json(), "inter_tokens": phrase_tokens(cap, r.phrases, tokens.get(cap))}
    stats = {k: v for k, v in stats.items() if k not in ("fallback_captions", "request_failed_captions")} | {
        "fallback_examples": dict(list(stats["fallback_captions"].items())[:5]),
        "interactive_captions": sum(bool(r["parts"]) for r in records.values())}
    return records, stats


def build_extractor(icfg: Mapping) -> Callable[[str], dict]:
    """caption -> its interaction record (as ``extract_index`` writes one, without tokens), through the
    backend of ``icfg`` (not cached: generation asks for a few captions at a time)."""
    cfg = extractor_config(icfg)
    backend = build_interaction_backend(cfg)

    def extract(caption: str) -> dict:
        return backend.extract(caption).to_json()
    return extract
