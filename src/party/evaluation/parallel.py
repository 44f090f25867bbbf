"""``evaluate``'s protocol in several processes, a share of the evaluator streams each.

On the CPU the protocol (embedding crops with the evaluators, FIDs, reconstructions, TC/SC) loses
from a second thread: on the default pipeline's outputs (2 cores), 153 s with
1 thread, 166 s with 2 (LAPACK's eigvalsh alone 14 ms at 1 thread, 45 ms at 2). Processes that each
score some evaluator streams with one thread use every core instead: 121 s with two
(``holistic`` | ``arms, legs``), 135 s with three on the two cores. Each share draws the same
sources (every replication's draws come from the replication's own generator) and each stream's
metrics come from a generator of that stream's own (``run_protocol``), so the merged result equals
the one-process result exactly, whatever the number of workers (a test checks it).

    inputs = protocol_inputs(cfg)                     # what the protocol reads, loaded from config
    results, sc_ref = run_shared(cfg, inputs, workers=3)

Shares: the whole-body stream (``PartLayout.whole_stream``; ``holistic`` in the default layout)
alone, first, with TC/SC, the physics metrics, the interaction metrics (of every source: that share
reconstructs with every tokenizer) and MultiModality (which reads its evaluator), the
other streams dealt round-robin over the other workers; a tokenizer's reconstruction error and the
physics metrics of its reconstructions are computed in the share scoring its stream (else the
first). What every share repeats: the draws, the whole-body
tokenizer's reconstructions (each evaluator scores them), loading. Each worker loads
what it needs itself (``spawn``: nothing of the parent's torch state is inherited) and runs
``max(1, threads // workers)`` threads.
"""
from __future__ import annotations

import logging
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from party.lifecycle import die_with_parent

log = logging.getLogger(__name__)


@dataclass
class ProtocolInputs:
    ctx: object
    device: torch.device
    evaluators: dict
    parts: object            # coherence part sets, or None (TC/SC off)
    sc_ref: object           # SC reference statistics, or None (TC/SC off or not fitted here)
    gt: object
    tokenizers: dict
    generated: list
    subsets: dict            # {name: (clip ids, description)}; the interactive subset under 'interaction'
    physics: object = None   # PhysicsSetup of the dataset, or None (eval.physics off)
    interaction: object = None   # InteractionSetup, or None (eval.interaction off or its folder missing)

    @property
    def source_order(self) -> list[str]:
        return ["ground_truth"] + [f"recon_{s}" for s in self.tokenizers] + [g.name for g in self.generated]


def protocol_inputs(cfg: DictConfig, streams: list[str] | None = None, sc_reference: bool = True,
                    interaction: bool = True) -> ProtocolInputs:
    """Everything ``run_protocol`` reads, from config: the evaluators of ``streams`` (default
    ``evaluator.streams``), the SC reference when ``sc_reference`` (fitting it takes a few seconds),
    ground truth, tokenizer reconstructions, generated runs, the held-out subsets, the physics
    metrics' setup (the dataset's foot joints and fps, ``eval.physics``) and, when ``interaction``,
    the interaction metrics' setup (``eval.interaction``; its clips and description also under
    ``subsets['interaction']``, which the report and the summary read)."""
    from party.data.context import load_context
    from party.evaluation.interaction import BLOCK
    from party.evaluation.loading import (coherence_parts, fit_sc_reference, held_out_subsets, interaction_setup,
                                          load_evaluators, tokenizer_sources)
    from party.evaluation.physics import PhysicsSetup
    from party.evaluation.sources import GeneratedSource, GroundTruthSource, discover_generated
    from party.motion import get_skeleton
    from party.training import resolve_device

    ec = cfg.eval
    ctx = load_context(cfg)
    device = resolve_device(ec.device)
    only = cfg
    if streams is not None:        # a share: its evaluator streams and retrievers (eval.retrievers) alone
        retr = OmegaConf.to_container(ec.retrievers, resolve=True) if ec.get("retrievers") else {}
        only = OmegaConf.merge(cfg, {"evaluator": {"streams": [s for s in streams if s not in retr]}})
        only.eval.retrievers = {k: v for k, v in retr.items() if k in streams}
    evaluators = load_evaluators(only, ctx, device)
    parts = coherence_parts(cfg, ctx) if ec.coherence.enabled else None
    sc_ref = None
    if parts is not None and sc_reference:
        sc_ref = fit_sc_reference(ctx, parts, ec.coherence.reference_split, ec.coherence.reference_max_clips,
                                  ec.seed)
    gt = GroundTruthSource(ctx, ec.split, ec.max_motion_len, ec.unit_length)
    toks = tokenizer_sources(cfg, ctx, device)
    spec = ec.sources.generated
    spec = list(spec) if isinstance(spec, ListConfig) else spec
    allow = bool(cfg.generator.get("allow_mismatch", False)) if "generator" in cfg else False
    generated = [GeneratedSource(p, ctx, ec.split, ec.unit_length, allow_mismatch=allow)
                 for p in discover_generated(spec, ec.sources.generated_dir)]
    names = [g.name for g in generated]
    reserved = {"ground_truth"} | {f"recon_{s}" for s in toks}
    clash = sorted({n for n in names if names.count(n) > 1 or n in reserved})
    if clash:
        raise ValueError(f"generated runs need unique names other than {sorted(reserved)}; clashing: {clash} "
                         f"(set `name` in their index.json)")
    physics = (PhysicsSetup.from_config(ec.physics, get_skeleton(ctx.index.skeleton), ctx.index.fps)
               if ec.physics.enabled else None)
    subsets = held_out_subsets(cfg, ctx)
    inter = interaction_setup(cfg, ctx) if interaction else None
    if inter is not None:
        subsets[BLOCK] = (set(inter.clips), inter.description)
    return ProtocolInputs(ctx, device, evaluators, parts, sc_ref, gt, toks, generated, subsets, physics, inter)


