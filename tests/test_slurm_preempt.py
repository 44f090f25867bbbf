"""Preemption and requeue (``party.training.RequeueOnSignal``): SLURM's warning signal before a
job's time limit saves the rolling checkpoint at the next step, ends the MLflow run KILLED (tag
``party.preempted``) and requeues the job as the process exits; the requeued job resumes from that
checkpoint, its run linked to the preempted one.

The fast tests raise the signal in-process (``$SLURM_JOB_ID`` set, ``party.slurm.requeue`` faked);
the slow one preempts a ``party submit train_vqvae`` job on the cluster of
``scripts/slurm_local.sh`` (``scancel --signal=USR1``) and skips, with the reason, where none answers."""
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset

from party import lifecycle, slurm, training
from party.config import compose
from party.lifecycle import Preempted
from party.stage import stage
from party.training import AtomicCheckpoint, build_trainer, checkpoint_step

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


# --------------------------------------------------------------------------- no cluster needed

class Tiny(L.LightningModule):
    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.net = torch.nn.Linear(4, 1)

    def training_step(self, batch, batch_idx):
        x, y = batch
        return torch.nn.functional.mse_loss(self.net(x), y)

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=0.05)


def _loader() -> DataLoader:
    # identical samples: where an epoch restarts after a resume does not change the batches, so a
    # resumed run must end with exactly the weights of an uninterrupted one
    x = torch.randn(1, 4, generator=torch.Generator().manual_seed(0)).repeat(16, 1)
    return DataLoader(TensorDataset(x, torch.ones(16, 1)), batch_size=4)


class SignalAt(L.Callback):
    """Sends this process ``signum`` as the batch of ``step`` starts (what ``scancel --signal`` does)."""

    def __init__(self, step: int, signum: int = signal.SIGUSR1):
        self.step, self.signum = step, signum

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            os.kill(os.getpid(), self.signum)


def _probe(ckpt: Path, max_steps: int, callbacks=(), resume: Path | None = None, keep_ckpt: bool = True):
    """A stage (``party.stage``: its MLflow run) fitting ``Tiny``; returns its weights."""
    @stage("preempt_probe")
    def run(cfg, run_):
        lit = Tiny()
        cbs = [AtomicCheckpoint(ckpt, 0)] if keep_ckpt else []
        trainer = build_trainer(cfg, max_steps=max_steps, callbacks=[*cbs, *callbacks],
                                default_root_dir=str(ckpt.parent))
        trainer.fit(lit, _loader(), ckpt_path=str(resume) if resume else None, weights_only=True)
        return {"step": trainer.global_step, "w": {k: v.detach().clone() for k, v in lit.state_dict().items()}}
    return run


@pytest.fixture
def slurm_job(monkeypatch, tmp_path):
    """This process as SLURM job 4242 (no cluster: ``party.slurm.requeue`` records its calls), its
    signal handlers and the preemption state restored afterwards; a tiny config tracking into tmp_path."""
    for k in [k for k in os.environ if k.startswith("SLURM_")]:
        monkeypatch.delenv(k)
    monkeypatch.setenv("SLURM_JOB_ID", "4242")
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    requeued: list[str] = []
    monkeypatch.setattr(slurm, "requeue", requeued.append)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGUSR1, signal.SIGTERM)}
    cfg = compose(["trainer=cpu", "progress=false", f"tracking.dir={tmp_path / 'mlruns'}"], ROOT / "conf")
    yield cfg, requeued
    for s, h in handlers.items():
        signal.signal(s, h)
    training._RECEIVED.clear()
    lifecycle._REQUEUE.clear()


def _runs(tmp_path):
    import mlflow
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}")
    exps = [e.experiment_id for e in client.search_experiments()]
    return client.search_runs(exps, "tags.`party.stage` = 'preempt_probe'", order_by=["attributes.start_time ASC"])


