"""Generation speed of the token generators at batch 1 and 32: the StackedDecoder against the module
path against no KV cache, measured in the same run in interleaved rounds (random weights).

    python bench/bench_generate.py [--frames 196] [--n1 20] [--n32 3] [--rounds 3]
                                   [--methods party,holistic,party_parts_only,parco,humantomato]
                                   [--profile cpu|paper] [--cond-scale S] [--text-dim 384] [--threads 2]
                                   [--device cpu]

Model numbers come from conf/generator/<profile>.yaml (``model``, ``methods``; ``cpu``, the
default, layers the CPU budget on the paper's), the guidance scale from its
``generate.cond_scale`` (methods trained with ``cond_drop`` > 0; 2 at the CPU budget), vocabularies
and code windows from conf/vqvae/paper.yaml (``tokenizers``, with conf/vqvae/cpu.yaml's on top for
``cpu``). HumanTOMATO's Hierarchical-GPT (``humantomato``) decodes rows of 2 core codes + 1 arms
code per 4 frames of its H2VQ stream (3 x frames // 4 positions); the ParCo-like method
(``parco``) its six part streams in one batched network of its own (no ``decoder`` switch: its
cached path and no cache). Every sample is forced to the full length (frames // w codes per
stream), so every run generates the same number of tokens. Prints, per method: parameters, ms per
sample at batch 1 and samples/s at batch 32 for ``decoder="stacked"`` (the default), ``"modules"``
and ``use_cache=False``, the ratios, and how many samples came out with the recomputed tokens.
Nothing is asserted (speed is machine-dependent). Run under ``ATEN_CPU_CAPABILITY=avx2
ONEDNN_MAX_CPU_ISA=AVX2`` for an AVX2-only CPU (docs/performance.md).

Also printed, per method: the **matmul ceiling** of the cache's batch-1 gain on this machine. A
stream of n positions is decoded in n steps; step L recomputes L rows without the cache, 1 row
with it. ``ceiling`` times only the transformers' ``nn.Linear`` layers (the model's own weights,
in forward order; over 90% of a step's FLOPs at these lengths) on L rows for L = 1..n and
returns sum_L T(L) / (n T(1)): about what the cache would gain if every other op and all per-op
overhead cost nothing. At d = 128 and a few dozen positions one row does not cost 1/L of L rows
(the weights are read either way), so this is near the most a cache can gain here, measured in
the same run.
"""
from __future__ import annotations

import argparse
import inspect
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from party.methods.party.model import GeneratorSpec, PartyGenerator
from party.repro import cpu_model

REPO = Path(__file__).resolve().parents[1]


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def timed(model: PartyGenerator, c: torch.Tensor, lengths: dict, mode: str, seed: int,
          cond_scale: float) -> tuple[float, dict]:
    sync(c.device)
    t0 = time.perf_counter()
    kw = {"use_cache": mode != "none"}
    if mode != "none" and "decoder" in inspect.signature(model.generate).parameters:
        kw["decoder"] = mode
    out = model.generate(c, lengths=lengths, sampling="sample", generator=torch.Generator(c.device).manual_seed(seed),
                         cond_scale=cond_scale, **kw)
    sync(c.device)
    return time.perf_counter() - t0, out


def windows_of(model) -> dict[str, int]:
    spec = model.spec
    return dict(spec.windows) if hasattr(spec, "windows") else {spec.stream: spec.window}


def build(name: str, gen_cfg, vocab: dict, windows: dict, text_dim: int):
    """The method ``name`` of ``gen_cfg`` with random weights: a ParTY-family model or the Hierarchical-GPT."""
    entry = gen_cfg.methods[name]
    torch.manual_seed(0)
    if entry.family == "parco":
        from party.methods.parco.model import ParcoGenerator, ParcoSpec
        streams = OmegaConf.load(REPO / "conf/dataset/parts/t2m.yaml").part_tokenizers
        entry = {**OmegaConf.to_container(entry, resolve=False), "streams": [str(s) for s in streams]}
        spec = ParcoSpec.from_config(gen_cfg.model, entry, vocab, windows, text_dim)
        return ParcoGenerator(spec)
    if entry.family == "humantomato":
        from party.methods.humantomato.hgpt import HGPTSpec, HierarchicalGPT
        s = str(entry.stream)
        spec = HGPTSpec.from_config(gen_cfg.model, entry, [0, 0, 1], 2, vocab[s], windows[s], text_dim)
        return HierarchicalGPT(spec)
    streams = OmegaConf.load(REPO / "conf/dataset/parts/t2m.yaml").streams     # the ParTY family's token streams
    spec = GeneratorSpec.from_config(gen_cfg.model, gen_cfg.loss, entry, {s: vocab[s] for s in streams},
                                     {s: windows[s] for s in streams}, text_dim)
    return PartyGenerator(spec)


