"""Training steps in bf16-mixed vs fp32 on this CPU, same run (what ``precision: auto`` buys).

    python bench/bench_precision.py [--steps 5] [--rounds 6] [--threads 1] [--profile N] [key=value ...]

Reads params.yaml (+ overrides) like a stage and needs the prepared data, tokens and
embeddings of the default pipeline. Two models, each with its real training step (forward,
loss, backward, fused AdamW) on real batches: the holistic tokenizer (``vqvae.*``) and the
ParTY generator (``generator.*``, method ``party``). The fp32 and bf16 arms (``torch.autocast``
on the CPU, as Lightning's ``bf16-mixed``) alternate in blocks of ``--steps`` steps, order
flipped every round, so load from other processes hits both alike. Prints ms per step of each
arm and the ratio, and whether this CPU computes bf16 natively (AVX512-BF16 / AMX): without
it ``precision: auto`` stays fp32, and this ratio is typically below 1. ``--profile N`` then
prints torch.profiler's N most expensive operators of each arm (docs/performance.md). Run under
``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2`` to time the fp32 arm as an AVX2-only CPU would.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from contextlib import nullcontext

import torch


def tokenizer_step(cfg):
    from party.data.context import load_stream_data
    from party.tokenizers.config import crop_length, stream_config
    from party.tokenizers.data import train_loader
    from party.tokenizers.lit import VQVAELit
    from party.tokenizers.vqvae import VQVAE, Tokenizer

    scfg = stream_config(cfg.vqvae, "holistic")
    data = load_stream_data(cfg, "holistic")
    model = VQVAE(data.in_dim, scfg["model"])
    lit = VQVAELit(Tokenizer(model, *data.stats(), data.meta()), scfg, cfg.vqvae.metrics)
    crop = crop_length(int(scfg["train"]["crop"]), model.window)
    it = iter(train_loader(data, crop, int(scfg["train"]["batch_size"]), 0, False, seed=0))
    batches = [next(it) for _ in range(8)]
    return model, (lambda b: lit._losses(model(b))["loss"]), batches


def generator_step(cfg):
    from party.generator.data import build_generator_data, collate_generator
    from party.methods import family_of

    ds = build_generator_data(cfg, "train")
    model = family_of(cfg.generator, "party").build_model(cfg, "party", ds)     # text statistics set
    bs = int(cfg.generator.train.batch_size)
    g = torch.Generator().manual_seed(0)
    batches = [collate_generator([ds[int(i)] for i in torch.randint(len(ds), (bs,), generator=g)], ds.pad)
               for _ in range(8)]
    return model, (lambda b: model.losses(b)["loss"]), batches


def measure(name, build, cfg, steps: int, rounds: int, profile: int = 0) -> None:
    torch.manual_seed(0)
    model, loss_of, batches = build(cfg)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, fused=True)

    def step(b, bf16: bool):
        with torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else nullcontext():
            loss = loss_of(b)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for k in range(2):                                          # warm-up both arms
        step(batches[k], False)
        step(batches[k], True)
    res = {False: [], True: []}
    for r in range(rounds):
        for bf16 in (False, True) if r % 2 == 0 else (True, False):
            t0 = time.perf_counter()
            for k in range(steps):
                step(batches[k % len(batches)], bf16)
            res[bf16].append((time.perf_counter() - t0) / steps * 1e3)
    fp, bf = sum(res[False]) / rounds, sum(res[True]) / rounds
    med = statistics.median(f / b for f, b in zip(res[False], res[True]))
    print(f"{name:9s}: fp32 {fp:7.1f} ms/step   bf16-mixed {bf:7.1f} ms/step   "
          f"speed-up {fp / bf:.2f}x (median per round {med:.2f}x)", flush=True)
    if profile:
        from torch.profiler import profile as torch_profile
        for bf16 in (False, True):
            with torch_profile(record_shapes=True) as prof:
                for k in range(steps):
                    step(batches[k % len(batches)], bf16)
            print(f"\n{name}, {'bf16-mixed' if bf16 else 'fp32'}, {steps} steps: operators by own CPU time")
            print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=profile))
            print(prof.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total",
                                                                     row_limit=profile), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=5, help="training steps per arm block")
    ap.add_argument("--rounds", type=int, default=6, help="blocks per arm, alternating arms")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (a pipeline lane has 1)")
    ap.add_argument("--only", choices=("tokenizer", "generator"), default=None)
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="after the timing, torch.profiler's N most expensive operators of each arm "
                         "(--steps steps), also by input shape")
    ap.add_argument("overrides", nargs="*", help="config overrides key=value (applied to params.yaml)")
    a = ap.parse_args(argv)

    from omegaconf import OmegaConf

    from party.config import load_params
    from party.training import cpu_has_native_bf16

    torch.set_num_threads(a.threads)
    cfg = load_params()
    cfg.merge_with(OmegaConf.from_dotlist(a.overrides))
    print(f"threads={torch.get_num_threads()}  native bf16 on this CPU: {cpu_has_native_bf16()} "
          f"(precision: auto -> {'bf16-mixed' if cpu_has_native_bf16() else '32-true'})")
    for name, build in (("tokenizer", tokenizer_step), ("generator", generator_step)):
        if a.only in (None, name):
            measure(name, build, cfg, a.steps, a.rounds, a.profile)
    return 0


if __name__ == "__main__":
    sys.exit(main())