def test_the_warning_signal_checkpoints_ends_the_run_killed_and_requeues_at_exit(slurm_job, tmp_path):
    cfg, requeued = slurm_job
    ckpt = tmp_path / "cut" / "last.ckpt"
    with pytest.raises(Preempted, match="SLURM job 4242: preempted at step 4") as e:
        _probe(ckpt, 10, [SignalAt(3)])(cfg)
    assert e.value.job_id == "4242" and e.value.step == 4 and e.value.checkpoint == ckpt
    assert checkpoint_step(ckpt) == 4                        # saved at the step the signal was acted on
    assert requeued == [] and lifecycle._REQUEUE == ["4242"]  # requeued at exit, after the run is closed
    assert signal.getsignal(signal.SIGUSR1) is training._note_signal      # a later warning is only noted
    (run,) = _runs(tmp_path)
    assert run.info.status == "KILLED" and run.data.tags["party.preempted"] == "4242"
    assert run.data.tags["party.error"].startswith("Preempted: SLURM job 4242: preempted at step 4")
    terminate = signal.getsignal(signal.SIGTERM)
    assert lifecycle.requeue_pending() == ["4242"] and requeued == ["4242"] and lifecycle._REQUEUE == []
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN and terminate is not signal.SIG_IGN

    # the requeued job: resumes from the checkpoint and ends with the uninterrupted run's weights
    resumed = _probe(tmp_path / "rest" / "last.ckpt", 10, resume=ckpt)(cfg)
    full = _probe(tmp_path / "full" / "last.ckpt", 10)(cfg)
    assert resumed["step"] == full["step"] == 10
    assert all(torch.equal(resumed["w"][k], full["w"][k]) for k in full["w"])
    assert [r.info.status for r in _runs(tmp_path)] == ["KILLED", "FINISHED", "FINISHED"]


@pytest.mark.parametrize("why", ["preemption.requeue=false", "no rolling checkpoint"])
def test_without_requeue_the_signal_is_logged_and_training_goes_on(slurm_job, tmp_path, caplog, why):
    cfg, requeued = slurm_job
    if why == "preemption.requeue=false":
        cfg.preemption.requeue = False
    out = _probe(tmp_path / "c" / "last.ckpt", 6, [SignalAt(2)], keep_ckpt=why != "no rolling checkpoint")(cfg)
    assert out["step"] == 6 and requeued == [] and lifecycle._REQUEUE == []
    assert re.search(r"SLURM job 4242: SIGUSR1 at step 3; not requeued \((preemption.requeue=false|"
                     r"this training keeps no rolling checkpoint)", caplog.text), caplog.text
    assert [r.info.status for r in _runs(tmp_path)] == ["FINISHED"]


def test_outside_slurm_nothing_is_installed(monkeypatch):
    for k in [k for k in os.environ if k.startswith("SLURM_")]:
        monkeypatch.delenv(k)
    cfg = compose(["trainer=cpu", "progress=false"], ROOT / "conf")
    t = build_trainer(cfg, max_steps=2)
    assert not any(type(c).__name__ == "RequeueOnSignal" for c in t.callbacks)
    with pytest.raises(ValueError, match="preemption.signal: 'NOPE' is not a signal name"):
        training.signal_number("NOPE")
    assert training.signal_number("USR1") == training.signal_number("SIGUSR1") == signal.SIGUSR1


# --------------------------------------------------------------------------- on a SLURM cluster

def _poll(what: str, fn, timeout: float, every: float = 0.5):
    t0 = time.time()
    while time.time() - t0 < timeout:
        got = fn()
        if got:
            return got
        time.sleep(every)
    raise TimeoutError(f"{what}: not within {timeout:.0f} s")


class Snapshot(L.Callback):
    """The module's weights after optimizer step ``step``."""

    def __init__(self, step: int):
        self.step, self.weights = step, None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.step:
            self.weights = {k: v.detach().clone() for k, v in pl_module.state_dict().items()}


def _weights(ckpt: Path) -> dict:
    return torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]


