"""Durable part-text cache and the loop that fills it.

``PartTextCache`` is SQLite in WAL mode, keyed by (backend, model, prompt_version, caption); every
answer is committed as soon as it arrives, so a crash or Ctrl-C loses at most the requests in
flight and never corrupts what is stored (SQLite's journal guarantees it). The cache lives
outside DVC's outs (``part_texts.cache_path``), so DVC never deletes it before a rerun.

``fill_part_texts`` asks the backend for every caption not in the cache, with a thread pool of
``concurrency`` workers; only the main thread writes to SQLite.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path

from tqdm import tqdm

from party.io import read_json
from party.sqlite import SQLiteCache, select_in
from party.text.backends.base import BackendError, PartTextResult

log = logging.getLogger(__name__)


class PartTextCache(SQLiteCache):
    kind = "part-text cache"
    hint = " (every caption is then asked again: the answers cost LLM calls)"
    schema = (
        "CREATE TABLE IF NOT EXISTS part_texts (backend TEXT NOT NULL, model TEXT NOT NULL, "
        "prompt_version TEXT NOT NULL, caption TEXT NOT NULL, parts TEXT NOT NULL, "
        "fallback INTEGER NOT NULL, reason TEXT, attempts INTEGER, raw TEXT, created REAL, "
        "PRIMARY KEY (backend, model, prompt_version, caption))",
        "CREATE TABLE IF NOT EXISTS prompts (backend TEXT NOT NULL, model TEXT NOT NULL, "
        "prompt_version TEXT NOT NULL, fingerprint TEXT NOT NULL, "
        "PRIMARY KEY (backend, model, prompt_version))",
    )

    def check_prompt(self, backend: str, model: str, prompt_version: str, fingerprint: str) -> None:
        """Refuse a prompt whose text changed while ``prompt_version`` did not."""
        row = self.db.execute("SELECT fingerprint FROM prompts WHERE backend=? AND model=? AND "
                              "prompt_version=?", (backend, model, prompt_version)).fetchone()
        if row is None:
            with self.db:
                self.db.execute("INSERT INTO prompts VALUES (?,?,?,?)", (backend, model, prompt_version, fingerprint))
        elif row[0] != fingerprint:
            raise ValueError(f"{self.path}: the prompt for prompt_version={prompt_version!r} changed "
                             f"(fingerprint {row[0]} -> {fingerprint}); set a new part_texts.prompt_version")

    def get_many(self, backend: str, model: str, prompt_version: str, captions: list[str],
                 parts: Sequence[str]) -> dict[str, dict]:
        """caption -> {"parts", "fallback", "reason"} for stored rows with a non-empty text for
        every part of ``parts``."""
        out = {}
        q = ("SELECT caption, parts, fallback, reason FROM part_texts WHERE backend=? AND model=? "
             "AND prompt_version=? AND caption IN ({})")
        for cap, texts, fb, reason in select_in(self.db, q, [backend, model, prompt_version], captions, 400):
            try:
                p = json.loads(texts)
                if all(isinstance(p.get(k), str) and p[k] for k in parts):
                    out[cap] = {"parts": {k: p[k] for k in parts}, "fallback": bool(fb), "reason": reason}
            except (ValueError, AttributeError):
                pass                                       # unreadable row: asked again
        return out

    def put(self, backend: str, model: str, prompt_version: str, caption: str, res: PartTextResult) -> None:
        with self.db:                                          # one transaction = one answer
            self.db.execute("INSERT OR REPLACE INTO part_texts VALUES (?,?,?,?,?,?,?,?,?,?)",
                            (backend, model, prompt_version, caption, json.dumps(res.parts),
                             int(res.fallback), res.reason, res.calls, res.raw, time.time()))

    def count(self) -> int:
        return self.db.execute("SELECT COUNT(*) FROM part_texts").fetchone()[0]


def fill_part_texts(captions: list[str], backend, cache: PartTextCache, cfg,
                    progress: bool = True) -> tuple[dict[str, dict], dict]:
    """Part texts for every caption (cache first, then the backend). Returns
    (caption -> {part: text} for the parts ``cfg.parts``, stats)."""
    captions = list(dict.fromkeys(c for c in captions))
    pv = str(cfg.prompt_version)
    cache.check_prompt(backend.name, backend.model, pv, backend.fingerprint)
    cached = cache.get_many(backend.name, backend.model, pv, captions, [str(p) for p in cfg.parts])
    if bool(cfg.retry_fallbacks):
        cached = {c: r for c, r in cached.items() if not r["fallback"]}
    results = {c: r["parts"] for c, r in cached.items()}
    fallbacks = {c: r["reason"] for c, r in cached.items() if r["fallback"]}
    todo = [c for c in captions if c not in cached]
    stats = {"captions": len(captions), "hits": len(cached), "misses": len(todo), "calls": 0,
             "retries": 0, "format_failures": 0, "fallbacks_new": 0, "request_failures": 0}
    request_failed: dict[str, str] = {}
    t0 = time.time()

    def record(cap: str, res: PartTextResult) -> None:
        stats["calls"] += res.calls
        stats["retries"] += res.retries
        stats["format_failures"] += res.format_failures
        results[cap] = res.parts
        if res.fallback:
            fallbacks[cap] = res.reason
            stats["fallbacks_new"] += 1
        if res.cacheable:
            cache.put(backend.name, backend.model, pv, cap, res)
        else:
            stats["request_failures"] += 1
            request_failed[cap] = res.reason

    workers = max(1, int(cfg.concurrency))
    max_consecutive = int(cfg.get("max_consecutive_failures") or 0) or None   # openai only
    bar = tqdm(total=len(todo), desc=f"part texts ({backend.name})", disable=not progress or not todo)
    stop: threading.Event = getattr(backend, "stop", threading.Event())
    streak = 0

    def check_streak(res: PartTextResult) -> None:
        """Stop after ``max_consecutive_failures`` captions in a row got no answer (any concurrency)."""
        nonlocal streak
        streak = streak + 1 if not res.cacheable else 0
        if max_consecutive and streak >= max_consecutive:
            raise BackendError(f"{streak} captions in a row failed after retries "
                               f"(last: {res.reason}); is the server at "
                               f"{cfg.get('base_url')} up?")

    if workers == 1:
        try:
            for cap in todo:
                res = backend.describe(cap)
                record(cap, res)
                bar.update()
                check_streak(res)
        finally:
            bar.close()
    else:
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="part-texts")
        try:
            pending, queue = set(), iter(todo)
            future_cap = {}
            for cap in queue:                                  # keep at most 2x workers queued
                f = pool.submit(backend.describe, cap)
                future_cap[f] = cap
                pending.add(f)
                if len(pending) >= 2 * workers:
                    break
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    res = f.result()                           # BackendError propagates
                    record(future_cap.pop(f), res)
                    bar.update()
                    check_streak(res)
                    nxt = next(queue, None)
                    if nxt is not None:
                        nf = pool.submit(backend.describe, nxt)
                        future_cap[nf] = nxt
                        pending.add(nf)
        except BaseException:
            stop.set()                                         # workers stop at their next request/sleep
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        finally:
            bar.close()
        pool.shutdown(wait=True)
    bar.close()
    stats["fallbacks"] = len(fallbacks)
    stats["seconds"] = round(time.time() - t0, 3)
    stats["backend"], stats["model"], stats["prompt_version"] = backend.name, backend.model, pv
    stats["prompt_fingerprint"] = backend.fingerprint
    stats["fallback_captions"] = fallbacks
    stats["request_failed_captions"] = request_failed
    return results, stats


def load_part_texts(path: str | Path, parts: Sequence[str] | None = None) -> dict[str, dict]:
    """{caption: {part: text}} as written by `party cache_part_texts`, validated: every entry holds
    a non-empty text for each of ``parts`` (``part_texts.parts``; None: the first entry's parts)."""
    path = Path(path)
    if path.is_dir():
        path = path / "part_texts.json"
    obj = read_json(path, "party cache_part_texts")
    for cap, texts in obj.items():
        if parts is None and isinstance(texts, dict):
            parts = list(texts)                        # the first entry's parts, for every entry
        if not (isinstance(texts, dict) and parts and all(isinstance(texts.get(k), str) and texts[k] for k in parts)):
            names = "/".join(repr(str(k)) for k in parts) if parts else "part"
            raise ValueError(f"{path}: entry for caption {cap!r} lacks non-empty {names} texts")
    return obj