def run(model, batch: int, reps: int, mode: str, frames: int, text_dim: int, device: torch.device,
        cond_scale: float) -> tuple[float, list]:
    """Total seconds for ``reps`` batches of ``batch`` samples (after one warm-up batch)."""
    lengths = {s: torch.full((batch,), frames // w, device=device) for s, w in windows_of(model).items()}
    g = torch.Generator().manual_seed(0)
    cs = [torch.randn(batch, text_dim, generator=g).to(device) for _ in range(reps + 1)]
    timed(model, cs[0], lengths, mode, 0, cond_scale)
    total, outs = 0.0, []
    for i, c in enumerate(cs[1:]):
        dt, out = timed(model, c, lengths, mode, i + 1, cond_scale)
        total += dt
        outs.append(out)
    for out in outs:                                 # forced lengths really generated the full length
        for s, rows in out.items():
            assert all(len(r) == int(lengths[s][0]) for r in rows), s
    return total, outs


def same_tokens(a: list, b: list) -> tuple[int, int]:
    """(samples whose tokens agree, samples) between two runs of the same seeds."""
    n = same = 0
    for x, y in zip(a, b):
        for i in range(len(next(iter(x.values())))):
            n += 1
            same += all(x[s][i].tolist() == y[s][i].tolist() for s in x)
    return same, n


def linear_chain(model: PartyGenerator, stream: str) -> list[torch.nn.Linear]:
    """The stream transformer's Linear layers in forward order (blocks, then the head)."""
    g = model.gpt[stream]
    return [m for m in g.body.modules() if isinstance(m, torch.nn.Linear)] + [g.head]


def ceiling(model: PartyGenerator, positions: dict[str, int], device: torch.device, reps: int = 50) -> float:
    """sum over streams and L = 1..n_s of T_s(L) / sum over streams of n_s T_s(1), T_s(L) the time of
    the stream's Linear layers on L rows (see the module docstring)."""
    def t(chain: list[torch.nn.Linear], rows: int) -> float:
        xs = [torch.randn(rows, m.in_features, device=device) for m in chain]
        for _ in range(5):
            for m, x in zip(chain, xs):
                torch.nn.functional.linear(x, m.weight, m.bias)
        sync(device)
        t0 = time.perf_counter()
        for _ in range(reps):
            for m, x in zip(chain, xs):
                torch.nn.functional.linear(x, m.weight, m.bias)
        sync(device)
        return (time.perf_counter() - t0) / reps

    recompute = cached = 0.0
    with torch.inference_mode():
        for s, n in positions.items():
            chain = linear_chain(model, s)
            one = t(chain, 1)
            cached += n * one
            recompute += one + sum(t(chain, L) for L in range(2, n + 1))
    return recompute / cached


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=196)
    ap.add_argument("--n1", type=int, default=20, help="samples timed at batch 1")
    ap.add_argument("--n32", type=int, default=3, help="batches of 32 timed")
    ap.add_argument("--methods", default="party,holistic,party_parts_only,parco,humantomato")
    ap.add_argument("--profile", default="cpu", choices=["paper", "cpu"], help="conf/generator/<profile>.yaml")
    ap.add_argument("--cond-scale", type=float, default=None,
                    help="guidance scale of the methods trained with cond_drop > 0 (default: the profile's "
                         "generate.cond_scale)")
    ap.add_argument("--text-dim", type=int, default=384, help="text embedding width (384: the default's MiniLM; "
                    "512: CLIP ViT-B/32)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds per mode")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    device = torch.device(a.device)
    gen_cfg = OmegaConf.load(REPO / "conf/generator/paper.yaml")
    if a.profile == "cpu":
        over = OmegaConf.load(REPO / "conf/generator/cpu.yaml")
        over.pop("defaults", None)
        gen_cfg = OmegaConf.merge(gen_cfg, over)
    if a.cond_scale is None:
        a.cond_scale = float(gen_cfg.generate.cond_scale)
    tok_cfg = OmegaConf.load(REPO / "conf/vqvae/paper.yaml").tokenizers
    if a.profile == "cpu":                         # the CPU budget's part tokenizers (ParCo-like's streams)
        tok_cfg = OmegaConf.merge(tok_cfg, OmegaConf.load(REPO / "conf/vqvae/cpu.yaml").tokenizers)
    vocab = {s: int(t.codebook_size) for s, t in tok_cfg.items()}
    windows = {s: int(t.window) for s, t in tok_cfg.items()}
    print(f"{a.frames} frames: " + ", ".join(f"{s} {a.frames // w} codes (w {w}, K {vocab[s]})"
                                            for s, w in windows.items())
          + f"; model {dict(gen_cfg.model)}; device {device}, {torch.get_num_threads()} thread(s)")
    print(f"CPU {cpu_model()}, ATen CPU capability {torch.backends.cpu.get_cpu_capability()}, fp32 "
          f"(generation never autocasts); profile {a.profile}, guidance {a.cond_scale:g}")
    modes = {"stacked": "cache, StackedDecoder", "modules": "cache, module forward", "none": "no cache"}
    for name in a.methods.split(","):
        model = build(name, gen_cfg, vocab, windows, a.text_dim).to(device).eval()
        spec = model.spec
        scale = a.cond_scale if getattr(spec, "cond_drop", 0) > 0 else 1.0
        counts = model.param_counts()
        print(f"\n[{name}] guidance scale {scale:g}; params: "
              + ", ".join(f"{k} {v / 1e6:.3f}M" for k, v in counts.items() if v))
        res = {}
        own = {m: l for m, l in modes.items()
               if m != "stacked" or "decoder" in inspect.signature(model.generate).parameters}
        if "stacked" not in own:                   # a generator with its own cached path only (ParCo-like)
            own["modules"] = "cache (its own batched forward)"
        for batch, reps in ((1, a.n1), (32, a.n32)):
            for _ in range(a.rounds):              # interleaved rounds: drift of a shared machine hits every mode
                for mode in own:
                    total, outs = run(model, batch, reps, mode, a.frames, a.text_dim, device, scale)
                    t, o = res.get((batch, mode), (0.0, []))
                    res[batch, mode] = (t + total / (batch * reps * a.rounds), o or outs)
        print(f"{'':36s} {'ms/sample':>10s} {'samples/s':>10s}")
        for batch in (1, 32):
            for mode, label in own.items():
                per = res[batch, mode][0]
                print(f"{f'batch {batch:2d} {label}':36s} {per * 1e3:10.2f} {1 / per:10.1f}")
        if "stacked" not in own:
            for batch in (1, 32):
                mo, no = res[batch, "modules"][0], res[batch, "none"][0]
                print(f"batch {batch}: cache vs recomputation {no / mo:.2f}x; samples with the recomputed tokens: "
                      f"{'%d/%d' % same_tokens(res[batch, 'modules'][1], res[batch, 'none'][1])}")
            print(f"batch 32 vs batch 1 per-sample throughput: {res[1, 'modules'][0] / res[32, 'modules'][0]:.1f}x")
            continue
        for batch in (1, 32):
            st, mo, no = (res[batch, m][0] for m in modes)
            agree = ", ".join(f"{m} {'%d/%d' % same_tokens(res[batch, m][1], res[batch, 'none'][1])}"
                              for m in ("stacked", "modules"))
            print(f"batch {batch}: StackedDecoder vs module forward {mo / st:.2f}x; cache vs recomputation "
                  f"{no / st:.2f}x (stacked), {no / mo:.2f}x (modules); samples with the recomputed tokens: {agree}")
        print(f"batch 32 vs batch 1 per-sample throughput: {res[1, 'stacked'][0] / res[32, 'stacked'][0]:.1f}x "
              f"(stacked), {res[1, 'none'][0] / res[32, 'none'][0]:.1f}x (no cache)")
        if not isinstance(model, PartyGenerator):
            continue
        positions = {s: a.frames // w + 1 for s, w in spec.windows.items() if s in spec.streams}
        b1 = res[1, "none"][0]
        print(f"matmul ceiling of the cache at batch 1 ({', '.join(f'{s} {n}' for s, n in positions.items())} "
              f"positions): {ceiling(model, positions, device):.1f}x (measured: {b1 / res[1, 'stacked'][0]:.1f}x "
              f"stacked, {b1 / res[1, 'modules'][0]:.1f}x modules)")


if __name__ == "__main__":
    main()
