"""Tokenizer training throughput: the real data loader vs preloaded tensors, same run.

    python bench/bench_vqvae_loader.py [--steps 30] [--stream holistic] [key=value ...]

Reads params.yaml (+ overrides) like a stage: the prepared dataset, ``vqvae.*``
and ``trainer.num_workers / pin_memory``. Both arms run the same training
step (forward, joint-position loss, backward, AdamW) on the same model; the
"loader" arm draws batches from ``DataLoader(WindowDataset)`` as
``train_vqvae`` does, the "preloaded" arm indexes batches sampled beforehand
into one tensor. The arms alternate in short blocks (``--steps`` steps,
``--rounds`` blocks each, order flipped every round) so that load from other
processes on a shared machine hits both alike; throughput is total samples over
total time per arm, plus the median of the per-round ratios.
Prints samples/s of each arm, the ratio, and the loader alone (no model).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=5, help="training steps per arm block")
    ap.add_argument("--rounds", type=int, default=12, help="blocks per arm, alternating arms")
    ap.add_argument("--stream", default=None, help="default: vqvae.stream")
    ap.add_argument("--threads", type=int, default=None, help="default: vqvae.train.threads")
    ap.add_argument("overrides", nargs="*", help="config overrides key=value (applied to params.yaml)")
    a = ap.parse_args(argv)

    from omegaconf import OmegaConf

    from party.config import load_params
    from party.tokenizers.config import crop_length, stream_config
    from party.data.context import load_stream_data
    from party.tokenizers.data import train_loader
    from party.tokenizers.lit import VQVAELit
    from party.tokenizers.vqvae import VQVAE, Tokenizer

    cfg = load_params()
    cfg.merge_with(OmegaConf.from_dotlist(a.overrides))
    stream = a.stream or str(cfg.vqvae.stream)
    scfg = stream_config(cfg.vqvae, stream)
    t = scfg["train"]
    threads = a.threads or t.get("threads")
    if threads:
        torch.set_num_threads(int(threads))
    torch.manual_seed(0)
    data = load_stream_data(cfg, stream)
    model = VQVAE(data.in_dim, scfg["model"])
    lit = VQVAELit(Tokenizer(model, *data.stats(), data.meta()), scfg, cfg.vqvae.metrics)
    opt = torch.optim.AdamW(model.parameters(), lr=float(scfg["optim"]["lr"]),
                            betas=tuple(scfg["optim"]["betas"]))
    crop, bs = crop_length(int(t["crop"]), model.window), int(t["batch_size"])
    tr = cfg.get("trainer") or {}
    workers, pin = int(tr.get("num_workers", 0)), bool(tr.get("pin_memory", False)) and torch.cuda.is_available()
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    model.to(dev)
    lit.to(dev)
    t0 = time.perf_counter()
    loader = train_loader(data, crop, bs, workers, pin, seed=0)
    setup_s = time.perf_counter() - t0
    print(f"stream={stream} window={model.window} crop={crop} batch={bs} workers={workers} "
          f"pin_memory={pin} threads={torch.get_num_threads()} device={dev} "
          f"train clips={len(loader.dataset)} (feature bank built in {setup_s:.2f}s)")

    def step(x):
        out = model(x.to(dev, non_blocking=True))
        loss = lit._losses(out)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    it = iter(loader)

    def next_batch():
        nonlocal it
        try:
            return next(it)
        except StopIteration:
            it = iter(loader)
            return next(it)

    pre = torch.stack([next_batch() for _ in range(8)])                # preloaded batches
    if dev.type == "cuda":
        pre = pre.to(dev)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(3):                                                  # warm-up both paths
        step(pre[0])
        step(next_batch())
    res = {"loader": [], "preloaded": []}
    for r in range(a.rounds):
        for arm in ("preloaded", "loader") if r % 2 == 0 else ("loader", "preloaded"):
            sync()
            t0 = time.perf_counter()
            for k in range(a.steps):
                step(pre[k % len(pre)] if arm == "preloaded" else next_batch())
            sync()
            res[arm].append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    n_only = 4 * a.steps
    for _ in range(n_only):
        next_batch()
    loader_only = n_only * bs / (time.perf_counter() - t0)
    n = a.rounds * a.steps * bs
    sp_l, sp_p = n / sum(res["loader"]), n / sum(res["preloaded"])
    per_round = statistics.median(p / l for p, l in zip(res["preloaded"], res["loader"]))
    print(f"preloaded tensors : {sp_p:9.1f} samples/s")
    print(f"real data loader  : {sp_l:9.1f} samples/s")
    print(f"loader / preloaded: {sp_l / sp_p:9.3f}  (loader overhead {100 * (1 - sp_l / sp_p):.1f}%, "
          f"median per-round ratio {per_round:.3f}; target overhead <= 10%)")
    print(f"loader alone      : {loader_only:9.1f} samples/s ({loader_only / sp_p:.0f}x the training step)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
