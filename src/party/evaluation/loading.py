"""Loading what an evaluation needs from config: the evaluators of each stream, the
coherence part sets and SC reference statistics, tokenizer reconstruction sources, the
interaction metrics' setup, and the efficiency table (parameters, AIT). Used by ``evaluate``, ``calibrate_coherence``
and the tokenizer ablation's reconstruction FID."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from party.evaluation.checkpoint import load_reference, load_trained
from party.evaluation.coherence import Parts, SCReference
from party.data.context import DataContext, load_context
from party.evaluation.efficiency import measure_ait
from party.evaluation.interaction import InteractionSetup
from party.evaluation.protocol import motion_joints
from party.evaluation.retrievers import load_retriever
from party.evaluation.sources import find_tokenizer, load_tokenizer_source
from party.io import load_npy
from party.training import count_params

log = logging.getLogger(__name__)


def load_evaluators(cfg: DictConfig, ctx: DataContext, device: torch.device) -> dict:
    evc = cfg.evaluator
    out = {}
    for s in evc.streams:
        if s == ctx.layout.whole_stream and evc.kind == "reference":
            r = evc.reference
            dims = {k: v for k, v in OmegaConf.to_container(r.model, resolve=True).items() if k != "dropout"}
            if not r.checkpoint or not r.glove_dir:
                raise ValueError("evaluator.kind=reference needs evaluator.reference.checkpoint and .glove_dir")
            mean = load_npy(r.mean, "the reference evaluator's release", "evaluator.reference.mean") if r.mean \
                else ctx.normalizer.mean
            std = load_npy(r.std, "the reference evaluator's release", "evaluator.reference.std") if r.std \
                else ctx.normalizer.std
            if not r.mean:
                log.warning("reference evaluator without its own mean/std: using the dataset's Mean.npy/Std.npy")
            out[s] = load_reference(r.checkpoint, r.glove_dir, mean, std, dims, evc.unit_length,
                                    evc.max_text_len, device, evc.max_motion_len, stream=s)
        else:
            path = Path(evc.out_dir) / s / "finest.tar"
            if not path.exists():
                log.warning("%s: no %s evaluator; its metrics are skipped (run `party train_evaluator "
                            "evaluator.stream=%s`)", path, s, s)
                continue
            out[s] = load_trained(path, device, glove_dir=cfg.evaluator.glove_dir)
        if out[s].feat_dim != ctx.feat_dim:
            raise ValueError(f"{s} evaluator reads {out[s].feat_dim}-dim features, dataset has {ctx.feat_dim}")
    for name, folder in ((cfg.get("eval") or {}).get("retrievers") or {}).items():
        if name in ctx.layout.streams or name.startswith("recon_") or name == "ground_truth":
            raise ValueError(f"eval.retrievers.{name}: the name of an evaluator stream or a source; name it otherwise")
        if not (Path(folder) / "model.pt").is_file():
            log.warning("%s: no model.pt; the %s retriever's metrics are skipped (eval.retrievers.%s)",
                        folder, name, name)
            continue
        out[name] = load_retriever(name, folder, cfg, ctx, device)
    if not out:
        raise FileNotFoundError(f"no evaluator found under {evc.out_dir}; run `party train_evaluator` first")
    return out


def coherence_parts(cfg: DictConfig, ctx: DataContext) -> Parts:
    pc = ctx.parts_cfg
    if "coherence" not in pc or "torso" not in pc:
        raise ValueError("dataset.parts needs `coherence` (five parts) and `torso` for TC/SC")
    ends = cfg.eval.coherence.end_joints
    ends = dict(ends) if ends else {k: v[-1] for k, v in pc["coherence"].items()}
    return Parts.build(pc["coherence"], ends, pc["torso"])


def fit_sc_reference(ctx: DataContext, parts: Parts, split: str, max_clips: int | None, seed: int) -> SCReference:
    """SC statistics over every frame of (up to max_clips) clips of ``split``, joints from features."""
    bank = ctx.bank(split, 2)
    ids = np.arange(len(bank))
    if max_clips and len(ids) > max_clips:
        ids = np.sort(np.random.default_rng(seed).choice(ids, max_clips, replace=False))

    def joints():
        for i in ids:
            yield motion_joints([ctx.normalizer.denorm(bank.get(int(i)).numpy())], ctx.n_joints)[0]

    return SCReference.fit(joints(), parts)


def tokenizer_sources(cfg: DictConfig, ctx: DataContext, device: torch.device) -> dict:
    src = cfg.eval.sources
    out = {}
    for s in src.tokenizers or []:
        ckpt = find_tokenizer(Path(src.tokenizers_dir) / s, src.tokenizer_ckpt)
        if ckpt is not None:
            out[s] = load_tokenizer_source(ckpt, s, ctx, device, memo=src.memo_reconstructions)
        else:
            log.info("%s: no tokenizer checkpoint, reconstruction of %s skipped", Path(src.tokenizers_dir) / s, s)
    return out


def efficiency(cfg: DictConfig, evaluators: dict, tokenizers: dict, generated: list, gt) -> dict:
    e = cfg.eval.efficiency
    out = {"evaluators": {s: count_params(ev) for s, ev in evaluators.items()}, "tokenizers": {}, "generated": {}}
    if tokenizers:
        sample = gt.draw(np.random.default_rng(0))
        for s, src in tokenizers.items():
            inputs = src.ait_inputs(sample, e.ait_samples)
            out["tokenizers"][s] = {"params": src.n_params(), "window": src.window,
                                    "steps": (getattr(src.tok, "meta", None) or {}).get("steps_trained"),
                                    **measure_ait(src.reconstruct_stream, inputs, e.ait_samples,
                                                  e.ait_warmup)}
    for g in generated:
        out["generated"][g.name] = {k: g.meta[k] for k in ("params", "ait_ms", "steps_trained") if k in g.meta}
    return out


def reconstruction_fid_scorer(cfg, stream: str):
    """A function ``tok_dir -> {recon_fid, recon_fid_ci95}`` scoring a tokenizer's reconstructions
    of ``eval.split`` under the stream's evaluator with the ``evaluate`` stage's protocol, or
    None when FID is off or no evaluator exists. ``run`` builds one per distinct evaluation
    setup, so data, evaluator and ground truth load once per sweep, not once per point."""
    from party.evaluation.protocol import Embedder, run_protocol
    from party.evaluation.sources import GroundTruthSource
    from party.training import resolve_device

    ab = cfg.vqvae.ablation
    if not ab.fid or "evaluator" not in cfg or "eval" not in cfg:
        return None
    ctx = load_context(cfg)
    device = resolve_device(cfg.eval.device)
    only = OmegaConf.merge(cfg, {"evaluator": {"streams": [stream]}})      # load this stream's alone
    try:
        ev = load_evaluators(only, ctx, device).get(stream)
    except FileNotFoundError:
        ev = None
    if ev is None:
        log.info("no %s evaluator under %s: reconstruction FID skipped", stream, cfg.evaluator.out_dir)
        return None
    ec = cfg.eval
    protocol = OmegaConf.to_container(ec, resolve=True)
    protocol.update(replications=ab.fid_replications, coherence={"enabled": False},
                    sources={"ground_truth": False})
    gt = GroundTruthSource(ctx, ec.split, ec.max_motion_len, ec.unit_length)
    embedders = {stream: Embedder(ev, ec.embed_batch_size)}

    def score(tok_dir: Path) -> dict:
        src = load_tokenizer_source(Path(tok_dir) / "model.pt", stream, ctx, device,
                                    memo=ec.sources.memo_reconstructions)
        res = run_protocol(protocol, gt, embedders, {stream: src}, [], None, None, ctx.n_joints, ctx.layout,
                           progress=False)
        fid = res[f"recon_{stream}"][stream]["fid"]
        return {"recon_fid": round(float(fid["mean"]), 4), "recon_fid_ci95": round(float(fid["ci95"]), 4)}

    return score


def held_out_subsets(cfg, ctx) -> dict[str, tuple[set[str], str]]:
    """{"held_out": (clip ids, description)} for ``eval.held_out_subset`` on the synthetic dataset
    (the test clips of ``dataset.synthetic.held_out``); {} otherwise."""
    if not cfg.eval.held_out_subset or cfg.dataset.kind != "synthetic":
        return {}
    from party.data.synthetic.checks import held_out_clips, load_specs
    held = [list(p) for p in cfg.dataset.synthetic.held_out]
    ids = held_out_clips(ctx.index, load_specs(ctx.index.root), cfg.eval.split, held)
    if not ids:
        log.warning("eval.held_out_subset: no %s clip holds a held-out combination %s", cfg.eval.split, held)
        return {}
    pairs = ", ".join(f"{a}+{g}" for a, g in held)
    return {"held_out": (ids, f"{len(ids)} {cfg.eval.split} clips of the arm x leg combinations held out of "
                              f"training ({pairs}): compositional generalisation")}


def interaction_setup(cfg: DictConfig, ctx: DataContext) -> InteractionSetup | None:
    """The interaction metrics' setup (``eval.interaction``, ``party.evaluation.interaction``): None
    when off, or, with one warning, when its folder (``party cache_interactions``' output) is missing."""
    ic = cfg.eval.get("interaction")
    if ic is None or not ic.enabled:
        return None
    if not Path(ic.dir).is_dir():
        log.warning("%s: no interactions folder; the interaction metrics (eval.interaction) are skipped "
                    "(run `party cache_interactions`)", ic.dir)
        return None
    length_unit = float(OmegaConf.select(cfg, "eval.physics.length_unit", default=1.0))
    return InteractionSetup.from_config(OmegaConf.to_container(ic, resolve=True), ctx, cfg.eval.split, length_unit)


#: (stream key or 'coherence', metric) columns a generator ablation row reports; "{whole}" / "{part}"
#: expand to ``dataset.parts`` streams
GENERATION_COLUMNS = (("{whole}", "top1"), ("{whole}", "top3"), ("{whole}", "fid"), ("{whole}", "mm_dist"),
                      ("{whole}", "diversity"), ("{part}", "top1"), ("{part}", "fid"), ("coherence", "tc"),
                      ("coherence", "sc"))


RETRIEVER_COLUMNS = ("top1", "top1_b{large}", "mm_dist")     # of every eval.retrievers model (e.g. TMA)


def _generation_keys(layout, cfg):
    """(results key, metric, column name) of every ``GENERATION_COLUMNS`` entry, streams expanded,
    then ``RETRIEVER_COLUMNS`` of every ``eval.retrievers`` model (``<name>_<metric>``)."""
    for stream, metric in GENERATION_COLUMNS:
        for s in (layout.part_streams if stream == "{part}" else [stream.format(whole=layout.whole_stream)]):
            yield s, metric, (metric if s == layout.whole_stream else f"{s}_{metric}")
    large = int(cfg.eval.large_batch_size)
    for r in (cfg.eval.get("retrievers") or {}):
        for metric in RETRIEVER_COLUMNS:
            metric = metric.format(large=large)
            yield r, metric, f"{r}_{metric}"


def generation_columns(cfg, ctx) -> list[str]:
    """Column names of ``generation_scorer`` rows (each with a ``_ci95`` twin)."""
    return [c for _, _, name in _generation_keys(ctx.layout, cfg) for c in (name, f"{name}_ci95")]


def generation_scorer(cfg, replications: int):
    """A function ``generated_dir -> {column: value}`` scoring one generated run with the
    ``evaluate`` stage's protocol (every trained evaluator, TC/SC when on, ``replications``
    replications); data, evaluators, coherence reference and ground truth load once."""
    from party.evaluation.protocol import Embedder, run_protocol
    from party.evaluation.sources import GeneratedSource, GroundTruthSource
    from party.training import resolve_device

    ec = cfg.eval
    ctx = load_context(cfg)
    device = resolve_device(ec.device)
    evaluators = load_evaluators(cfg, ctx, device)
    parts = coherence_parts(cfg, ctx) if ec.coherence.enabled else None
    sc_ref = (fit_sc_reference(ctx, parts, ec.coherence.reference_split, ec.coherence.reference_max_clips, ec.seed)
              if parts is not None else None)
    protocol = OmegaConf.to_container(ec, resolve=True)
    protocol.update(replications=replications, sources={**protocol["sources"], "ground_truth": False})
    gt = GroundTruthSource(ctx, ec.split, ec.max_motion_len, ec.unit_length)
    embedders = {s: Embedder(ev, ec.embed_batch_size) for s, ev in evaluators.items()}
    allow = bool(cfg.generator.get("allow_mismatch", False)) if "generator" in cfg else False

    def score(gen_dir: Path) -> dict:
        src = GeneratedSource(gen_dir, ctx, ec.split, ec.unit_length, allow_mismatch=allow)
        res = run_protocol(protocol, gt, embedders, {}, [src], parts, sc_ref, ctx.n_joints, ctx.layout,
                           progress=False)[src.name]
        row = {}
        for s, metric, name in _generation_keys(ctx.layout, cfg):
            stat = res.get(s, {}).get(metric)
            if stat is not None:
                row[name], row[f"{name}_ci95"] = round(float(stat["mean"]), 4), round(float(stat["ci95"]), 4)
        return row

    return score
