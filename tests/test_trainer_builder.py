"""party.training: one trainer builder for every training stage, DDP from config."""
import os
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from party.lifecycle import Busy
from party.config import compose, write_params
from party.training import (build_trainer, config_key, count_params, hold_resume_dir, resume_checkpoint,
                            trainer_kwargs)

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def test_trainer_builder_honours_trainer_keys_and_a_stage_section():
    cfg = compose(["trainer=cpu", "trainer.precision=bf16-mixed", "trainer.log_every_n_steps=3"], ROOT / "conf")
    kw = trainer_kwargs(cfg, {"precision": "32-true", "num_workers": 7})       # non-Trainer keys ignored
    assert kw == {"accelerator": "cpu", "devices": 1, "num_nodes": 1, "strategy": "auto", "precision": "32-true",
                  "deterministic": False, "log_every_n_steps": 3}
    t = build_trainer(cfg, max_steps=5, val_check_interval=2)
    assert t.max_steps == 5 and t.num_devices == 1 and t.log_every_n_steps == 3 and t.val_check_interval == 2
    assert "bf16" in str(t.precision) or "bf16" in type(t.strategy.precision_plugin).__name__.lower()


def test_precision_auto_is_bf16_only_where_the_cpu_has_it(monkeypatch):
    import party.training as T
    cfg = compose(["trainer=cpu", "trainer.precision=auto"], ROOT / "conf")
    for native, want in ((True, "bf16-mixed"), (False, "32-true")):
        monkeypatch.setattr(T, "cpu_has_native_bf16", lambda native=native: native)
        assert trainer_kwargs(cfg)["precision"] == want
        assert trainer_kwargs(cfg, {"precision": None})["precision"] == want          # null: inherit
        assert trainer_kwargs(cfg, {"precision": "32-true"})["precision"] == "32-true"  # a value wins
    monkeypatch.undo()
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    native = torch.backends.cpu.get_cpu_capability().startswith("AVX512") and \
        any(f in flags.split() for f in ("avx512_bf16", "amx_bf16"))
    assert T.cpu_has_native_bf16() == native
    for isa, keeps in (("AVX2", False), ("avx512_core", False), ("AVX512_CORE_BF16", True), ("ALL", True)):
        monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", isa)          # oneDNN capped below its bf16 instructions
        assert T.cpu_has_native_bf16() == (keeps and native), isa


