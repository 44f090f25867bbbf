"""Part texts from any OpenAI-compatible chat-completions endpoint (vLLM, Ollama, llama.cpp
server, hosted APIs), with the standard library's HTTP client.

Per caption (``describe``):
- up to ``max_format_attempts`` answers are requested; an answer that fails ``parse_answer``
  is asked again (TextIM §3.3); after the last failure the result is the fallback
  ``"No significant movement"`` for every part, marked ``fallback`` (and cached: asking again
  would cost the same);
- each request is retried up to ``max_retries`` times on 429, 5xx, timeouts, connection
  errors and HTTP 200 bodies that are not a chat completion (truncated JSON, a proxy's page), sleeping ``backoff_base_s * 2**k`` (capped at ``backoff_max_s``, at least the
  server's ``Retry-After``); when retries run out the caption is a *request failure*: not cached,
  and the stage stops or falls back according to ``request_failure``;
- other HTTP errors (400/401/403/404...) raise ``BackendError``: config is wrong, retrying won't help.

The API key is read from the environment variable named by ``api_key_env`` and only ever put in
the Authorization header; it is never logged or stored.
"""
from __future__ import annotations

import email.utils
import http.client
import json
import logging
import os
import random
import socket
import threading
import time
import urllib.error
import urllib.request

from party.text.backends.base import BackendError, PartTextResult
from party.text.prompt import FormatError, build_messages, parse_answer, prompt_fingerprint

log = logging.getLogger(__name__)
RETRY_STATUS = {408, 409, 425, 429, 500, 502, 503, 504, 520, 522, 524, 529}


class TransientError(Exception):
    def __init__(self, msg: str, retry_after: float | None = None):
        super().__init__(msg)
        self.retry_after = retry_after


def _retry_after(value: str | None) -> float | None:
    if not value:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(value)
            return max(0.0, when.timestamp() - time.time())
        except (TypeError, ValueError):
            return None


class OpenAIBackend:
    name = "openai"

    def __init__(self, cfg, stop: threading.Event | None = None):
        self.cfg = cfg
        self.model = str(cfg.model)
        self.url = str(cfg.base_url).rstrip("/") + "/chat/completions"
        self.no_movement = str(cfg.no_movement_text)
        self.part_names = [str(p) for p in cfg.parts]
        self.stop = stop or threading.Event()
        self.fingerprint = prompt_fingerprint(self.part_names)
        env = str(cfg.api_key_env) if cfg.get("api_key_env") else None
        self._key = os.environ.get(env) if env else None
        if env and not self._key:
            log.warning("environment variable %s is not set: sending requests without an API key", env)
        self._rng = random.Random(int(cfg.seed))

    # -- one HTTP request -------------------------------------------------------------
    def _post(self, body: bytes) -> str:
        headers = {"Content-Type": "application/json", "Accept": "application/json"}
        if self._key:
            headers["Authorization"] = f"Bearer {self._key}"
        req = urllib.request.Request(self.url, data=body, headers=headers, method="POST")
        try:
            with urllib.request.urlopen(req, timeout=float(self.cfg.timeout_s)) as resp:
                payload = resp.read()
        except urllib.error.HTTPError as e:
            detail = e.read()[:300].decode("utf-8", "replace")
            if e.code in RETRY_STATUS:
                raise TransientError(f"HTTP {e.code}", _retry_after(e.headers.get("Retry-After"))) from None
            raise BackendError(f"{self.url}: HTTP {e.code} {e.reason}: {detail} "
                               f"(check part_texts.base_url / model / {self.cfg.api_key_env})") from None
        except (TimeoutError, socket.timeout) as e:
            raise TransientError(f"timeout after {self.cfg.timeout_s}s ({e})") from None
        except urllib.error.URLError as e:
            if isinstance(e.reason, (TimeoutError, socket.timeout)):
                raise TransientError(f"timeout after {self.cfg.timeout_s}s") from None
            raise TransientError(f"connection error: {e.reason}") from None
        except (ConnectionError, http.client.HTTPException) as e:
            raise TransientError(f"connection error: {type(e).__name__}: {e}") from None
        try:
            obj = json.loads(payload)
            content = obj["choices"][0]["message"]["content"]
        except (ValueError, KeyError, IndexError, TypeError) as e:
            # a truncated or foreign body (a proxy's HTML page, a cut connection) is the
            # transport's failure, not the model's answer: retried, never cached as an answer
            raise TransientError(f"response body is not a chat completion ({type(e).__name__}: "
                                 f"{payload[:120]!r})") from None
        if content is not None and not isinstance(content, str):
            raise TransientError(f"response content is a {type(content).__name__}, not text")
        return content or ""

    def _request(self, body: bytes, res: PartTextResult) -> str:
        attempt = 0
        while True:
            if self.stop.is_set():
                raise InterruptedError("stopped")
            res.calls += 1
            try:
                return self._post(body)
            except TransientError as e:
                if attempt >= int(self.cfg.max_retries):
                    raise
                delay = min(float(self.cfg.backoff_base_s) * 2 ** attempt, float(self.cfg.backoff_max_s))
                delay *= 1 + float(self.cfg.backoff_jitter) * self._rng.random()
                if e.retry_after is not None:
                    delay = max(delay, min(e.retry_after, float(self.cfg.retry_after_max_s)))
                log.info("part_texts: %s, retry %d in %.2fs", e, attempt + 1, delay)
                attempt += 1
                res.retries += 1
                if self.stop.wait(delay):
                    raise InterruptedError("stopped") from None

    # -- one caption -------------------------------------------------------------------
    def _fallback(self) -> dict:
        return {p: self.no_movement for p in self.part_names}

    def describe(self, caption: str) -> PartTextResult:
        body = json.dumps({"model": self.model, "messages": build_messages(caption, self.part_names),
                           "temperature": float(self.cfg.temperature),
                           "max_tokens": int(self.cfg.max_tokens)}).encode()
        res = PartTextResult(parts={})
        last = ""
        for _ in range(int(self.cfg.max_format_attempts)):
            try:
                res.raw = self._request(body, res)
                res.parts = parse_answer(res.raw, self.part_names, self.no_movement,
                                         bool(self.cfg.allow_extra_lines))
                return res
            except FormatError as e:
                res.format_failures += 1
                last = str(e)
            except TransientError as e:
                res.parts = self._fallback()
                res.fallback, res.cacheable, res.reason = True, False, f"request: {e}"
                return res
        res.parts = self._fallback()
        res.fallback, res.reason = True, f"format: {last}"
        return res

