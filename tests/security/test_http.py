"""Keys stay with their host: the openai part-text backend against local HTTP servers on
127.0.0.1 (redirects, plain http, proxies, error messages), and setup.sh's package sources."""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from party.text.backends import build_backend
from party.text.backends.base import BackendError

REPO = Path(__file__).resolve().parents[2]
KEY_ENV = "PARTY_TEST_HTTP_KEY"
KEY = "sk-test-http-key-7f3a9c51"
CAPTION = "a person walks forward."


def _completion(content: str) -> bytes:
    return json.dumps({"id": "x", "object": "chat.completion", "model": "test-model",
                       "choices": [{"index": 0, "finish_reason": "stop",
                                    "message": {"role": "assistant", "content": content}}]}).encode()


GOOD = _completion("Arms: The arms swing.\nLegs: The legs walk forward.")


class Server:
    """A recording HTTP server on 127.0.0.1 in a thread; ``respond(handler)`` -> (code, headers, body)."""

    def __init__(self, respond):
        self.requests: list[dict] = []
        self.lock = threading.Lock()
        rec = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def _handle(self):
                n = int(self.headers.get("Content-Length") or 0)
                body = self.rfile.read(n) if n else b""
                with rec.lock:
                    rec.requests.append({"method": self.command, "path": self.path, "body": body,
                                         "auth": self.headers.get("Authorization")})
                code, headers, data = respond(self)
                self.send_response(code)
                for k, v in headers.items():
                    self.send_header(k, v)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)
                self.close_connection = True

            do_GET = do_POST = do_PUT = do_CONNECT = _handle

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.origin = f"http://127.0.0.1:{self.port}"
        threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def serve():
    servers: list[Server] = []

    def make(respond) -> Server:
        servers.append(Server(respond))
        return servers[-1]
    yield make
    for s in servers:
        s.close()


@pytest.fixture(autouse=True)
def _env(monkeypatch):
    monkeypatch.setenv(KEY_ENV, KEY)
    for name in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY",
                 "no_proxy", "NO_PROXY"):
        monkeypatch.delenv(name, raising=False)
    urllib.request.install_opener(None)     # urlopen's shared opener reads the proxies when first built
    yield
    urllib.request.install_opener(None)


def _backend(base_url: str, **kw):
    cfg = OmegaConf.load(REPO / "conf" / "part_texts" / "openai.yaml")
    over = {"base_url": base_url, "model": "test-model", "api_key_env": KEY_ENV, "timeout_s": 2.0,
            "max_retries": 3, "backoff_base_s": 0.01, "backoff_max_s": 0.02, "backoff_jitter": 0.0,
            "retry_after_max_s": 0.02, "seed": 0}
    over.update(kw)
    return build_backend(OmegaConf.merge(cfg, over))


def _describe(base_url: str, **kw):
    """(result, None) or (None, error message) of one caption."""
    try:
        return _backend(base_url, **kw).describe(CAPTION), None
    except BackendError as e:
        return None, str(e)


def test_redirect_to_another_origin_is_refused_and_the_key_stays(serve):
    """A 302 to another host (here another port) is not followed: the other server never sees
    the Authorization header, the error names both origins, and nothing is retried."""
    other = serve(lambda h: (503, {}, b"busy"))          # transient: a follower would retry into it
    first = serve(lambda h: (302, {"Location": f"{other.origin}/v1/chat/completions"}, b""))
    res, err = _describe(f"{first.origin}/v1")
    assert [r["auth"] for r in other.requests] == []
    assert other.requests == []
    assert err is not None, f"no error; result {res}"
    assert f"{first.origin}/v1/chat/completions" in err and other.origin in err
    assert "302" in err and "part_texts.base_url" in err and "final address" in err
    assert len(first.requests) == 1                      # not retried
    assert first.requests[0]["auth"] == f"Bearer {KEY}"  # the configured host does get the key
    assert KEY not in err


def test_plain_http_to_a_non_loopback_host_is_refused_before_connecting(monkeypatch):
    connects = []

    def no_network(address, *a, **kw):
        connects.append(address)
        raise ConnectionRefusedError("no network in tests")
    monkeypatch.setattr(socket, "create_connection", no_network)
    res, err = _describe("http://10.255.255.1:9/v1", timeout_s=0.2, max_retries=0)
    assert connects == []
    assert err is not None and "http://10.255.255.1:9/v1" in err and "allow_insecure_http" in err
    # the switch allows it (a trusted network): now it connects
    res, err = _describe("http://10.255.255.1:9/v1", timeout_s=0.2, max_retries=0, allow_insecure_http=True)
    assert err is None and res.fallback and not res.cacheable
    assert connects == [("10.255.255.1", 9)]


@pytest.mark.parametrize("url", ["http://127.0.0.1:9/v1", "http://127.8.9.10:9/v1", "http://localhost:9/v1",
                                 "http://[::1]:9/v1", "https://10.255.255.1/v1", "https://llm.invalid/v1"])
def test_loopback_http_and_https_need_no_switch(url):
    assert _backend(url).url.endswith("/v1/chat/completions")


