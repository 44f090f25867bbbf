"""What every training stage shares: one trainer builder, one resume mechanism,
one parameter counter, one file hasher, one device resolver.

    trainer = build_trainer(cfg, max_steps=..., logger=lightning_logger(cfg, run),
                            callbacks=[AtomicCheckpoint(ckpt, every)])

``build_trainer`` honours ``trainer.*`` (accelerator, devices, num_nodes, strategy,
precision, deterministic, log_every_n_steps) and the progress flag, so every training
stage runs single-device, DDP on N devices or N nodes from config alone. A stage with
its own ``<group>.trainer`` section (e.g. ``evaluator.trainer.precision``) passes it
as ``section``: its keys win over ``trainer.*``.

Resume: ``resume_dir(root, name, key)`` is a folder outside DVC outputs (DVC deletes
outputs before it runs a stage) named by ``config_key(config, identity)``, a hash of
everything that changes what a step computes plus the data's identity
(``data_identity``: the index and normalisation files), so a killed run rerun with the
same settings continues from ``last.ckpt`` there and a changed dataset never resumes
an old run. ``hold_resume_dir(folder)`` keeps a second run with the same key (a sweep and a
``party repro`` started side by side) out of that folder while the first trains there.

Budgets (``max_steps``, not in the key) are what they say (``plan_resume``): a larger
``max_steps`` continues the folder's ``last.ckpt``; a checkpoint trained past ``max_steps`` is
never reused as the shorter run. That run starts from the furthest checkpoint at or below its
budget (a shorter budget's ``steps-<N>/last.ckpt``, kept beside), else from scratch, and
checkpoints to ``steps-<max_steps>/last.ckpt``, so the longer run's ``last.ckpt`` is kept. The
export records the steps trained (``steps_trained``).

Preemption (SLURM): in a SLURM job (``$SLURM_JOB_ID``) ``build_trainer`` turns Lightning's own
auto-requeue off and adds ``RequeueOnSignal``: the scheduler's warning signal
(``preemption.signal``, ``--signal=USR1@<s>`` or ``scancel --signal=USR1``) saves the rolling
checkpoint at the next step and raises ``party.lifecycle.Preempted`` (the run ends KILLED, tag
``party.preempted``); rank zero requeues the job when its process exits, after the run is closed.
The requeued job resumes from that checkpoint like any rerun (docs/scaling.md).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Mapping

import torch

from party.slurm import current_job

log = logging.getLogger(__name__)

# trainer.* keys passed to lightning.Trainer
TRAINER_KEYS = ("accelerator", "devices", "num_nodes", "strategy", "precision", "deterministic",
                "log_every_n_steps")


# --------------------------------------------------------------------------- small shared pieces

def adam(params, *, decoupled: bool = False, **kw) -> torch.optim.Optimizer:
    """Adam (``decoupled``: AdamW) with the fused kernel: one pass over every parameter instead of
    PyTorch's per-tensor loop on CPU (bench/bench_optimizer.py). Same update rule and state."""
    cls = torch.optim.AdamW if decoupled else torch.optim.Adam
    return cls(params, fused=True, **kw)


def step_lr_factor(step: int, optim: Mapping) -> float:
    """The two-stage schedule every training stage uses, as a ``LambdaLR`` factor: 1 until
    ``optim["milestone"]`` iterations, then ``optim["lr_after"] / optim["lr"]``."""
    return 1.0 if step < int(optim["milestone"]) else float(optim["lr_after"]) / float(optim["lr"])


def count_params(module: torch.nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters of ``module`` (only those with ``requires_grad`` if asked)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)


