"""Stage ``cache_part_texts``: Arms/Legs part texts for every caption of the prepared index
(SPEC §4), through the backend ``part_texts.backend`` (``rules`` offline, ``openai`` any
OpenAI-compatible server), cached durably in ``part_texts.cache_path`` (SQLite, not a DVC out).

Writes (atomically) ``<part_texts.out_dir>/part_texts.json`` = {caption: {"arms", "legs"}} and
``stats.json`` (hits, misses, calls, retries, fallbacks, ...); logs the counts to MLflow.
"""
from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from party.data.index import load_index
from party.io import atomic_dir, write_json
from party.stage import stage
from party.text.backends import build_backend
from party.text.backends.base import BackendError
from party.text.cache import PartTextCache, fill_part_texts

log = logging.getLogger(__name__)
COUNTS = ("captions", "hits", "misses", "calls", "retries", "format_failures", "fallbacks",
          "fallbacks_new", "request_failures", "seconds")


@stage("cache_part_texts")
def run(cfg: DictConfig, run_) -> dict:
    pcfg = cfg.part_texts
    index = load_index(pcfg.index_path)
    captions = index.captions()
    if not captions:
        raise ValueError(f"{index.path}: the index has no captions")
    backend = build_backend(pcfg)
    progress = cfg.progress
    cache = PartTextCache(pcfg.cache_path)
    try:
        results, stats = fill_part_texts(captions, backend, cache, pcfg, progress=progress)
    finally:
        cache.close()
    summary = {k: stats[k] for k in COUNTS}
    print("cache_part_texts: " + ", ".join(f"{k}={v}" for k, v in summary.items()))
    run_.log_metrics({f"part_texts/{k}": v for k, v in summary.items()})
    if stats["request_failures"] and pcfg.request_failure != "fallback":
        raise BackendError(
            f"{stats['request_failures']} captions got no answer after {pcfg.max_retries} "
            f"retries (e.g. {next(iter(stats['request_failed_captions'].items()))}); the other "
            f"answers are cached in {pcfg.cache_path}: rerun to resume, or set "
            f"part_texts.request_failure=fallback")
    rate = stats["fallbacks"] / max(1, len(captions))
    if rate > float(pcfg.max_fallback_rate):
        raise BackendError(
            f"{stats['fallbacks']} of {len(captions)} captions ({rate:.0%}) got the fallback "
            f"{pcfg.no_movement_text!r} (e.g. {next(iter(stats['fallback_captions'].items()))}), "
            f"above part_texts.max_fallback_rate {pcfg.max_fallback_rate}; nothing was written. "
            f"The answers are cached in {pcfg.cache_path}: fix the server or prompt and rerun "
            f"with part_texts.retry_fallbacks=true, or raise part_texts.max_fallback_rate")
    if stats["fallbacks"]:
        log.warning("%d of %d captions (%.1f%%) got the fallback part texts (cached in %s)",
                    stats["fallbacks"], len(captions), 100 * rate, pcfg.cache_path)
    out = Path(pcfg.out_dir)
    with atomic_dir(out) as tmp:                   # both files or neither
        write_json(tmp / "part_texts.json", {c: results[c] for c in captions})
        write_json(tmp / "stats.json", stats)
    run_.log_json({k: stats[k] for k in (*COUNTS, "backend", "model", "prompt_version")},
                  "part_texts/stats.json")
    log.info("wrote %s (%d captions)", out / "part_texts.json", len(captions))
    return stats

