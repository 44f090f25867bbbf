"""Throughput of the openai part-text backend: concurrency N vs 1 (baseline, same run),
against a local OpenAI-compatible stub with a fixed latency per request.

    python bench/bench_text_part_texts.py [--captions 200] [--latency 0.05] [--concurrency 8]

Prints captions/s for both and their ratio (ideal: ~concurrency when latency dominates).
"""
from __future__ import annotations

import argparse
import json
import re
import tempfile
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from omegaconf import OmegaConf

from party.text.backends.openai import OpenAIBackend
from party.text.cache import PartTextCache, fill_part_texts

REPO = Path(__file__).resolve().parents[1]


def serve(latency: float) -> ThreadingHTTPServer:
    class H(BaseHTTPRequestHandler):
        def log_message(self, *a):
            pass

        def do_POST(self):
            body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
            cap = re.search(r'"(.*)"', body["messages"][-1]["content"]).group(1)
            time.sleep(latency)
            out = json.dumps({"choices": [{"message": {"content": f"Arms: arms of {cap}\nLegs: legs"}}]}).encode()
            self.send_response(200)
            self.send_header("Content-Length", str(len(out)))
            self.end_headers()
            self.wfile.write(out)
    srv = ThreadingHTTPServer(("127.0.0.1", 0), H)
    srv.daemon_threads = True
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--captions", type=int, default=200)
    ap.add_argument("--latency", type=float, default=0.05)
    ap.add_argument("--concurrency", type=int, default=8)
    args = ap.parse_args()
    srv = serve(args.latency)
    rates = {}
    for conc in (1, args.concurrency):
        cfg = OmegaConf.load(REPO / "conf/part_texts/openai.yaml")
        cfg.base_url = f"http://127.0.0.1:{srv.server_address[1]}/v1"
        cfg.concurrency = conc
        caps = [f"caption {conc} {i}" for i in range(args.captions)]
        with tempfile.TemporaryDirectory() as d:
            cache = PartTextCache(Path(d) / "c.sqlite")
            t0 = time.perf_counter()
            _, stats = fill_part_texts(caps, OpenAIBackend(cfg), cache, cfg, progress=False)
            dt = time.perf_counter() - t0
            cache.close()
        assert stats["calls"] == args.captions and stats["fallbacks"] == 0
        rates[conc] = args.captions / dt
        print(f"concurrency {conc:3d}: {rates[conc]:8.1f} captions/s ({dt:.2f} s)")
    print(f"ratio concurrency {args.concurrency} / 1: {rates[args.concurrency] / rates[1]:.2f}x")
    srv.shutdown()


if __name__ == "__main__":
    main()