def file_sha(path: str | os.PathLike, n: int = 16) -> str:
    """Short sha256 of a file's bytes (identity of data files)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:n]


def resolve_device(name: str | None) -> torch.device:
    """``auto``/``gpu``/``cuda``: CUDA when available (a warning when asked for and absent),
    else the CPU; any other name is passed to ``torch.device``."""
    if name in (None, "auto", "gpu", "cuda"):
        if torch.cuda.is_available():
            return torch.device("cuda")
        if name in ("gpu", "cuda"):
            log.warning("accelerator %s requested but CUDA is not available; using the CPU", name)
        return torch.device("cpu")
    return torch.device(name)


# --------------------------------------------------------------------------- trainer

#: oneDNN ISA caps (``ONEDNN_MAX_CPU_ISA``) that keep its bf16 instructions (AVX512-BF16, AMX, AVX10)
_ONEDNN_BF16_ISAS = ("ALL", "AVX512_CORE_BF16", "AVX512_CORE_FP16", "AVX512_CORE_AMX", "AVX512_CORE_AMX_FP16",
                     "AVX10_1_512", "AVX10_1_512_AMX", "AVX10_1_512_AMX_FP16", "AVX10_2_512", "AVX10_2_512_AMX_2")


def cpu_has_native_bf16() -> bool:
    """Whether bf16 runs natively here: this CPU has AVX512-BF16 or AMX-BF16 (/proc/cpuinfo's
    flags; False where that file does not exist) and the kernels may use them: ATen's CPU
    capability is AVX-512 (``ATEN_CPU_CAPABILITY`` may cap it) and ``ONEDNN_MAX_CPU_ISA``, if set,
    allows oneDNN's bf16 instructions. Without them oneDNN emulates bf16, no faster than fp32
    (AVX-512 without BF16) or far slower: a tokenizer training step under
    ``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2`` (how docs/performance.md times a stage as
    an AVX2-only CPU) takes 5.3 s in bf16-mixed against 0.39 s in fp32."""
    isa = os.environ.get("ONEDNN_MAX_CPU_ISA", "").strip().upper()
    if isa and isa not in _ONEDNN_BF16_ISAS:
        return False
    if not torch.backends.cpu.get_cpu_capability().upper().startswith("AVX512"):
        return False
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    flags = set()
    for line in text.splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[1].split())
            break
    return bool(flags & {"avx512_bf16", "amx_bf16"})


def resolve_precision(precision: str, accelerator: str) -> str:
    """Lightning's ``precision`` for ``trainer.precision`` (or a section's): any Lightning value
    is returned as is; ``auto`` is ``bf16-mixed`` where the device that will train computes bf16
    natively (a CUDA GPU that supports it; a CPU with AVX512-BF16 or AMX), else ``32-true``.
    bf16-mixed autocasts matmuls and convolutions; parameters, optimiser state and whatever a
    module keeps out of autocast (the tokenizers' quantizer) stay fp32."""
    if precision != "auto":
        return precision
    cuda = accelerator in ("auto", "gpu", "cuda") and torch.cuda.is_available()
    if cuda:
        return "bf16-mixed" if torch.cuda.is_bf16_supported() else "32-true"
    return "bf16-mixed" if cpu_has_native_bf16() else "32-true"


def precision_identity(precision: str) -> dict[str, str]:
    """What a resume key adds for a resolved ``precision``: a bf16 step differs from an fp32 one,
    so anything but ``32-true`` is part of the key; ``32-true`` adds nothing, so keys written
    before precision was a switch still match."""
    return {} if precision == "32-true" else {"precision": precision}


#: the file a stage started by ``party repro`` adds what it ran with to (``note_stage``)
STAGE_INFO_ENV = "PARTY_STAGE_INFO"


def note_stage(**info: str) -> None:
    """Tell ``party repro`` what this stage ran with (``precision=...``): each value is added to the
    list under its key in the JSON file ``$PARTY_STAGE_INFO`` names, which ``party repro`` sets for
    every stage it starts and reads into ``logs/repro/summary.json`` when the stage ends. Nothing
    happens without the variable (a stage run by hand, or by ``dvc repro``)."""
    path = os.environ.get(STAGE_INFO_ENV)
    if not path:
        return
    f = Path(path)
    try:
        cur = json.loads(f.read_text()) if f.exists() else {}
    except (OSError, ValueError):
        cur = {}
    for k, v in info.items():
        cur.setdefault(k, [])
        if v not in cur[k]:
            cur[k].append(v)
    tmp = f.with_name(f.name + ".tmp")
    tmp.write_text(json.dumps(cur))
    os.replace(tmp, f)


def trainer_kwargs(cfg, section: Mapping | None = None) -> dict[str, Any]:
    """``lightning.Trainer`` keyword arguments from ``trainer.*``, ``section`` winning (a
    section key set to null inherits ``trainer.*``); ``precision: auto`` resolved
    (``resolve_precision``)."""
    from party.config import plain

    t = plain(cfg.trainer)
    for k, v in dict(plain(section) or {}).items():
        if k in TRAINER_KEYS and v is not None:
            t[k] = v
    t["precision"] = resolve_precision(str(t["precision"]), str(t["accelerator"]))
    note_stage(precision=t["precision"])
    return {k: t[k] for k in TRAINER_KEYS}


def build_trainer(cfg, *, max_steps: int, logger=False, callbacks: Iterable = (),
                  section: Mapping | None = None, **kw):
    """The ``lightning.Trainer`` of every training stage (see the module docstring).

    ``kw``: stage-specific Trainer arguments (validation cadence, gradient clipping,
    ``default_root_dir``, ...). Lightning's own checkpointing and model summary are off:
    stages checkpoint with ``AtomicCheckpoint`` and export their outputs themselves. In a SLURM
    job, Lightning's auto-requeue is off and ``RequeueOnSignal`` handles ``preemption.signal``
    (``preemption.requeue``; see the module docstring)."""
    import lightning as L

    callbacks = list(callbacks)
    if cfg.progress and int(max_steps) > 0:
        callbacks.append(_step_progress_bar_cls()())
    if in_slurm_job():
        kw = {**kw, "plugins": _slurm_plugins(kw.get("plugins"))}
        # last: it acts after the rolling checkpoint's own batch-end save
        callbacks.append(__getattr__("RequeueOnSignal")(str(cfg.preemption.signal),
                                                        bool(cfg.preemption.requeue)))
    args = dict(max_steps=int(max_steps), logger=logger or False, callbacks=callbacks,
                enable_checkpointing=False, enable_model_summary=False, num_sanity_val_steps=0,
                enable_progress_bar=bool(cfg.progress), **trainer_kwargs(cfg, section))
    args.update(kw)
    return L.Trainer(**args)


def _step_progress_bar_cls():
    from lightning.pytorch.callbacks import TQDMProgressBar
    from lightning.pytorch.callbacks.progress.tqdm_progress import _update_n

    class StepProgressBar(TQDMProgressBar):
        """The training bar counts optimizer steps up to ``max_steps`` (every stage trains for a
        number of steps; Lightning's bar counts batches of an epoch, ``Epoch 1/-2``)."""

        def on_train_epoch_start(self, trainer, *_):
            bar = self.train_progress_bar
            if bar.total != trainer.max_steps:
                bar.reset(total=trainer.max_steps)
                _update_n(bar, trainer.global_step)
            bar.set_description(f"step (epoch {trainer.current_epoch})")

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            n = trainer.global_step
            if self._should_update(n, self.train_progress_bar.total):
                _update_n(self.train_progress_bar, n)
                self.train_progress_bar.set_postfix(self.get_metrics(trainer, pl_module))

        def on_train_epoch_end(self, trainer, pl_module):
            if not self.train_progress_bar.disable:
                self.train_progress_bar.set_postfix(self.get_metrics(trainer, pl_module))

    return StepProgressBar


def _atomic_checkpoint_cls():
    from lightning.pytorch.callbacks import Callback

    class AtomicCheckpoint(Callback):
        """Save ``path`` every ``every`` iterations and at the end, via a unique temp name,
        fsync and rename."""

        def __init__(self, path: Path, every: int):
            self.path, self.every = Path(path), int(every)
            self.saved_step: int | None = None      # the global step of the last save

        def _save(self, trainer) -> None:
            from party.io import replace_durably, temp_beside
            # rank 0 makes the temp (O_EXCL: never a planted file or link); every rank names it
            tmp = temp_beside(self.path) if trainer.is_global_zero else None
            tmp = Path(trainer.strategy.broadcast(str(tmp) if tmp else None, src=0))
            try:
                trainer.save_checkpoint(tmp, weights_only=False)   # the full state: a resume continues exactly
                if trainer.is_global_zero:
                    replace_durably(tmp, self.path)
            finally:
                if trainer.is_global_zero and os.path.lexists(tmp):
                    tmp.unlink()
            self.saved_step = int(trainer.global_step)

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            if self.every > 0 and trainer.global_step % self.every == 0:
                self._save(trainer)

        def on_train_end(self, trainer, pl_module) -> None:
            self._save(trainer)

    AtomicCheckpoint.__qualname__ = "AtomicCheckpoint"
    return AtomicCheckpoint


# --------------------------------------------------------------------------- preemption (SLURM)

def in_slurm_job() -> bool:
    """Whether this process runs in a SLURM job (``$SLURM_JOB_ID``)."""
    return bool(os.environ.get("SLURM_JOB_ID"))


def _slurm_plugins(plugins) -> list:
    """``plugins`` plus Lightning's SLURM environment with its auto-requeue off (when Lightning
    detects SLURM and none is given): ``RequeueOnSignal`` alone acts on the warning signal."""
    from lightning.pytorch.plugins.environments import SLURMEnvironment

    plugins = list(plugins or []) if isinstance(plugins, (list, tuple)) or plugins is None else [plugins]
    if SLURMEnvironment.detect() and not any(isinstance(p, SLURMEnvironment) for p in plugins):
        plugins.append(SLURMEnvironment(auto_requeue=False))
    return plugins


def signal_number(name: str) -> int:
    """``USR1`` / ``SIGUSR1`` -> its number; ValueError naming ``preemption.signal`` otherwise."""
    import signal
    sig = str(name).upper()
    sig = sig if sig.startswith("SIG") else f"SIG{sig}"
    try:
        return int(signal.Signals[sig])
    except KeyError:
        raise ValueError(f"preemption.signal: {name!r} is not a signal name (USR1, USR2)") from None


#: warning signals received and not acted on yet (``_note_signal``; a list: appending is all a handler does)
_RECEIVED: list[int] = []


def _note_signal(signum, frame) -> None:
    _RECEIVED.append(signum)


def _wait_for_requeue(job: str, poll_s: float = 2.0) -> None:
    """Block (a DDP rank other than zero) while SLURM lists ``job`` as RUNNING: rank zero requeues it
    once it has closed its MLflow run, and SLURM then ends every rank. Exiting earlier would end
    the step (``srun --kill-on-bad-exit``) and kill rank zero before its run is closed. The SIGTERM
    of the requeue ends this process at once (its default: this rank has nothing to close;
    Lightning's handler would wait on a collective of rank zero, which is gone)."""
    import signal
    import time

    from party import slurm
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    while True:
        try:
            if slurm.job_states([job]).get(str(job), "RUNNING") != "RUNNING":
                return
        except slurm.SlurmError as e:       # squeue unreachable: the requeue's SIGTERM still ends this rank
            log.warning("waiting for rank zero to requeue job %s: %s", job, e)
        time.sleep(poll_s)


def _requeue_on_signal_cls():
    import signal
    import threading

    from lightning.pytorch.callbacks import Callback

    class RequeueOnSignal(Callback):
        """SLURM's warning before the time limit (``signame``) ends the training at the next step:
        the rolling checkpoint (the ``AtomicCheckpoint`` among the trainer's callbacks) is saved
        there, and ``Preempted`` is raised, so the stage ends its MLflow run KILLED (tag
        ``party.preempted`` = the job); rank zero requeues the job as its process exits
        (``party.lifecycle.requeue_at_exit``), and the requeued job resumes from that checkpoint.

        The handler (installed when ``fit`` sets up, main thread) only records the signal; the
        decision is taken at a batch end, after the rolling checkpoint's own save, and under DDP
        agreed by all ranks (any rank that received it). Without a rolling checkpoint, or with
        ``requeue=False`` (``preemption.requeue``), the signal is logged and ignored: the
        training goes on until SLURM ends the job (SIGTERM: the run ends KILLED). The handler stays
        after ``fit`` (a warning during the export is noted, not fatal: a signal's default would end
        the process)."""

        def __init__(self, signame: str, requeue: bool):
            self.signame, self.signum, self.requeue = str(signame), signal_number(signame), bool(requeue)

        def setup(self, trainer, pl_module, stage: str) -> None:
            if stage != "fit":
                return
            if threading.current_thread() is not threading.main_thread():
                log.warning("not in the main thread: SIG%s (SLURM's warning) is not handled", self.signame)
                return
            if signal.getsignal(self.signum) is not _note_signal:
                signal.signal(self.signum, _note_signal)
            if trainer.is_global_zero:
                log.info("SLURM job %s: SIG%s %s", current_job(), self.signame,
                         "saves the rolling checkpoint and requeues the job" if self.requeue
                         else "is ignored (preemption.requeue=false)")

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            got = bool(_RECEIVED)
            if trainer.world_size > 1:
                got = bool(trainer.strategy.reduce_boolean_decision(got, all=False))
            if got:
                _RECEIVED.clear()
                self._preempt(trainer)

        def teardown(self, trainer, pl_module, stage: str) -> None:
            if stage == "fit" and _RECEIVED and trainer.is_global_zero:
                log.warning("SIG%s arrived after the training loop: not requeued; the stage goes on (SLURM "
                            "ends the job at its time limit)", self.signame)
            _RECEIVED.clear()

        def _preempt(self, trainer) -> None:
            from party.lifecycle import Preempted, requeue_at_exit
            job, step = current_job(), int(trainer.global_step)
            ckpt = next((c for c in trainer.callbacks if isinstance(c, __getattr__("AtomicCheckpoint"))), None)
            if not self.requeue or ckpt is None:
                if trainer.is_global_zero:
                    log.warning("SLURM job %s: SIG%s at step %d; not requeued (%s): training goes on until "
                                "SLURM ends the job", job, self.signame, step,
                                "preemption.requeue=false" if not self.requeue
                                else "this training keeps no rolling checkpoint to resume from")
                return
            if ckpt.saved_step != step:
                ckpt._save(trainer)
            trainer.strategy.barrier("party.preempted")        # the checkpoint is in place on every rank
            if trainer.is_global_zero:
                log.warning("SLURM job %s: SIG%s at step %d: saved %s; ending the run, then requeueing the "
                            "job", job, self.signame, step, ckpt.path)
                requeue_at_exit(job)
            else:
                _wait_for_requeue(job)
            raise Preempted(job, step, ckpt.path)

    RequeueOnSignal.__qualname__ = "RequeueOnSignal"
    return RequeueOnSignal


def __getattr__(name: str):
    # the callbacks (``AtomicCheckpoint``, ``RequeueOnSignal``) are built on first use: importing
    # lightning is slow and most users of this module (parameter counts, hashes) do not need it
    if name in _LAZY:
        if name not in globals():
            globals()[name] = _LAZY[name]()
        return globals()[name]
    raise AttributeError(name)


# classes built on first use (``__getattr__``)
_LAZY = {"AtomicCheckpoint": _atomic_checkpoint_cls, "RequeueOnSignal": _requeue_on_signal_cls}


# --------------------------------------------------------------------------- resume

def _numbers_as_floats(x):
    """``0`` and ``0.0`` (a command-line ``key=0`` against a config's ``0.0``) hash alike."""
    if isinstance(x, Mapping):
        return {k: _numbers_as_floats(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_numbers_as_floats(v) for v in x]
    return float(x) if isinstance(x, int) and not isinstance(x, bool) else x


def config_key(config: Mapping[str, Any], identity: Mapping[str, Any] = ()) -> str:
    """Short hash of everything that makes two training runs the same run: the settings
    that change what a step computes (``config``) and what it reads (``identity``)."""
    blob = json.dumps(_numbers_as_floats({**config, **dict(identity)}), sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def data_identity(index_path: str | os.PathLike, root: str | os.PathLike,
                  files: tuple[str, ...] = ("Mean.npy", "Std.npy")) -> dict[str, Any]:
    """The data's identity: the clip list (index file) and the normalisation statistics
    (regenerated features with the same clip names must not resume an old run)."""
    return {"index": file_sha(index_path), "norm": [file_sha(Path(root) / f) for f in files]}


def resume_dir(root: str | os.PathLike, name: str, key: str) -> Path:
    """``<root>/<name>/<key>``: where a run with that key checkpoints (``last.ckpt``)."""
    return Path(root) / name / key


def _launch_rank() -> int:
    """The process's rank as its launcher set it (torchrun, SLURM, Lightning's DDP children), 0
    when none did: a DDP run's other ranks re-enter the stage and must not claim the folder."""
    for var in ("RANK", "SLURM_PROCID", "NODE_RANK", "LOCAL_RANK"):
        if os.environ.get(var, "0") != "0":
            return int(os.environ[var])
    return 0


@contextmanager
def hold_resume_dir(folder: str | os.PathLike):
    """Hold ``folder/.lock`` while a run trains in ``folder`` (rank 0 only).

    Two runs with the same resume key would write the same ``last.ckpt``: the second would resume
    from the first's checkpoint mid-run, and each would copy whichever ``last.ckpt`` was written
    last into its output. The lock is an advisory ``flock``: the OS releases it when the process
    ends, killed or not, so a crashed run never leaves the folder locked. A second run raises
    ``party.lifecycle.Busy`` naming the folder and the process holding it, before it reads anything
    there."""
    folder = Path(folder)
    if _launch_rank() != 0:
        yield folder
        return
    import fcntl

    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / ".lock"
    with open(lock, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            locked = True
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            from party.lifecycle import Busy
            raise Busy(f"{folder}: a training run with the same settings (the same resume key) is "
                               f"running there ({holder}); both would write its last.ckpt. Wait for it to "
                               "finish (this run then resumes or reuses its result), or change a setting "
                               "such as the seed") from None
        except OSError as e:        # a filesystem without locks (some NFS mounts): train unguarded
            log.warning("%s: cannot lock the resume folder (%s); not guarding against a second run "
                        "with the same settings", folder, e)
            locked = False
        if not locked:
            yield folder
            return
        try:
            f.seek(0)
            f.truncate()
            f.write(f"pid {os.getpid()} on {os.uname().nodename}\n")
            f.flush()
            yield folder
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _checked(ckpt: Path, key: str) -> Path:
    """``ckpt``, checked (a torch checkpoint is a zip: its directory and every member's CRC): a
    truncated or damaged one raises ValueError naming the file and the two ways out (delete it,
    or ``<key>=false``), instead of torch's bare ``PytorchStreamReader failed``."""
    import zipfile
    try:
        with zipfile.ZipFile(ckpt) as z:
            bad = z.testzip()
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        bad = f"{type(e).__name__}: {e}"
    if bad is not None:
        raise ValueError(f"{ckpt}: the rolling checkpoint to resume from is truncated or damaged "
                         f"({bad}); delete it to start this training over, or set {key}=false")
    return ckpt


def checkpoint_step(ckpt: str | os.PathLike) -> int:
    """The optimizer step a Lightning checkpoint was saved at (its ``global_step``; 0 if none)."""
    obj = torch.load(ckpt, map_location="cpu", weights_only=True, mmap=True)
    return int(obj.get("global_step", 0)) if isinstance(obj, Mapping) else 0


class ResumePlan:
    """Where a run resumes from and where it checkpoints (``plan_resume``).

    ``resume_from``: the checkpoint to continue (None: from scratch), saved at ``resume_step``;
    ``ckpt``: this run's rolling checkpoint; ``past``: the checkpoints trained past the budget
    (path -> step), not reused."""

    def __init__(self, resume_from: Path | None, resume_step: int, ckpt: Path, past: Mapping[Path, int] = ()):
        self.resume_from, self.resume_step, self.ckpt, self.past = resume_from, int(resume_step), ckpt, dict(past)


def plan_resume(folder: str | os.PathLike, enabled: bool, key: str = "<group>.train.resume",
                max_steps: int | None = None) -> ResumePlan:
    """Which checkpoint of ``folder`` a run with budget ``max_steps`` resumes from, and where it
    checkpoints.

    Resuming off: from scratch into ``folder/last.ckpt``. Without ``max_steps``: ``last.ckpt``
    when it exists. With it, the candidates are ``last.ckpt`` and the kept shorter budgets'
    ``steps-<N>/last.ckpt``: the run resumes from the furthest one saved at or below
    ``max_steps`` (a larger budget continues a finished run) and never from one trained past it
    (it would export a longer run under a shorter budget); the run checkpoints to ``last.ckpt``
    unless that one is past the budget, then to ``steps-<max_steps>/last.ckpt`` (the longer run
    stays resumable). A damaged candidate raises ValueError (``_checked``)."""
    folder = Path(folder)
    last = folder / "last.ckpt"
    if not enabled:
        return ResumePlan(None, 0, last)
    if max_steps is None:
        return ResumePlan(_checked(last, key) if last.exists() else None, 0, last)
    cands = [c for c in (last, *sorted(folder.glob("steps-*/last.ckpt"))) if c.exists()]
    steps = {c: checkpoint_step(_checked(c, key)) for c in cands}
    fits = {c: s for c, s in steps.items() if s <= int(max_steps)}
    past = {c: s for c, s in steps.items() if s > int(max_steps)}
    start = max(fits, key=fits.get) if fits else None
    ckpt = last if last not in past else folder / f"steps-{int(max_steps)}" / "last.ckpt"
    return ResumePlan(start, fits.get(start, 0), ckpt, past)


def resume_checkpoint(folder: Path, enabled: bool, key: str = "<group>.train.resume",
                      max_steps: int | None = None) -> Path | None:
    """The checkpoint to resume from (``plan_resume``): ``folder/last.ckpt`` when resuming is on
    and it exists (with ``max_steps``: never one trained past it), else None. A truncated or
    damaged checkpoint raises ValueError naming the file and the two ways out (delete it, or
    ``<key>=false``)."""
    return plan_resume(folder, enabled, key, max_steps).resume_from


# --------------------------------------------------------------------------- the recipe

def start_training(seed: int, threads: int | None = None) -> None:
    """What every training does first: the thread count (None: torch's default), then every
    random stream seeded (``lightning.seed_everything``, workers too)."""
    import lightning as L
    if threads:
        torch.set_num_threads(int(threads))
    L.seed_everything(int(seed), workers=True, verbose=False)


class TrainingSession:
    """The bookkeeping of one resumable training around its ``trainer.fit``:

        with TrainingSession(run, root, name, key, resume=t.resume, flag="generator.train.resume",
                             tags={"party.method": name}, max_steps=t.max_steps) as s:
            trainer = build_trainer(..., callbacks=[AtomicCheckpoint(s.ckpt, every)], default_root_dir=str(s.dir))
            trainer.fit(lit, train, val, ckpt_path=s.resume_from, weights_only=True)
            s.export(out_dir, write, ["model.pt", "metrics.json"], "generator", log_checkpoint=True)

    Entering holds ``<root>/<name>/<key>/.lock`` (``hold_resume_dir``), finds the checkpoint to
    resume from and the one to write (``plan_resume``: with ``max_steps``, never a checkpoint
    trained past the budget; which one is logged), tags the run (``party.resume_key``,
    ``party.resumed``, ``party.resume_step``, in a SLURM job ``party.slurm_job_id`` and
    ``party.slurm_restarts``, and ``tags``) and links a resumed run to its earlier ones (a job
    requeued after preemption continues this way). ``export`` builds ``out_dir`` under a temp name (the rolling checkpoint as
    ``last.ckpt`` and what ``write(tmp)`` writes), swaps it in whole and logs the files named to
    the run."""

    def __init__(self, run, root, name: str, key: str, resume: bool, flag: str, tags: Mapping[str, Any] = (),
                 max_steps: int | None = None):
        self.run, self.key, self.flag, self.enabled = run, key, flag, bool(resume)
        self.max_steps = None if max_steps is None else int(max_steps)
        self.dir = resume_dir(root, name, key)
        self.ckpt = self.dir / "last.ckpt"
        self.tags = dict(tags)
        self.resume_from: Path | None = None
        self.resume_step = 0
        self._hold = None

    def _plan(self) -> None:
        plan = plan_resume(self.dir, self.enabled, self.flag, self.max_steps)
        self.resume_from, self.resume_step, self.ckpt = plan.resume_from, plan.resume_step, plan.ckpt
        if plan.past:
            budget = f"{self.flag.rsplit('.', 1)[0]}.max_steps={self.max_steps}"
            start = (f"continuing the {self.resume_step}-step checkpoint {self.resume_from}"
                     if self.resume_from is not None else "training from scratch")
            past = ", ".join(f"{c} (trained {s} steps)" for c, s in plan.past.items())
            log.warning("%s: past %s, not reused as this shorter run: %s, checkpointing to %s (the longer "
                        "checkpoint is kept)", past, budget, start, self.ckpt)
        elif self.resume_from is not None:
            log.info("%s: resuming at step %d of %s", self.resume_from, self.resume_step,
                     self.max_steps if self.max_steps is not None else "?")
        self.ckpt.parent.mkdir(parents=True, exist_ok=True)

    def __enter__(self) -> "TrainingSession":
        from party import tracking
        self._hold = hold_resume_dir(self.dir)
        self._hold.__enter__()
        try:
            self._plan()
            slurm = ({"party.slurm_job_id": current_job(), "party.slurm_restarts":
                      os.environ.get("SLURM_RESTART_COUNT", "0")} if in_slurm_job() else {})
            self.run.set_tags({**self.tags, "party.resume_key": self.key,
                               "party.resumed": str(self.resume_from is not None).lower(),
                               "party.resume_step": str(self.resume_step), **slurm})
            if self.resume_from is not None:
                tracking.link_resumed(self.run, self.key)
        except BaseException:
            self._hold.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> bool:
        return bool(self._hold.__exit__(*exc))

    def export(self, out_dir, write, log_files: Iterable[str], artifact_path: str, log_checkpoint: bool) -> Path:
        """``out_dir`` whole: the rolling checkpoint (``ckpt``) as ``last.ckpt`` plus what ``write(tmp)``
        writes; then the files ``log_files`` (and ``last.ckpt`` with ``log_checkpoint``) logged under
        ``artifact_path``."""
        import shutil

        from party.io import atomic_dir
        with atomic_dir(out_dir) as tmp:
            shutil.copy2(self.ckpt, tmp / "last.ckpt")
            write(tmp)
        out_dir = Path(out_dir)
        for f in (*log_files, *(["last.ckpt"] if log_checkpoint else [])):
            self.run.log_file(out_dir / f, artifact_path)
        return out_dir
