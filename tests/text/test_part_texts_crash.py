"""A crash (SIGKILL) or Ctrl-C (SIGINT) mid-run loses at most the requests in flight and never
corrupts the cache; the rerun asks only for what is missing."""
from __future__ import annotations

import signal
import sqlite3
import subprocess
import sys
import time

import pytest
from omegaconf import OmegaConf

from party.stages import cache_part_texts
from text_helpers import REPO, openai_cfg, write_index

N = 120                                  # 9 s of slow requests: the signal lands mid-run on a loaded machine
CAPS = [[f"a person waves {i} times."] for i in range(N)]


def _rows(path) -> int:
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    n = db.execute("SELECT COUNT(*) FROM part_texts").fetchone()[0]
    db.close()
    return n


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_interrupted_run_keeps_a_valid_cache_and_resumes(tmp_path, fake_llm, sig):
    write_index(tmp_path, CAPS)
    llm = fake_llm(default="slow", slow_s=0.15)
    cfg = openai_cfg(tmp_path, llm, **{"part_texts.concurrency": 2, "part_texts.timeout_s": 5})
    cfg_path = tmp_path / "cfg.yaml"
    OmegaConf.save(cfg, cfg_path)
    # Ctrl-C raises KeyboardInterrupt in the child even where this test runs with SIGINT ignored (a
    # background job of a shell without job control: ignored dispositions are inherited)
    code = ("import signal; signal.signal(signal.SIGINT, signal.default_int_handler);"
            "import sys; from omegaconf import OmegaConf; from party.stages import cache_part_texts;"
            f"cache_part_texts.run(OmegaConf.load({str(cfg_path)!r}))")
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    deadline = time.time() + 60
    while llm.requests < 8 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    proc.send_signal(sig)
    t0 = time.time()
    _, err = proc.communicate(timeout=30)
    assert proc.returncode != 0
    if sig == signal.SIGINT:
        assert b"KeyboardInterrupt" in err
        assert time.time() - t0 < 5                  # stops promptly, does not drain the queue
    sent = llm.requests
    stored = _rows(cfg.part_texts.cache_path)
    assert 0 < stored < N
    assert stored >= sent - 2 - 1                    # lost at most the requests in flight (+1 racing)
    assert not (tmp_path / "part_texts" / "part_texts.json").exists()
    # rerun: only the missing captions are asked for
    llm.default = "good"
    stats = cache_part_texts.run(cfg)
    assert stats["hits"] == stored and stats["misses"] == N - stored
    assert llm.requests - sent == N - stored
    assert _rows(cfg.part_texts.cache_path) == N
