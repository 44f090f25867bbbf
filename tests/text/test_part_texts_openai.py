"""cache_part_texts with the openai backend against a real HTTP server on 127.0.0.1."""
from __future__ import annotations

import json
import sqlite3
import time

import pytest

from party.stages import cache_part_texts
from party.text.backends.base import BackendError
from party.text.cache import load_part_texts
from text_helpers import good_answer, openai_cfg, write_index

CAPS = [["a person walks forward.", "someone strolls ahead."], ["a man waves his right hand."],
        ["a person jumps up and down."], ["a person sits down slowly."], ["the person kicks with the left foot."]]
ALL = [c for caps in CAPS for c in caps]


def _cache_rows(cfg) -> dict:
    db = sqlite3.connect(cfg.part_texts.cache_path)
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    rows = {r[0]: (json.loads(r[1]), r[2]) for r in
            db.execute("SELECT caption, parts, fallback FROM part_texts WHERE backend='openai'")}
    db.close()
    return rows


def _expected(caption):
    arms = good_answer(caption).splitlines()[0].removeprefix("Arms: ")
    return {"arms": arms, "legs": "No significant movement"}


def test_good_answers_then_rerun_makes_no_calls(tmp_path, fake_llm, monkeypatch):
    monkeypatch.setenv("PARTY_TEST_LLM_KEY", "sk-secret-test-key-123")
    write_index(tmp_path, CAPS)
    llm = fake_llm()
    cfg = openai_cfg(tmp_path, llm)
    stats = cache_part_texts.run(cfg)
    assert stats["misses"] == len(ALL) and stats["calls"] == len(ALL) == llm.requests
    assert stats["fallbacks"] == 0 and stats["retries"] == 0
    out = load_part_texts(cfg.part_texts.out_dir)
    assert out == {c: _expected(c) for c in ALL}
    # the request: model, temperature and the five few-shot examples of Fig. S5
    body = llm.bodies[0]
    assert body["model"] == "test-model" and body["temperature"] == 0
    assert len(body["messages"]) == 1 + 2 * 5 + 1
    assert llm.auth[0] == "Bearer sk-secret-test-key-123"
    # the key is never written anywhere
    for f in (tmp_path / "part_texts").iterdir():
        assert "sk-secret" not in f.read_text()
    assert b"sk-secret" not in open(cfg.part_texts.cache_path, "rb").read()
    # second run on the unchanged dataset: zero requests reach the server
    before = llm.requests
    stats2 = cache_part_texts.run(cfg)
    assert llm.requests == before
    assert stats2["hits"] == len(ALL) and stats2["calls"] == 0 and stats2["misses"] == 0
    assert load_part_texts(cfg.part_texts.out_dir) == out
    # a new caption costs exactly one request
    write_index(tmp_path, CAPS + [["a person claps."]])
    stats3 = cache_part_texts.run(cfg)
    assert llm.requests == before + 1 and stats3["hits"] == len(ALL) and stats3["misses"] == 1


def test_malformed_429_500_timeout_all_end_in_valid_cache(tmp_path, fake_llm):
    script = {
        ALL[0]: ["malformed", "malformed", "malformed"],          # -> fallback after 3 attempts
        ALL[1]: ["malformed", "badjson", "good"],                 # a format failure, a retry, good
        ALL[2]: ["429", "429", "good"],                           # retried
        ALL[3]: ["500", "503", "good"],
        ALL[4]: ["slow", "good"],                                 # read timeout, retried
        ALL[5]: ["extra"],                                        # extra line -> invalid, then good
    }
    write_index(tmp_path, CAPS)
    llm = fake_llm(script=script, slow_s=1.5)
    cfg = openai_cfg(tmp_path, llm, **{"part_texts.timeout_s": 0.4})
    stats = cache_part_texts.run(cfg)
    assert stats["fallbacks"] == 1 and stats["fallbacks_new"] == 1
    assert list(stats["fallback_captions"]) == [ALL[0]]
    assert stats["format_failures"] == 3 + 1 + 1
    assert stats["retries"] == 1 + 2 + 2 + 1
    assert stats["calls"] == llm.requests == 3 + 3 + 3 + 3 + 2 + 2
    out = load_part_texts(cfg.part_texts.out_dir)
    assert out[ALL[0]] == {"arms": "No significant movement", "legs": "No significant movement"}
    for c in ALL[1:]:
        assert out[c] == _expected(c)
    rows = _cache_rows(cfg)
    assert set(rows) == set(ALL)                                   # every caption has an entry
    assert [c for c, (_, fb) in rows.items() if fb] == [ALL[0]]    # fallback recorded as such
    saved = json.loads((tmp_path / "part_texts" / "stats.json").read_text())
    assert saved["fallbacks"] == 1 and saved["retries"] == 6
    # cached fallbacks are not asked again ...
    n = llm.requests
    assert cache_part_texts.run(cfg)["calls"] == 0 and llm.requests == n
    # ... unless retry_fallbacks
    cfg.part_texts.retry_fallbacks = True
    stats = cache_part_texts.run(cfg)
    assert stats["calls"] == 1 and stats["fallbacks"] == 0
    assert load_part_texts(cfg.part_texts.out_dir)[ALL[0]] == _expected(ALL[0])


