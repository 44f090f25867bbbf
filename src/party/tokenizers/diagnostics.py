"""Collapse diagnostics for a trained tokenizer (logged to MLflow, printed by ``train_vqvae``).

A VQ-VAE can reach a plausible loss while decoding (nearly) the same pose for
every code: its error then sits at the level of the trivial baseline that
predicts the dataset mean. Three numbers tell the two apart:

- ``mpjpe_ratio``: validation MPJPE over the *mean-pose baseline*'s (every frame
  decoded as the dataset's mean features, i.e. normalised features of zero),
  both root-aligned, on the same clips and joints (``VQVAELit`` accumulates both);
- ``code_spread``: per-channel std, across the codebook, of what each code
  decodes to alone (normalised units, time-averaged over a run of that code),
  next to the data's own per-channel std (about 1 after z-normalisation): a
  collapsed decoder maps every code to nearly one pose;
- code usage and perplexity on validation clips.

``verdict`` calls a tokenizer *collapsed* when its MPJPE is not below
``max_baseline_ratio`` x the baseline's, or when the code spread is below
``min_code_spread`` x the data's.
"""
from __future__ import annotations

import torch


@torch.no_grad()
def code_spread(model, run_length: int) -> float:
    """Mean over channels of the std across codes of ``decode([k] * run_length)`` (time-averaged)."""
    was = model.training
    model.eval()
    K, Q = int(model.codebook_size), int(model.levels)
    dev = next(model.parameters()).device
    codes = torch.arange(K, device=dev)[:, None].repeat(1, run_length)          # (K, n)
    if Q > 1:                     # several levels: code k at every level (a row of one code index)
        codes = codes[..., None].repeat(1, 1, Q)
    dec = model.decode(codes)                                                    # (K, n*w, D)
    model.train(was)
    return float(dec.mean(1).std(0).mean())


@torch.no_grad()
def data_spread(seqs: list[torch.Tensor]) -> float:
    """Mean over channels of the per-channel std of normalised frames (the scale code_spread compares to)."""
    x = torch.cat([s.reshape(-1, s.shape[-1]) for s in seqs], 0)
    return float(x.std(0).mean())


def verdict(val: dict, spread: float, data_std: float, cfg: dict) -> dict:
    """Diagnostics dict: baseline ratio, code spread, usage and ``status`` (ok | collapsed) with reasons."""
    base = float(val["val/mpjpe_meanpose_mm"])
    ratio = float(val["val/mpjpe_mm"]) / base if base > 0 else float("nan")
    rel_spread = spread / data_std if data_std > 0 else float("nan")
    reasons = []
    if not ratio < float(cfg["max_baseline_ratio"]):
        reasons.append(f"MPJPE {val['val/mpjpe_mm']:.1f} mm is {ratio:.2f}x the mean-pose baseline's "
                       f"{base:.1f} mm (must be < {cfg['max_baseline_ratio']}x)")
    if not rel_spread >= float(cfg["min_code_spread"]):
        reasons.append(f"codes decode to nearly one pose: spread {spread:.3f} vs data {data_std:.3f} "
                       f"(ratio {rel_spread:.2f} < {cfg['min_code_spread']})")
    return {"mpjpe_mm": float(val["val/mpjpe_mm"]), "mpjpe_meanpose_mm": base, "mpjpe_ratio": ratio,
            "code_spread": spread, "data_spread": data_std, "code_spread_ratio": rel_spread,
            "code_usage": float(val["val/code_usage"]), "perplexity": float(val["val/perplexity"]),
            "status": "collapsed" if reasons else "ok", "reasons": reasons}


def banner(stream: str, diag: dict) -> str:
    """The loud message for a collapsed tokenizer (empty when it is fine)."""
    if diag["status"] == "ok":
        return ""
    bar = "!" * 78
    lines = [bar, f"TOKENIZER FAILED [{stream}]: it does not clearly beat decoding the mean pose.",
             *[f"  - {r}" for r in diag["reasons"]],
             "  Its tokens cannot carry the motion; see docs/tokenizers.md (Collapse).", bar]
    return "\n".join(lines)
