"""``party train_vqvae vqvae.stream=holistic|arms|legs``: train one tokenizer.

Writes ``<vqvae.out_dir>/<stream>/`` (``model.pt``, ``last.ckpt``, ``config.json``,
``metrics.json``; see ``party.tokenizers.train``), resuming from
``<vqvae.resume_dir>/<stream>/<config hash>/`` when a run with the same settings was
interrupted. A tokenizer that does not clearly beat the mean-pose baseline fails the
stage after its outputs are written (``vqvae.diagnostics.on_collapse: error``).
"""
from __future__ import annotations

from pathlib import Path

from party.stage import stage
from party.tokenizers.train import train_tokenizer


@stage("train_vqvae", run_name=lambda cfg: f"train_vqvae-{cfg.vqvae.stream}")
def run(cfg, run_) -> dict:
    stream = cfg.vqvae.stream
    out = Path(cfg.vqvae.out_dir) / stream
    metrics = train_tokenizer(cfg, stream, out, run_)
    diag = metrics["diagnostics"]
    if diag["status"] != "ok" and cfg.vqvae.diagnostics.on_collapse == "error":
        raise RuntimeError(f"{out}: tokenizer collapsed: " + "; ".join(diag["reasons"])
                           + " (outputs and checkpoint kept; vqvae.diagnostics.on_collapse=warn "
                             "to continue anyway)")
    return metrics