def test_a_broken_body_is_a_transport_failure_never_cached(tmp_path, fake_llm):
    """HTTP 200 with truncated JSON is retried like a dropped connection; when retries run out
    the caption is a request failure (not cached), so a rerun against a fixed server asks it."""
    write_index(tmp_path, CAPS)
    llm = fake_llm(script={ALL[1]: ["truncated", "good"], ALL[2]: ["truncated"] * 10})
    cfg = openai_cfg(tmp_path, llm, **{"part_texts.request_failure": "fallback"})
    stats = cache_part_texts.run(cfg)
    assert stats["format_failures"] == 0 and stats["retries"] == 1 + 3
    assert stats["request_failures"] == 1 and list(stats["request_failed_captions"]) == [ALL[2]]
    assert "not a chat completion" in stats["request_failed_captions"][ALL[2]]
    assert load_part_texts(cfg.part_texts.out_dir)[ALL[1]] == _expected(ALL[1])
    assert ALL[2] not in _cache_rows(cfg)                 # not remembered as the model's answer
    llm.script = {}
    stats = cache_part_texts.run(cfg)
    assert stats["calls"] == 1 and stats["fallbacks"] == 0
    assert load_part_texts(cfg.part_texts.out_dir)[ALL[2]] == _expected(ALL[2])


def test_too_many_fallbacks_fail_the_stage(tmp_path, fake_llm):
    """Most captions answered out of format: the stage fails naming the rate and the cache,
    writes nothing, and a rerun with retry_fallbacks against a good server recovers."""
    write_index(tmp_path, CAPS)
    llm = fake_llm(default="malformed")
    cfg = openai_cfg(tmp_path, llm)
    with pytest.raises(BackendError, match=rf"6 of 6 captions \(100%\) got the fallback.*"
                       rf"max_fallback_rate 0.2.*{cfg.part_texts.cache_path}"):
        cache_part_texts.run(cfg)
    assert not (tmp_path / "part_texts" / "part_texts.json").exists()
    llm.default = "good"
    cfg.part_texts.retry_fallbacks = True
    assert cache_part_texts.run(cfg)["fallbacks"] == 0


def test_retry_after_is_respected(tmp_path, fake_llm):
    write_index(tmp_path, [["a person claps."]])
    llm = fake_llm(script={"a person claps.": ["429", "good"]}, retry_after="0.6")
    cfg = openai_cfg(tmp_path, llm)
    t0 = time.time()
    stats = cache_part_texts.run(cfg)
    assert time.time() - t0 >= 0.6                 # backoff_max_s is 0.05: the wait came from Retry-After
    assert stats["retries"] == 1 and stats["fallbacks"] == 0


def test_request_failures_are_not_cached(tmp_path, fake_llm):
    write_index(tmp_path, CAPS)
    llm = fake_llm(script={ALL[2]: ["500"] * 10})   # more failures than max_retries (3)
    cfg = openai_cfg(tmp_path, llm)
    with pytest.raises(BackendError, match="rerun to resume"):
        cache_part_texts.run(cfg)
    assert not (tmp_path / "part_texts" / "part_texts.json").exists()   # no incomplete output
    rows = _cache_rows(cfg)
    assert set(rows) == set(ALL) - {ALL[2]}         # everything else is cached
    assert llm.per_caption[ALL[2]] == 4             # 1 + max_retries
    # with request_failure=fallback the output is complete, the failure still not cached
    cfg.part_texts.request_failure = "fallback"
    stats = cache_part_texts.run(cfg)
    assert stats["hits"] == len(ALL) - 1 and stats["request_failures"] == 1 and stats["fallbacks"] == 1
    assert load_part_texts(cfg.part_texts.out_dir)[ALL[2]]["arms"] == "No significant movement"
    assert ALL[2] not in _cache_rows(cfg)
    # the server recovers: the next run asks only for that caption
    llm.script = {}
    n = llm.requests
    stats = cache_part_texts.run(cfg)
    assert llm.requests == n + 1 and stats["fallbacks"] == 0 and set(_cache_rows(cfg)) == set(ALL)


def test_fatal_http_error_stops_with_clear_message(tmp_path, fake_llm):
    write_index(tmp_path, CAPS)
    llm = fake_llm(default="401")
    cfg = openai_cfg(tmp_path, llm, **{"part_texts.concurrency": 1})
    with pytest.raises(BackendError, match="HTTP 401"):
        cache_part_texts.run(cfg)
    assert llm.requests == 1                        # not retried


def test_changed_prompt_needs_new_prompt_version(tmp_path, fake_llm, monkeypatch):
    write_index(tmp_path, [["a person claps."]])
    llm = fake_llm()
    cfg = openai_cfg(tmp_path, llm)
    cache_part_texts.run(cfg)
    import party.text.backends.openai as ob
    monkeypatch.setattr(ob, "prompt_fingerprint", lambda parts: "changed12345")
    with pytest.raises(ValueError, match="prompt_version"):
        cache_part_texts.run(cfg)
    cfg.part_texts.prompt_version = "fig_s5-v2"
    assert cache_part_texts.run(cfg)["misses"] == 1


@pytest.mark.parametrize("concurrency", [1, 4])
def test_max_consecutive_failures_holds_at_any_concurrency(tmp_path, fake_llm, concurrency):
    """Server down: the stage stops after max_consecutive_failures captions, not after trying all."""
    write_index(tmp_path, CAPS)
    llm = fake_llm(default="500")
    cfg = openai_cfg(tmp_path, llm, **{"part_texts.concurrency": concurrency,
                                       "part_texts.max_consecutive_failures": 2})
    with pytest.raises(BackendError, match="2 captions in a row failed"):
        cache_part_texts.run(cfg)
    tries = 1 + int(cfg.part_texts.max_retries)
    if concurrency == 1:                 # exactly the first two captions, each with every retry
        assert sorted(llm.per_caption.values()) == [tries, tries]
    assert llm.requests < len(ALL) * tries                   # not every caption with all retries
