"""party.training: one trainer builder for every training stage, DDP from config."""
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from party.config import compose, write_params
from party.training import build_trainer, config_key, count_params, resume_checkpoint, trainer_kwargs

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
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    assert T.cpu_has_native_bf16() == any(f in flags.split() for f in ("avx512_bf16", "amx_bf16"))


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
