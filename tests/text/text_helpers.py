"""Helpers for the text tests: a prepared index on disk, stage configs, and a scripted
OpenAI-compatible chat-completions server on 127.0.0.1 (a real HTTP server in a thread)."""
from __future__ import annotations

import copy
import functools
import json
import re
import threading
import time
from collections import Counter
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[2]


def write_index(root: Path, captions_per_clip: list[list[str]]) -> Path:
    """A prepared index (format of party.data.index, version 1) with the given captions."""
    clips = [{"id": f"{i:06d}", "motion": f"{i:06d}", "start": 0, "end": 60, "split": "train",
              "captions": [{"caption": c, "tokens": [f"{w}/NOUN" for w in c.split()]} for c in caps]}
             for i, caps in enumerate(captions_per_clip)]
    path = root / "prepared" / "index.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"version": 1, "dataset": "test", "root": ".", "fps": 20.0, "feat_dim": 263,
                                "n_joints": 22, "skeleton": "t2m", "clips": clips}))
    return path


@functools.lru_cache(maxsize=None)
def _composed(part_texts: str, text: str) -> dict:
    from party.config import compose
    cfg = compose([f"part_texts={part_texts}", f"text={text}", "progress=false", "tracking.enabled=false"],
                  REPO / "conf")
    return OmegaConf.to_container(cfg, resolve=False)          # interpolations kept: paths set below


def stage_cfg(tmp_path: Path, part_texts: str = "rules", text: str = "minilm", **overrides):
    """Full stage config (conf/ composed with part_texts=<part_texts>, text=<text>), outputs in tmp."""
    cfg = OmegaConf.create(copy.deepcopy(_composed(part_texts, text)))
    cfg.paths.prepared = str(tmp_path / "prepared")
    cfg.part_texts.out_dir = str(tmp_path / "part_texts")
    cfg.part_texts.cache_path = str(tmp_path / "cache" / "part_texts.sqlite")
    cfg.text.embeddings_dir = str(tmp_path / "embeddings")
    cfg.text.cache_path = str(tmp_path / "cache" / "embeddings.sqlite")
    cfg.text.device = "cpu"
    for k, v in overrides.items():
        OmegaConf.update(cfg, k, v)
    return cfg


def good_answer(caption: str) -> str:
    return f"Arms: The arms move for <{caption}>.\nLegs: No significant movement."


class FakeLLM:
    """Scripted server. ``script[caption]`` lists the replies to that caption's successive
    requests ("good", "malformed", "badjson", "429", "500", "slow", "401", "extra"); after the
    list runs out (or for unscripted captions) it answers ``default``."""

    def __init__(self, script: dict | None = None, default: str = "good", slow_s: float = 1.0,
                 retry_after: str = "0"):
        self.script, self.default, self.slow_s, self.retry_after = script or {}, default, slow_s, retry_after
        self.requests = 0
        self.per_caption: Counter = Counter()
        self.auth: list[str | None] = []
        self.bodies: list[dict] = []
        self.lock = threading.Lock()
        llm = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                caption = re.search(r'Holistic Description: "(.*)"', body["messages"][-1]["content"]).group(1)
                with llm.lock:
                    llm.requests += 1
                    n = llm.per_caption[caption]
                    llm.per_caption[caption] += 1
                    llm.auth.append(self.headers.get("Authorization"))
                    llm.bodies.append(body)
                steps = llm.script.get(caption, [])
                action = steps[n] if n < len(steps) else llm.default
                if self.path != "/v1/chat/completions":
                    return self._send(404, b'{"error": "not found"}')
                if action in ("429", "500", "503", "401"):
                    headers = {"Retry-After": llm.retry_after} if action == "429" else {}
                    return self._send(int(action), b'{"error": "scripted"}', headers)
                if action == "badjson":
                    return self._send(200, b"<html>oops</html>")
                if action == "truncated":                  # HTTP 200, the JSON cut mid-way
                    return self._send(200, b'{"id": "x", "object": "chat.completion", "choi')
                if action == "slow":
                    time.sleep(llm.slow_s)
                content = {"good": good_answer(caption), "slow": good_answer(caption),
                           "malformed": "Sure! The person waves their arm.",
                           "extra": "Here you go:\n" + good_answer(caption),
                           "empty": "Arms:\nLegs: No significant movement."}[action]
                payload = {"id": "x", "object": "chat.completion", "model": body["model"],
                           "choices": [{"index": 0, "finish_reason": "stop",
                                        "message": {"role": "assistant", "content": content}}]}
                self._send(200, json.dumps(payload).encode())

            def _send(self, code, data, headers=None):
                try:
                    self.send_response(code)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    for k, v in (headers or {}).items():
                        self.send_header(k, v)
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):
                    pass                       # the client gave up (timeout test)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/v1"

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


def openai_cfg(tmp_path: Path, server: FakeLLM, **overrides):
    """Stage config for the openai backend against ``server``, with fast retries."""
    base = {"part_texts.base_url": server.base_url, "part_texts.model": "test-model",
            "part_texts.api_key_env": "PARTY_TEST_LLM_KEY", "part_texts.timeout_s": 0.5,
            "part_texts.backoff_base_s": 0.01, "part_texts.backoff_max_s": 0.05,
            "part_texts.max_retries": 3, "part_texts.concurrency": 4}
    base.update(overrides)
    return stage_cfg(tmp_path, "openai", **base)
