"""Two training stages side by side with one thread each, against the same two one after the
other with every core: what `party repro -j 2` gains on a small CPU machine. Measured in one run.

    python bench/bench_parallel_stages.py [--stage train_vqvae] [--steps 200]

Runs the real stage twice (``train_vqvae`` on the holistic and arms streams, or
``train_generator`` for holistic and party_parts_only) with ``max_steps`` = --steps, tracking off, outputs
in a temp folder, on the project's ``params.yaml`` and data (``dvc repro prepare`` first; for
``train_generator`` also ``extract_tokens`` and ``embed_texts``). Baseline: the two runs in
sequence with torch's default threads (every core); then: both at once with
``OMP_NUM_THREADS = cores // 2``. Prints both wall times and the ratio (> 1: parallel is
faster). Nothing is asserted: speed is machine-dependent.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARTY = [sys.executable, "-m", "party.cli"]


def commands(stage: str, steps: int, out: Path) -> list[list[str]]:
    common = ["tracking.enabled=false", "progress=false"]
    if stage == "train_vqvae":
        return [[*PARTY, stage, f"vqvae.stream={s}", f"vqvae.train.max_steps={steps}", "vqvae.train.threads=null",
                 f"vqvae.train.val_every={steps}", f"vqvae.train.ckpt_every={steps}", "vqvae.train.resume=false",
                 f"vqvae.out_dir={out / s}", f"generator.tokenizers_dir={out / s}",
                 f"vqvae.resume_dir={out / 'ckpt' / s}", "vqvae.diagnostics.on_collapse=warn", *common]
                for s in ("holistic", "arms")]
    if stage == "train_generator":
        return [[*PARTY, stage, f"generator.method={m}", f"generator.train.max_steps={steps}",
                 "generator.train.threads=null", f"generator.train.val_every={steps}",
                 f"generator.train.ckpt_every={steps}", "generator.train.resume=false",
                 "generator.train.render_samples=0", f"generator.out_dir={out / m}",
                 f"generator.resume_dir={out / 'ckpt' / m}", *common]
                for m in ("holistic", "party_parts_only")]
    raise SystemExit(f"--stage: train_vqvae or train_generator, not {stage!r}")


def wall(cmds: list[list[str]], parallel: bool, threads: str | None) -> float:
    env = dict(os.environ)
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(k, None)
        if threads:
            env[k] = threads
    t0 = time.perf_counter()
    if parallel:
        procs = [subprocess.Popen(c, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                 for c in cmds]
        errs = [p.communicate()[1] for p in procs]
        codes = [p.returncode for p in procs]
    else:
        res = [subprocess.run(c, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
               for c in cmds]
        errs, codes = [r.stderr for r in res], [r.returncode for r in res]
    for c, e, code in zip(cmds, errs, codes):
        if code:
            raise SystemExit(f"{' '.join(c[2:5])} failed:\n{e[-3000:]}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stage", default="train_vqvae")
    ap.add_argument("--steps", type=int, default=200)
    a = ap.parse_args()
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        cmds = commands(a.stage, a.steps, Path(tmp))
        seq = wall(cmds, parallel=False, threads=None)
        par = wall(cmds, parallel=True, threads=str(max(1, cores // 2)))
    print(f"{a.stage}, 2 runs x {a.steps} steps, {cores} cores:")
    print(f"  one after the other, {cores} threads each: {seq:7.1f} s")
    print(f"  side by side, {max(1, cores // 2)} thread(s) each:   {par:7.1f} s")
    print(f"  ratio (sequential / parallel): {seq / par:.2f}x")


if __name__ == "__main__":
    main()
