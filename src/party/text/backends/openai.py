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
the Authorization header of requests to ``base_url``'s own host; it is never logged or stored, and
error messages and failure reasons are masked (the key, URL userinfo and credential query values,
``party.secrets.redact``). The key stays with its host:

- redirects are never followed (an OpenAI-compatible POST has no use for them, and urllib would
  copy the header to the new host): a 3xx is a ``BackendError``, not retried, naming the
  configured URL and the Location's origin; set ``base_url`` to the final address;
- ``base_url`` must be https, except for loopback hosts (127.0.0.0/8, ::1, localhost), unless
  ``allow_insecure_http: true`` (a trusted network); checked when the backend is built, before
  any request; credentials in the URL itself (``user:pass@``) are refused;
- plain-http requests never go through a proxy (``http_proxy`` would receive the key in clear);
  https requests honour ``https_proxy``/``no_proxy`` through a CONNECT tunnel, so a proxy sees
  only the host name.
"""
from __future__ import annotations

import email.utils
import http.client
import ipaddress
import json
import logging
import os
import random
import socket
import threading
import time
import urllib.error
import urllib.parse
import urllib.request

from party.secrets import MASK, redact, register
from party.text.backends.base import BackendError, PartTextResult
from party.text.prompt import FormatError, build_messages, parse_answer, prompt_fingerprint

log = logging.getLogger(__name__)
RETRY_STATUS = {408, 409, 425, 429, 500, 502, 503, 504, 520, 522, 524, 529}


class TransientError(Exception):
    def __init__(self, msg: str, retry_after: float | None = None):
        super().__init__(msg)
        self.retry_after = retry_after


def is_loopback(host: str | None) -> bool:
    """True for 127.0.0.0/8, ::1 (also IPv4-mapped) and ``localhost``."""
    h = (host or "").strip("[]").rstrip(".").lower()
    if h == "localhost":
        return True
    try:
        ip = ipaddress.ip_address(h)
    except ValueError:
        return False
    mapped = getattr(ip, "ipv4_mapped", None)
    return (mapped or ip).is_loopback


def origin(url: str) -> str:
    """``scheme://host[:port]`` of ``url``, without userinfo, path or query."""
    u = urllib.parse.urlsplit(url)
    host = u.hostname or ""
    if ":" in host:
        host = f"[{host}]"
    try:
        port = u.port
    except ValueError:
        port = None
    return f"{u.scheme.lower()}://{host}" + (f":{port}" if port is not None else "")


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    """Every 3xx reaches the caller as an ``HTTPError``: nothing is re-sent anywhere."""

    def http_error_302(self, req, fp, code, msg, headers):
        return None

    http_error_301 = http_error_303 = http_error_307 = http_error_308 = http_error_302


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
        base = cfg.get("base_url")
        if not base:
            raise BackendError("part_texts.base_url is not set (the server's OpenAI-compatible /v1 address)")
        u = urllib.parse.urlsplit(str(base))          # a query (?api-version=...) stays a query
        self.url = urllib.parse.urlunsplit(u._replace(path=u.path.rstrip("/") + "/chat/completions",
                                                      fragment=""))
        self.no_movement = str(cfg.no_movement_text)
        self.part_names = [str(p) for p in cfg.parts]
        self.stop = stop or threading.Event()
        self.fingerprint = prompt_fingerprint(self.part_names)
        env = str(cfg.api_key_env) if cfg.get("api_key_env") else None
        self._key = os.environ.get(env) if env else None
        if env and not self._key:
            log.warning("environment variable %s is not set: sending requests without an API key", env)
        register(self._key)                                  # masked in whatever is logged
        self._opener = self._build_opener(bool(cfg.get("allow_insecure_http") or False))
        self._rng = random.Random(int(cfg.seed))

    def _scrub(self, text) -> str:
        text = redact(text)
        return text.replace(self._key, MASK) if self._key else text

    def _build_opener(self, allow_insecure_http: bool) -> urllib.request.OpenerDirector:
        """Check ``base_url`` (before any request) and build the opener that never redirects."""
        shown = self._scrub(self.url)
        u = urllib.parse.urlsplit(self.url)
        scheme = u.scheme.lower()
        if scheme not in ("http", "https") or not u.hostname:
            raise BackendError(f"part_texts.base_url {shown}: not an http(s) URL with a host")
        if u.username is not None or u.password is not None:
            raise BackendError(f"part_texts.base_url {shown}: credentials in the URL are not supported; "
                               f"put the key in the environment variable named by part_texts.api_key_env")
        if scheme == "http" and not is_loopback(u.hostname) and not allow_insecure_http:
            raise BackendError(
                f"part_texts.base_url {shown}: plain http to a host that is not loopback would send the "
                f"API key and the captions in clear; use https, or set part_texts.allow_insecure_http=true "
                f"for a trusted network")
        handlers: list = [_NoRedirect()]
        if scheme == "http":
            handlers.append(urllib.request.ProxyHandler({}))   # a proxy would see the key in clear
        # https: the default ProxyHandler (https_proxy, no_proxy) tunnels with CONNECT; the
        # Authorization header only travels inside TLS to the host itself
        return urllib.request.build_opener(*handlers)

    # -- one HTTP request -------------------------------------------------------------
    def _post(self, body: bytes) -> str:
        headers = {"Content-Type": "application/json", "Accept": "application/json"}
        req = urllib.request.Request(self.url, data=body, headers=headers, method="POST")
        if self._key:      # unredirected: never copied onto a follow-up request by any handler
            req.add_unredirected_header("Authorization", f"Bearer {self._key}")
        try:
            with self._opener.open(req, timeout=float(self.cfg.timeout_s)) as resp:
                payload = resp.read()
        except urllib.error.HTTPError as e:
            if 300 <= e.code < 400:
                loc = e.headers.get("Location")
                e.close()
                where = origin(urllib.parse.urljoin(self.url, loc)) if loc else "no Location given"
                raise BackendError(
                    f"{self._scrub(self.url)}: HTTP {e.code} redirect to {self._scrub(where)}; redirects "
                    f"are not followed (the API key goes only to the configured host): set "
                    f"part_texts.base_url to the final address") from None
            try:
                detail = self._scrub(e.read(65536).decode("utf-8", "replace"))[:300]
            except (OSError, http.client.HTTPException):
                detail = ""
            if e.code in RETRY_STATUS:
                raise TransientError(f"HTTP {e.code}", _retry_after(e.headers.get("Retry-After"))) from None
            raise BackendError(f"{self._scrub(self.url)}: HTTP {e.code} {self._scrub(e.reason)}: {detail} "
                               f"(check part_texts.base_url / model / {self.cfg.api_key_env})") from None
        except (TimeoutError, socket.timeout) as e:
            raise TransientError(self._scrub(f"timeout after {self.cfg.timeout_s}s ({e})")) from None
        except urllib.error.URLError as e:
            if isinstance(e.reason, (TimeoutError, socket.timeout)):
                raise TransientError(f"timeout after {self.cfg.timeout_s}s") from None
            raise TransientError(self._scrub(f"connection error: {e.reason}")) from None
        except (ConnectionError, http.client.HTTPException) as e:
            raise TransientError(self._scrub(f"connection error: {type(e).__name__}: {e}")) from None
        try:
            obj = json.loads(payload)
            content = obj["choices"][0]["message"]["content"]
        except (ValueError, KeyError, IndexError, TypeError) as e:
            # a truncated or foreign body (a proxy's HTML page, a cut connection) is the
            # transport's failure, not the model's answer: retried, never cached as an answer
            excerpt = self._scrub(repr(payload[:4096]))[:120]
            raise TransientError(f"response body is not a chat completion ({type(e).__name__}: "
                                 f"{excerpt})") from None
        if content is not None and not isinstance(content, str):
            raise TransientError(f"response content is a {type(content).__name__}, not text")
        return content or ""

    def request(self, body: bytes, res: PartTextResult) -> str:
        """The answer's text of one chat-completion request ``body`` (JSON bytes), retried on transient
        failures with backoff (``Retry-After`` honoured); ``res.calls`` / ``res.retries`` count them.
        Every prompt family on this server calls it (part texts, interactions)."""
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
                res.raw = self.request(body, res)
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

