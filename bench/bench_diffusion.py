"""Generation speed of the diffusion generators: TextIM (two modules + Part-GCN) against MDM (one
denoiser) at the same number of sampling steps, batch 1 and batch 32, measured in the same run
(random weights; SPEC-textim §11 item 11).

    python bench/bench_diffusion.py [--profile cpu|paper] [--frames 196] [--steps N] [--n1 3] [--n32 1]
                                    [--threads 2] [--precision fp32|bf16] [--device cpu]

Model numbers come from conf/generator/paper.yaml ``methods.textim`` / ``methods.mdm`` (``cpu``
layers conf/generator/cpu.yaml on them); ``--steps`` defaults to the profile's ``sample_steps``
(the paper profile's null means all diffusion steps: give ``--steps`` to keep a paper-size run
short; the time per step is what carries over). The six-part table is
conf/dataset/parts/t2m.yaml ``groups.textim6``. Rows timed:

- ``mdm``: the caption-only denoiser with classifier-free guidance (both passes in one batch);
- ``textim (left arm)``: a caption with one interacting part (module 1 on its 48 channels, the
  Part-GCN's S, module 2 with the overwrite after every step);
- ``textim (no interaction)``: m = 0, where module 1 and the GCN are skipped.

The text vectors are random (the LLM extraction is cached in the pipeline and costs nothing here;
``party cache_interactions`` times it). Prints ms per sample at batch 1, samples/s at batch 32,
and each TextIM row's ratio to MDM. Nothing is asserted (speed is machine-dependent).
"""
from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from party.methods.textim.family import model_config
from party.methods.textim.model import MDM, TextIM
from party.motion.parts import group_index
from party.repro import cpu_model
from party.text.interactions.extract import part_mask

REPO = Path(__file__).resolve().parents[1]
FEAT_DIM, N_JOINTS = 263, 22


def entries(profile: str) -> dict:
    cfg = OmegaConf.load(REPO / "conf/generator/paper.yaml")
    if profile == "cpu":
        over = OmegaConf.load(REPO / "conf/generator/cpu.yaml")
        over.pop("defaults", None)
        cfg = OmegaConf.merge(cfg, over)
    root = OmegaConf.create({"generator": cfg})            # the profiles interpolate generator.methods.*
    return {m: OmegaConf.to_container(root.generator.methods[m], resolve=True) for m in ("textim", "mdm")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="cpu", choices=["paper", "cpu"], help="conf/generator/<profile>.yaml")
    ap.add_argument("--frames", type=int, default=196)
    ap.add_argument("--steps", type=int, default=None, help="sampling steps (default: the profile's sample_steps)")
    ap.add_argument("--n1", type=int, default=3, help="samples timed at batch 1")
    ap.add_argument("--n32", type=int, default=1, help="batches of 32 timed")
    ap.add_argument("--text-dim", type=int, default=384, help="the offline MiniLM's width (CLIP: 512)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--precision", default="fp32", choices=["fp32", "bf16"])
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    dev = torch.device(a.device)
    ents = entries(a.profile)
    steps = a.steps or ents["textim"]["sample_steps"] or ents["textim"]["diffusion_steps"]
    torch.manual_seed(0)
    models = {m: (MDM if m == "mdm" else TextIM)(model_config(e, FEAT_DIM, N_JOINTS, a.text_dim)).to(dev).eval()
              for m, e in ents.items()}
    parts_cfg = OmegaConf.load(REPO / "conf/dataset/parts/t2m.yaml")
    groups = group_index(N_JOINTS, OmegaConf.to_container(parts_cfg.groups.textim6, resolve=True))
    arm = torch.from_numpy(part_mask(["left_arm"], groups, FEAT_DIM))
    print(f"CPU {cpu_model()}, {torch.get_num_threads()} thread(s), {a.precision}, ATen CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}, device {dev}; profile {a.profile}: "
          f"{a.frames} frames, {steps} {ents['textim']['sampler']} steps, guidance {ents['textim']['guidance']}")
    for m, model in models.items():
        n = sum(p.numel() for p in model.parameters())
        print(f"  {m}: {n / 1e6:.2f}M parameters")
    amp = torch.autocast(dev.type, dtype=torch.bfloat16) if a.precision == "bf16" else contextlib.nullcontext()

    def one(row: str, b: int, seed: int) -> float:
        g = torch.Generator(dev).manual_seed(seed)
        cap = torch.randn(b, a.text_dim, generator=g, device=dev)
        n = torch.full((b,), a.frames, device=dev)
        t0 = time.perf_counter()
        with amp:
            if row == "mdm":
                models["mdm"].sample(cap, n, g, steps=steps)
            else:
                mask = (arm if row == "textim (left arm)" else torch.zeros_like(arm)).to(dev).expand(b, -1)
                inter = torch.randn(b, a.text_dim, generator=g, device=dev)
                models["textim"].sample(cap, inter, torch.randn(b, a.text_dim, generator=g, device=dev), mask, n, g,
                                        steps=steps)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - t0

    rows = ("mdm", "textim (left arm)", "textim (no interaction)")
    res = {}
    for row in rows:
        one(row, 1, 99)                                       # warm-up
        res[row, 1] = float(np.mean([one(row, 1, s) for s in range(a.n1)]))
        res[row, 32] = float(np.mean([one(row, 32, s) for s in range(a.n32)])) / 32
    print(f"\n{'':26s} {'ms/sample b1':>13s} {'x MDM':>6s} {'samples/s b32':>14s} {'x MDM':>6s}")
    for row in rows:
        r1, r32 = res[row, 1] / res["mdm", 1], res[row, 32] / res["mdm", 32]
        print(f"{row:26s} {res[row, 1] * 1e3:13.1f} {r1:6.2f} {1 / res[row, 32]:14.2f} {r32:6.2f}")
    print(f"per sampling step at batch 1: mdm {res['mdm', 1] / steps * 1e3:.1f} ms, "
          f"textim {res['textim (left arm)', 1] / steps * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