def protocol_workers(setting: int | None, device: torch.device, n_streams: int) -> int:
    """``eval.workers``: a number (at most one per stream), or null: on the CPU, one per thread
    ``torch.get_num_threads()`` gives (OMP_NUM_THREADS, which ``party repro`` sets), at most one per
    stream; 1 on a GPU (in-process, as before)."""
    if setting is not None:
        return max(1, min(int(setting), n_streams))
    if device.type != "cpu":
        return 1
    return max(1, min(n_streams, torch.get_num_threads()))


def run_protocol_on(cfg: DictConfig, inp: ProtocolInputs, streams: list[str] | None = None,
                    stream_order: list[str] | None = None, extras: bool = True, mpjpe: set[str] | None = None,
                    position: int = 0) -> dict:
    """``run_protocol`` over loaded inputs (one share when ``streams`` is given); the interaction
    metrics where ``extras`` (``inp.interaction``, not a retrieval subset)."""
    from party.evaluation.interaction import BLOCK
    from party.evaluation.protocol import Embedder, run_protocol

    ec = cfg.eval
    evs = {s: ev for s, ev in inp.evaluators.items() if streams is None or s in streams}
    return run_protocol(OmegaConf.to_container(ec, resolve=True), inp.gt,
                        {s: Embedder(ev, ec.embed_batch_size) for s, ev in evs.items()}, inp.tokenizers,
                        inp.generated, inp.parts, inp.sc_ref, inp.ctx.n_joints, inp.ctx.layout,
                        progress=cfg.progress, subsets={k: ids for k, (ids, _) in inp.subsets.items() if k != BLOCK},
                        stream_order=stream_order, extras=extras, mpjpe=mpjpe, position=position,
                        physics=inp.physics, interaction=inp.interaction)


def _share(cfg: dict, streams: list[str], stream_order: list[str], extras: bool, mpjpe: set[str], threads: int,
           position: int) -> tuple[dict, object]:
    """One worker: load this share's inputs, score them; -> (results, SC reference or None)."""
    torch.set_num_threads(threads)
    c = OmegaConf.create(cfg)
    inp = protocol_inputs(c, streams, sc_reference=extras, interaction=extras)
    return run_protocol_on(c, inp, streams, stream_order, extras, mpjpe, position), inp.sc_ref


def run_shared(cfg: DictConfig, inp: ProtocolInputs, workers: int) -> tuple[dict, object]:
    """The protocol in ``workers`` processes; -> (merged results, SC reference of the share that
    scored TC/SC, or None). ``inp`` (the parent's inputs) gives the streams and the source order."""
    from party.evaluation.protocol import merge_results

    streams = list(inp.evaluators)
    whole = inp.ctx.layout.whole_stream
    first = [s for s in streams if s == whole]               # the whole-body stream alone: it has the extras
    rest = [s for s in streams if s not in first]
    shares = [first] + [rest[i::workers - 1] for i in range(workers - 1)] if first else \
        [streams[i::workers] for i in range(workers)]
    owner = {t: next((i for i, sh in enumerate(shares) if t in sh), 0) for t in inp.tokenizers}   # else: share 0
    threads = max(1, torch.get_num_threads() // workers)
    log.info("evaluation protocol in %d processes (%s), %d thread(s) each", workers,
             " | ".join(", ".join(sh) for sh in shares), threads)
    container = OmegaConf.to_container(cfg, resolve=True)
    if "interaction" in container["eval"] and inp.interaction is None:   # off, or skipped here (warned once)
        container["eval"]["interaction"]["enabled"] = False
    # workers end with this process, whatever kills it (kill -9 included): a worker holds ~2 GB
    ex = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=die_with_parent,
                             initargs=(os.getpid(),))
    try:
        futures = [ex.submit(_share, container, sh, streams, i == 0, {t for t, o in owner.items() if o == i},
                             threads, i) for i, sh in enumerate(shares)]
        outs = [f.result() for f in futures]
    except BaseException:
        for p in list((getattr(ex, "_processes", None) or {}).values()):   # no waiting for the other shares
            p.terminate()
        raise
    finally:
        ex.shutdown(wait=True, cancel_futures=True)
    return merge_results([r for r, _ in outs], inp.source_order, streams), outs[0][1]   # share 0 has TC/SC
