"""Optimiser step time: the fused Adam(W) every training stage uses (``party.training.adam``) against
PyTorch's default per-tensor loop on CPU, on the parameters of the real models, measured in the same run.

    python bench/bench_optimizer.py [--steps 30] [--threads 1]

Models: the ParTY generator at the paper dims (conf/generator/paper.yaml, K and windows from
conf/vqvae/paper.yaml, 384-d text as the offline MiniLM encoder) and the CPU-budget tokenizer
(conf/vqvae/cpu.yaml). Random gradients; prints ms per ``step()`` for both and the ratio, and checks
the two optimisers give the same parameters (to float tolerance) after the timed steps.
"""
from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from party.config import compose
from party.methods.party.model import GeneratorSpec, PartyGenerator
from party.tokenizers.config import stream_config
from party.tokenizers.vqvae import build_model
from party.training import adam

REPO = Path(__file__).resolve().parents[1]


def generator() -> torch.nn.Module:
    g = OmegaConf.load(REPO / "conf/generator/paper.yaml")
    tok = OmegaConf.load(REPO / "conf/vqvae/paper.yaml").tokenizers
    spec = GeneratorSpec.from_config(g.model, g.loss, g.methods.party, {s: int(t.codebook_size) for s, t in tok.items()},
                                     {s: int(t.window) for s, t in tok.items()}, 384)
    return PartyGenerator(spec)


def tokenizer() -> torch.nn.Module:
    cfg = compose(["vqvae=cpu"], REPO / "conf")
    return build_model(263, stream_config(cfg.vqvae, "holistic")["model"])    # HumanML3D's 263 channels


def time_steps(model: torch.nn.Module, fused: bool, steps: int) -> tuple[float, torch.nn.Module]:
    model = copy.deepcopy(model)
    params = [p for p in model.parameters() if p.requires_grad]
    kw = dict(lr=1e-4, betas=(0.5, 0.99), weight_decay=0.0)
    opt = adam(params, decoupled=True, **kw) if fused else torch.optim.AdamW(params, **kw)
    g = torch.Generator().manual_seed(0)
    grads = [[torch.randn(p.shape, generator=g) for p in params] for _ in range(3)]
    total = 0.0
    for i in range(steps + 1):
        for p, gr in zip(params, grads[i % 3]):
            p.grad = gr
        t0 = time.perf_counter()
        opt.step()
        if i:                                    # the first step allocates the state
            total += time.perf_counter() - t0
    return total / steps, model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    for name, build in (("generator (party, paper dims)", generator), ("tokenizer (holistic, vqvae=cpu)", tokenizer)):
        torch.manual_seed(0)
        model = build()
        n = sum(p.numel() for p in model.parameters() if p.requires_grad)
        loop, m_loop = time_steps(model, False, a.steps)
        fused, m_fused = time_steps(model, True, a.steps)
        for p, q in zip(m_loop.parameters(), m_fused.parameters()):
            assert torch.allclose(p, q, atol=1e-5), name
        print(f"{name}: {n / 1e6:.2f}M params; per-tensor loop {loop * 1e3:.1f} ms/step, fused {fused * 1e3:.1f} "
              f"ms/step: {loop / fused:.1f}x ({torch.get_num_threads()} thread(s))")


if __name__ == "__main__":
    main()
