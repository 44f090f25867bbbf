"""Figures a generator logs while it trains (paper Fig. 5, Fig. 6, fixed-prompt samples).

- ``attention_figure``: HPF attention (Fig. 5) on one validation sample: the self-attention
  over [holistic; SPLIT; arms; SPLIT; legs] and the holistic stream's cross-attention to each
  part, averaged over heads.
- ``gate_figure``: PTG gate selection ratios (Fig. 6): per part, the mean gate weight of each
  of the K text-grounding embeddings.
- ``TrainingFigures``: the Lightning callback that, after every validation (rank zero), logs
  both as PNGs under ``figures/`` of the MLflow run and, when ``render_samples`` > 0,
  ``render_samples`` stick-figure samples per fixed prompt (``generator.train.prompts``) as one
  GIF under ``samples/`` (generated with the sampling settings of ``generator.generate``,
  decoded through the tokenizers; the prompts are embedded once, before training).
"""
from __future__ import annotations

import logging
import tempfile
from pathlib import Path
from typing import Callable, Mapping, Sequence

import lightning as L
import numpy as np
import torch

from party.render import PLAIN_TEXT, plain_legend

log = logging.getLogger(__name__)


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def attention_figure(maps: Mapping[str, torch.Tensor], lengths: Mapping[str, int], parts: Sequence[str],
                     title: str = ""):
    """maps: ``PartyGenerator.attention_maps`` of a batch; lengths {stream: positions of sample 0}
    (holistic first). Shows sample 0, mean over heads, cut to its valid positions."""
    plt = _plt()
    hol = next(iter(lengths))
    L_h = lengths[hol]
    n_p = [lengths[p] for p in parts]
    Lh_full = maps[parts[0]].shape[-2]          # the batch's holistic positions (cross-attention queries)
    keep = list(range(L_h))                     # the sample's positions in [hol; SPLIT; p1; SPLIT; p2]
    ticks, names, off = [0], [hol], Lh_full
    for p, n in zip(parts, n_p):
        ticks.append(len(keep))
        names.append(f"SPLIT+{p}")
        keep += list(range(off, off + 1 + n))
        off += 1 + maps[p].shape[-1]
    sa = maps["self"][0].float().mean(0)[keep][:, keep].cpu().numpy()
    fig, axes = plt.subplots(1, 1 + len(parts), figsize=(4.2 * (1 + len(parts)), 4.0))
    ax = axes[0]
    ax.imshow(sa, cmap="viridis", aspect="auto")
    ax.set_title("HPF self-attention", **PLAIN_TEXT)
    ax.set_xticks(ticks, names, fontsize=7, **PLAIN_TEXT)
    ax.set_yticks(ticks, names, fontsize=7, **PLAIN_TEXT)
    for p, n, ax in zip(parts, n_p, axes[1:]):
        ca = maps[p][0].float().mean(0)[:L_h, :n].cpu().numpy()
        ax.imshow(ca, cmap="viridis", aspect="auto")
        ax.set_title(f"cross-attention {hol} -> {p}", **PLAIN_TEXT)
        ax.set_xlabel(f"{p} token", **PLAIN_TEXT)
        ax.set_ylabel(f"{hol} position", **PLAIN_TEXT)
    fig.suptitle(title, **PLAIN_TEXT)
    fig.tight_layout()
    return fig


def gate_figure(ratios: Mapping[str, Sequence[float]], title: str = ""):
    """ratios {part: K mean gate weights}: one bar group per part."""
    plt = _plt()
    parts = list(ratios)
    K = len(next(iter(ratios.values())))
    fig, ax = plt.subplots(figsize=(1.6 + 1.2 * len(parts) * K / 4, 3.2))
    width = 0.8 / K
    for k in range(K):
        ax.bar(np.arange(len(parts)) + (k - (K - 1) / 2) * width, [ratios[p][k] for p in parts], width,
               label=f"c'_{k + 1}")
    ax.set_xticks(np.arange(len(parts)), parts, **PLAIN_TEXT)
    ax.set_ylabel("gate selection ratio", **PLAIN_TEXT)
    ax.set_ylim(0, 1)
    plain_legend(ax.legend(fontsize=7, ncol=K))
    ax.set_title(title or "PTG gate selection per part", **PLAIN_TEXT)
    fig.tight_layout()
    return fig


def gate_ratios(values: Mapping[str, float], parts: Sequence[str]) -> dict[str, list[float]]:
    """{part: [mean gate weight of embedding k]} from ``val/gate_<part>_<k>`` scalars (empty without PTG)."""
    out = {}
    for p in parts:
        ks = sorted(int(k.rsplit("_", 1)[1]) for k in values if k.startswith(f"val/gate_{p}_"))
        if ks:
            out[p] = [float(values[f"val/gate_{p}_{k}"]) for k in ks]
    return out


class TrainingFigures(L.Callback):
    """Logs the figures of this module to ``run`` after every validation (rank zero only).

    batch: one fixed validation batch (attention maps of its first sample); samples: a callable
    ``(model) -> (list of (T, J, 3) joints, titles)`` or None (no samples).
    """

    def __init__(self, run, batch: Mapping, samples: Callable | None, skeleton: str, fps: float,
                 max_frames: int):
        self.run, self.batch, self.samples = run, batch, samples
        self.skeleton, self.fps, self.max_frames = skeleton, fps, max_frames

    def on_validation_end(self, trainer, lit):
        if not trainer.is_global_zero or trainer.sanity_checking:
            return
        try:
            self.log_figures(lit.model, lit.val_results, int(trainer.global_step))
        except Exception:              # a figure must never stop training
            log.exception("generator figures at step %d failed", trainer.global_step)

    def log_figures(self, model, val_results: Mapping[str, float], step: int) -> list[str]:
        plt = _plt()
        written = []
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            figs = {}
            parts = list(getattr(model, "parts", []))
            if getattr(model, "hpf", None) is not None:          # models with Holistic-Part Fusion
                maps = model.attention_maps(self.batch)
                lens = {s: int(self.batch["lengths"][s][0]) + 1 for s in model.spec.vocab}
                figs["hpf_attention"] = attention_figure(maps, lens, parts,
                                                         f"step {step}: {self.batch['caption'][0]}")
            ratios = gate_ratios(val_results, parts)
            if ratios:
                figs["ptg_gates"] = gate_figure(ratios, f"PTG gate selection ratios, step {step}")
            for name, fig in figs.items():
                path = tmp / f"{name}_step{step:06d}.png"
                fig.savefig(path, dpi=90)
                plt.close(fig)
                self.run.log_file(path, "figures")
                written.append(f"figures/{path.name}")
            if self.samples is not None:
                from party.render import render_comparison
                joints, titles = self.samples(model)
                path = render_comparison(joints, titles, tmp / f"samples_step{step:06d}.gif", self.skeleton,
                                         fps=self.fps, max_frames=self.max_frames)
                self.run.log_file(path, "samples")
                written.append(f"samples/{path.name}")
        return written