@pytest.mark.slow
def test_a_preempted_training_job_is_requeued_and_resumes(slurm_cluster, tmp_path, monkeypatch):
    """``party submit train_vqvae``, then ``scancel --signal=USR1`` mid-training: the job saves its
    rolling checkpoint, its run ends KILLED (``party.preempted``), SLURM restarts the same job, which
    resumes at that step and finishes, its run FINISHED and linked to the first. Against an
    uninterrupted run of the same config (in this process): the checkpoint equals its weights at that
    step; the final weights differ, within the bound docs/scaling.md states (the tokenizer's resume
    is not exact: batch order, crops and code resets restart their random streams after it)."""
    import mlflow

    from party.config import load_params, write_params
    from party.tokenizers.train import train_tokenizer
    from party.tokenizers.vqvae import load_tokenizer

    t_start = time.time()
    max_steps, every = 240, 20
    proj = tmp_path / "proj"
    proj.mkdir()
    (proj / "conf").symlink_to(ROOT / "conf")
    params = proj / "params.yaml"
    write_params(params, ["experiment=tiny", f"paths.prepared={tmp_path / 'prepared'}", f"tracking.dir={proj / 'mlruns'}",
                          "progress=false", "tracking.n_render_samples=0", f"vqvae.resume_dir={proj / 'resume'}",
                          f"vqvae.out_dir={proj / 'tok'}", "vqvae.stream=holistic", "vqvae.train.render_samples=0",
                          f"vqvae.train.max_steps={max_steps}", f"vqvae.train.ckpt_every={every}",
                          "vqvae.train.val_every=120"], ROOT / "conf")
    env = {k: v for k, v in slurm_cluster.items() if k not in ("MLFLOW_TRACKING_URI", "DVC_ROOT", "LOCAL_RANK")}
    env.update(PARTY_PARAMS=str(params), PARTY_NO_RENDER="1", OMP_NUM_THREADS="1")

    def run(*args, timeout=600):
        r = subprocess.run(args, cwd=proj, env=env, capture_output=True, text=True, timeout=timeout)
        assert r.returncode == 0, f"{' '.join(map(str, args))}: exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-4000:]}"
        return r.stdout

    run(str(BIN / "party"), "prepare")
    out = run(str(BIN / "party"), "submit", "train_vqvae", "--launcher", "slurm_local")
    job = re.search(r"train_vqvae: job (\d+)", out).group(1)
    logfile = proj / "logs" / "slurm" / f"party-train_vqvae-{job}.out"

    def state() -> str:
        return run("squeue", "-h", "-r", "-t", "all", "-o", "%T", "-j", job).strip()

    def log() -> str:
        return logfile.read_text() if logfile.exists() else ""

    try:
        # once the handler is installed and a rolling checkpoint is written: the warning
        _poll("the job's first rolling checkpoint", lambda: "SIGUSR1 saves the rolling checkpoint" in log()
              and list((proj / "resume").glob("holistic/*/last.ckpt")), 300)
        (ckpt,) = list((proj / "resume").glob("holistic/*/last.ckpt"))
        run("scancel", "--signal=USR1", job)
        t_signal = time.time()
        # requeued: pending again (Restarts=1); SLURM holds a requeued job back (its BeginTime: the
        # credential lifetime, 10 s on the local cluster, 2 min by default): copy the checkpoint now,
        # then let it start
        _poll("the job requeued", lambda: state() == "PENDING", 120)
        shutil.copy2(ckpt, tmp_path / "preempted.ckpt")
        run("scontrol", "update", f"JobId={job}", "StartTime=now")
        _poll("the requeued job's end", lambda: state() in ("COMPLETED", "FAILED", "CANCELLED", "TIMEOUT"), 600, 2)
    finally:
        if state() not in ("COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", ""):
            subprocess.run(["scancel", job], env=env, timeout=30)
    text = log()
    assert state() == "COMPLETED", text[-6000:]
    restarts = re.search(r"Restarts=(\d+)", run("scontrol", "show", "job", job)).group(1)
    cut = checkpoint_step(tmp_path / "preempted.ckpt")
    assert restarts == "1" and every <= cut < max_steps, (restarts, cut)
    assert f"SLURM job {job}: SIGUSR1 at step {cut}: saved" in text and f"requeued SLURM job {job}" in text, text[-6000:]
    assert f"resuming at step {cut} of {max_steps}" in text, text[-6000:]

    client = mlflow.MlflowClient(f"sqlite:///{proj / 'mlruns' / 'mlflow.db'}")
    exps = [e.experiment_id for e in client.search_experiments()]
    first, second = client.search_runs(exps, "tags.`party.stage` = 'train_vqvae'", order_by=["attributes.start_time ASC"])
    assert first.info.status == "KILLED" and first.data.tags["party.preempted"] == job
    assert first.data.tags["party.slurm_restarts"] == "0" and first.data.tags["party.resume_step"] == "0"
    assert second.info.status == "FINISHED" and second.data.tags["party.resumed_from"] == first.info.run_id
    assert second.data.tags["party.slurm_restarts"] == "1" and second.data.tags["party.resume_step"] == str(cut)
    assert second.data.tags["mlflow.parentRunId"] == first.info.run_id
    metrics = json.loads((proj / "tok" / "holistic" / "metrics.json").read_text())
    assert metrics["step"] == max_steps

    # the same config, uninterrupted, in this process
    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    cfg = load_params(params)
    cfg.vqvae.resume_dir, cfg.vqvae.out_dir = str(tmp_path / "ref_resume"), str(tmp_path / "ref_tok")
    snap, threads = Snapshot(cut), torch.get_num_threads()
    try:
        ref = train_tokenizer(cfg, "holistic", tmp_path / "ref_tok" / "holistic", callbacks=[snap])
    finally:
        torch.set_num_threads(threads)
    at_cut = _weights(tmp_path / "preempted.ckpt")
    assert all(torch.equal(at_cut[k], snap.weights[k]) for k in at_cut), "the first life is not the reference's"
    a, b = _weights(proj / "tok" / "holistic" / "last.ckpt"), _weights(tmp_path / "ref_tok" / "holistic" / "last.ckpt")
    assert set(a) == set(b)
    # the weights gradient descent trains, apart from the quantizer's buffers (EMA codebook, code
    # counts: a dead code is reset to a random encoder output, so the codebooks differ entirely)
    learned = [f"tok.model.{k}" for k, _ in load_tokenizer(proj / "tok" / "holistic").model.named_parameters()]
    flat = lambda w, keys: torch.cat([w[k].float().flatten() for k in keys])  # noqa: E731
    diff = max((a[k] - b[k]).abs().max().item() for k in learned)
    rel = ((flat(a, learned) - flat(b, learned)).norm() / (flat(b, learned) - flat(at_cut, learned)).norm()).item()
    code = (a["tok.model.quantizer.codebook"] - b["tok.model.quantizer.codebook"]).abs().max().item()
    mpjpe = abs(metrics["val/mpjpe_mm"] - ref["val/mpjpe_mm"]) / ref["val/mpjpe_mm"]
    print(f"\npreempted at step {cut} of {max_steps}, resumed there; {time.time() - t_signal:.0f} s from the signal to "
          f"the end. Final weights vs the uninterrupted run: learned max |dw| = {diff:.3g}, "
          f"|w_resumed - w_ref| / |w_ref - w_cut| = {rel:.3g}; codebook max |dw| = {code:.3g}; val MPJPE "
          f"{metrics['val/mpjpe_mm']:.2f} vs {ref['val/mpjpe_mm']:.2f} mm ({mpjpe:.2%}); test took "
          f"{time.time() - t_start:.0f} s")
    # the bound docs/scaling.md states: the continuations stay much closer to each other than the
    # distance trained after the cut, and the tokenizer's quality is the same
    assert rel < 0.5 and mpjpe < 0.02, (rel, mpjpe)