def test_precision_auto_is_fp32_when_timed_as_an_avx2_only_cpu():
    """docs/performance.md: the two variables alone make a stage run as an AVX2-only CPU runs it,
    fp32 included (bf16 under the capped ISA is ~14x slower than fp32, not the user's case)."""
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"}
    out = subprocess.run([sys.executable, "-c", "import torch; from party.training import resolve_precision as r; "
                          "print(torch.backends.cpu.get_cpu_capability(), r('auto', 'cpu'))"],
                         env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out == ["AVX2", "32-true"], out


def test_config_key_and_resume_checkpoint(tmp_path):
    assert config_key({"lr": 1}, {"index": "a"}) == config_key({"lr": 1.0}, {"index": "a"})   # 1 and 1.0 alike
    assert config_key({"lr": 1}, {"index": "a"}) != config_key({"lr": 1}, {"index": "b"})     # data identity counts
    assert resume_checkpoint(tmp_path, True) is None
    torch.save({"w": torch.arange(5000.0)}, tmp_path / "last.ckpt")
    assert resume_checkpoint(tmp_path, True) == tmp_path / "last.ckpt" and resume_checkpoint(tmp_path, False) is None
    data = (tmp_path / "last.ckpt").read_bytes()
    for damaged in (data[: len(data) // 2], data[:2000] + b"\0" * 1000 + data[3000:]):   # truncated, overwritten
        (tmp_path / "last.ckpt").write_bytes(damaged)
        with pytest.raises(ValueError, match=r"last.ckpt: the rolling checkpoint .* truncated or damaged .*"
                           r"delete it .* or set vqvae.train.resume=false"):
            resume_checkpoint(tmp_path, True, "vqvae.train.resume")
        assert resume_checkpoint(tmp_path, False) is None                      # resume off: not read
    assert count_params(torch.nn.Linear(3, 2)) == 8


RANK_VARS = ("RANK", "SLURM_PROCID", "NODE_RANK", "LOCAL_RANK")
REFUSED = "a training run with the same settings \\(the same resume key\\) is running there"


def test_a_second_run_with_the_same_key_is_refused_while_the_first_trains(tmp_path, monkeypatch):
    for var in RANK_VARS:
        monkeypatch.delenv(var, raising=False)
    folder = tmp_path / "generator" / "party" / "abc"
    with hold_resume_dir(folder):
        with pytest.raises(Busy, match=re.escape(str(folder)) + f": {REFUSED} \\(pid {os.getpid()} on "):
            with hold_resume_dir(folder):
                pass
        with hold_resume_dir(folder.parent / "other"):      # another key trains alongside
            pass
        monkeypatch.setenv("LOCAL_RANK", "1")              # a DDP child re-entering the stage claims nothing
        with hold_resume_dir(folder):
            pass
        monkeypatch.delenv("LOCAL_RANK")
    with pytest.raises(ZeroDivisionError):                # released after the run, and after an error
        with hold_resume_dir(folder):
            1 / 0
    with hold_resume_dir(folder):
        pass


def test_a_filesystem_without_locks_trains_unguarded(tmp_path, monkeypatch, caplog):
    import fcntl

    def no_locks(*a):
        raise OSError(37, "No locks available")
    monkeypatch.setattr(fcntl, "flock", no_locks)
    for var in RANK_VARS:
        monkeypatch.delenv(var, raising=False)
    with hold_resume_dir(tmp_path) as folder:
        assert folder == tmp_path
    assert "cannot lock the resume folder" in caplog.text and "No locks available" in caplog.text


def test_a_killed_run_leaves_its_folder_free(tmp_path, monkeypatch):
    for var in RANK_VARS:
        monkeypatch.delenv(var, raising=False)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from party.training import hold_resume_dir\n"
         f"with hold_resume_dir({str(tmp_path)!r}):\n    print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True, env={k: v for k, v in os.environ.items() if k not in RANK_VARS})
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RuntimeError, match=f"{REFUSED} \\(pid {holder.pid} on "):
            with hold_resume_dir(tmp_path):
                pass
    finally:
        holder.kill()                                      # SIGKILL: no cleanup code runs
        holder.wait()
    with hold_resume_dir(tmp_path):                       # the OS released the lock
        pass


@pytest.mark.slow
def test_train_evaluator_runs_under_ddp_on_two_cpu_processes(tmp_path):
    """The shared builder with trainer.devices=2 trainer.strategy=ddp (gloo) trains two steps;
    only rank zero writes the outputs and the MLflow run."""
    params = tmp_path / "params.yaml"
    write_params(params, ["experiment=tiny", f"paths.prepared={tmp_path / 'prepared'}",
                          f"tracking.dir={tmp_path / 'mlruns'}", f"evaluator.out_dir={tmp_path / 'ev'}",
                          "progress=false", "tracking.n_render_samples=0"], ROOT / "conf")
    env = os.environ | {"PARTY_PARAMS": str(params), "PARTY_NO_RENDER": "1"}
    env.pop("LOCAL_RANK", None)

    def party(*args):
        res = subprocess.run([str(BIN / "party"), *args], cwd=tmp_path, env=env, capture_output=True, text=True,
                             timeout=900)
        assert res.returncode == 0, res.stderr[-4000:]
        return res

    party("prepare")
    res = party("train_evaluator", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.strategy=ddp",
                "evaluator.train.max_steps=2", "evaluator.movement_pretrain.max_steps=2")
    assert "Starting with 2 processes" in res.stdout + res.stderr
    out = tmp_path / "ev" / "holistic"
    assert (out / "finest.tar").exists() and (out / "metrics.json").exists()
    assert not list((tmp_path / "ev").glob(".*tmp*"))
    with sqlite3.connect(tmp_path / "mlruns" / "mlflow.db") as con:
        runs = con.execute("select r.status from runs r join tags t on t.run_uuid = r.run_uuid "
                           "where t.key = 'party.stage' and t.value = 'train_evaluator'").fetchall()
    assert runs == [("FINISHED",)]