def test_http_proxy_from_the_environment_never_sees_a_loopback_request(serve, monkeypatch):
    proxy = serve(lambda h: (502, {}, b"proxy"))
    server = serve(lambda h: (200, {"Content-Type": "application/json"}, GOOD))
    for name in ("http_proxy", "HTTP_PROXY", "all_proxy"):
        monkeypatch.setenv(name, proxy.origin)
    res, err = _describe(f"{server.origin}/v1")
    assert proxy.requests == []
    assert err is None and not res.fallback and res.parts["legs"] == "The legs walk forward."
    assert [r["auth"] for r in server.requests] == [f"Bearer {KEY}"]


def test_https_goes_through_a_proxy_only_as_a_connect_tunnel(serve, monkeypatch):
    """https may use https_proxy, through CONNECT: the proxy sees the host name, never the key."""
    proxy = serve(lambda h: (502, {}, b""))
    monkeypatch.setenv("https_proxy", proxy.origin)
    res, err = _describe("https://llm.invalid/v1", max_retries=0)
    assert err is None and res.fallback and not res.cacheable          # the tunnel was refused
    assert [(r["method"], r["path"], r["auth"]) for r in proxy.requests] == [("CONNECT", "llm.invalid:443", None)]


def test_the_key_never_appears_in_errors(serve, caplog):
    def echo(h):                                     # a server that echoes the request headers
        said = f"denied for {h.headers.get('Authorization')} at {h.path}".encode()
        return {"/401/v1/chat/completions": (401, {}, said),
                "/html/v1/chat/completions": (200, {}, b"<html>" + said + b"</html>"),
                "/moved/v1/chat/completions": (307, {"Location": "https://u:pw@evil.example:8443/x?token=t0k"}, b"")
                }[h.path.split("?")[0]]
    s = serve(echo)
    caplog.set_level("DEBUG")
    res, err = _describe(f"{s.origin}/401/v1")
    assert err is not None and "HTTP 401" in err and "denied for Bearer ***" in err
    assert KEY not in err
    res, err = _describe(f"{s.origin}/html/v1", max_retries=1)       # a transport failure's reason
    assert err is None and res.fallback and "not a chat completion" in res.reason
    assert KEY not in res.reason
    res, err = _describe(f"{s.origin}/moved/v1?api_key={KEY}")
    assert err is not None and "https://evil.example:8443" in err and "api_key=***" in err
    assert KEY not in err and "pw" not in err and "t0k" not in err
    assert KEY not in caplog.text
    assert all(r["auth"] == f"Bearer {KEY}" for r in s.requests)


def test_a_query_in_base_url_stays_a_query(serve):
    s = serve(lambda h: (200, {}, GOOD))
    res, err = _describe(f"{s.origin}/v1?api-version=preview")
    assert err is None and not res.fallback
    assert [r["path"] for r in s.requests] == ["/v1/chat/completions?api-version=preview"]


FAKE_PY = """#!/usr/bin/env bash
case "$1 $2" in
  "-m uv") printf '%s\\n' "$@" > "$REC/argv"; env | grep '^UV_' > "$REC/env" || true; exit 0 ;;
  "-m pip") [ "$3" = config ] && exec "$REALPY" "$@"; exit 0 ;;
  "-c "*) exit 0 ;;
esac
exec "$REALPY" "$@"
"""


def test_setup_gives_pip_index_credentials_to_uv_by_environment_not_argv(tmp_path):
    """scripts/setup.sh with pip.conf index URLs that hold credentials: uv's command line (readable
    by every user through ps) holds none of them; its environment carries the sources."""
    root = tmp_path / "repo"
    (root / "scripts").mkdir(parents=True)
    for f in ("setup.sh", "pip_sources.py"):
        shutil.copy(REPO / "scripts" / f, root / "scripts" / f)
    py = root / ".venv" / "bin" / "python"
    py.parent.mkdir(parents=True)
    py.write_text(FAKE_PY)
    py.chmod(0o755)
    conf = tmp_path / "pip.conf"
    conf.write_text("[global]\nindex-url = https://user:s3cret@idx.example/simple\n"
                    "extra-index-url =\n    https://tok3n@extra.example/simple\n    https://plain.example/simple\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIP_", "UV_", "PARTY_"))}
    env.update(PIP_CONFIG_FILE=str(conf), REALPY=sys.executable, REC=str(tmp_path))
    out = subprocess.run(["bash", str(root / "scripts" / "setup.sh")], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    argv = (tmp_path / "argv").read_text().splitlines()
    assert argv[:4] == ["-m", "uv", "pip", "install"]
    assert [a for a in argv if "s3cret" in a or "tok3n" in a] == []
    uv_env = dict(line.split("=", 1) for line in (tmp_path / "env").read_text().splitlines())
    assert uv_env["UV_INDEX_URL"] == "https://user:s3cret@idx.example/simple"
    assert uv_env["UV_EXTRA_INDEX_URL"] == "https://tok3n@extra.example/simple https://plain.example/simple"
