"""The evaluation protocol: replications over sources x evaluators -> mean ± CI.

Per replication (Guo et al. 2022): every clip of the split is drawn once
(random caption, random crop); an independent second draw of the ground
truth gives the FID reference statistics; every source is embedded by
every applicable evaluator; R-Precision (B = 32 and B = 256), FID, MM-Dist
and Diversity are computed; TC/SC on full-body sources; MPJPE on
reconstructions. MultiModality runs its own replications on generated
runs with repeats. TextIM's interaction metrics (``party.evaluation.interaction``) score every
source on the interactive subset when ``eval.interaction`` gives them.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections import defaultdict
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from tqdm import tqdm

from party.evaluation import metrics as M
from party.evaluation.coherence import Parts, SCReference, spatial_coherence, temporal_coherence
from party.evaluation.evaluator import Evaluator
from party.evaluation.interaction import BLOCK as INTERACTION, InteractionScorer, InteractionSetup
from party.evaluation.physics import PhysicsSetup, physics_sums, pooled
from party.evaluation.sources import GeneratedSource, MotionSet, content_key, first_unseen
from party.evaluation.stats import aggregate

log = logging.getLogger(__name__)


class Embedder:
    """Embeds texts and motions with one evaluator, memoised by content.

    Texts are keyed by caption + tokens; motions by a hash of their feature
    bytes (the evaluator is deterministic in eval mode, and
    ``Evaluator.motion_input`` pads every clip with enough zeros for the convolutions'
    receptive field, so an embedding does not depend on its batch). Replications redraw captions and
    crops; a crop seen before (ground-truth clips have few possible crops, a
    generated file is fixed) is not embedded again.
    """

    def __init__(self, ev: Evaluator, batch_size: int = 256):
        self.ev, self.bs = ev.eval(), batch_size
        self.text_cache: dict[tuple, torch.Tensor] = {}
        self.motion_cache: dict[bytes, torch.Tensor] = {}

    @torch.no_grad()
    def texts(self, ms: MotionSet) -> torch.Tensor:
        keys = [(c, tuple(t) if t else None) for c, t in zip(ms.captions, ms.tokens, strict=True)]
        todo = list(dict.fromkeys(k for k in keys if k not in self.text_cache))
        for i in range(0, len(todo), self.bs):
            chunk = todo[i : i + self.bs]
            emb = self.ev.embed_text([c for c, _ in chunk], [list(t) if t else None for _, t in chunk]).cpu()
            self.text_cache.update(zip(chunk, emb, strict=True))
        return torch.stack([self.text_cache[k] for k in keys])

    @torch.no_grad()
    def motions(self, feats: list[np.ndarray] | MotionSet) -> torch.Tensor:
        if isinstance(feats, MotionSet):
            keys, feats = feats.content_keys, feats.feats
        else:
            keys = [content_key(f) for f in feats]
        todo = list(first_unseen(keys, self.motion_cache).values())
        lengths = np.array([len(f) for f in feats])
        todo.sort(key=lambda i: -lengths[i])
        for b in range(0, len(todo), self.bs):
            idx = todo[b : b + self.bs]
            T = int(lengths[idx].max())
            x = np.zeros((len(idx), T, feats[idx[0]].shape[-1]), dtype=np.float32)
            for k, j in enumerate(idx):
                x[k, : lengths[j]] = feats[j]
            emb = self.ev.embed_motion(torch.from_numpy(x), torch.as_tensor(lengths[idx])).cpu()
            self.motion_cache.update({keys[j]: e for j, e in zip(idx, emb, strict=True)})
        return torch.stack([self.motion_cache[k] for k in keys])


def retrieval_metrics(t: torch.Tensor, m: torch.Tensor, ref: M.FrechetReference | None, cfg: Mapping,
                      rng: np.random.Generator) -> dict[str, float]:
    out: dict[str, float] = {}
    n, k = len(t), int(cfg["top_k"])
    for bs, tag in ((int(cfg["batch_size"]), ""), (int(cfg["large_batch_size"]), f"_b{int(cfg['large_batch_size'])}")):
        if n >= bs:
            rp = M.r_precision(t, m, bs, k, rng=rng)
            out.update({f"top{i + 1}{tag}": float(rp[i]) for i in range(k)})
    out["mm_dist"] = M.matching_score(t, m)
    if ref is not None and len(m) > 1:
        out["fid"] = ref.fid(m)
    times = min(int(cfg["diversity_times"]), n - 1)
    if times >= 2:
        out["diversity"] = M.diversity(m, times, rng=rng)
    return out


def motion_joints(feats: list[np.ndarray], n_joints: int) -> list[np.ndarray]:
    from party.motion import recover_from_ric_np

    return [recover_from_ric_np(f.astype(np.float32), n_joints) for f in feats]


class JointScorer(ABC):
    """Scores computed per motion on its joint positions, memoised by feature content like
    ``Embedder``: ``add`` scores new motions, ``score`` a set's metrics from the memo;
    ``score_blocks`` recovers each new motion's joints once for several scorers."""

    block: str                       # the results key: results[source][block][metric]

    def __init__(self, n_joints: int):
        self.n_joints = n_joints
        self.cache: dict[bytes, object] = {}

    @abstractmethod
    def add(self, keys: Sequence[bytes], joints: Sequence[np.ndarray]) -> None:
        """Score the motions ``keys`` (not in the memo yet) from their (T, J, 3) ``joints``."""

    @abstractmethod
    def score(self, keys: Sequence[bytes]) -> dict[str, float]:
        """The metrics of the set of (memoised) motions ``keys``."""

    def __call__(self, ms: MotionSet) -> dict[str, float]:
        return score_blocks(ms, [self])[self.block]


def score_blocks(ms: MotionSet, scorers: Sequence[JointScorer]) -> dict[str, dict[str, float]]:
    """{scorer.block: metrics of ``ms``}; the motions some scorer has not seen are recovered to
    joints once and given to the scorers lacking them."""
    keys = ms.content_keys
    todo = {k: i for k, i in first_unseen(keys, {}).items() if any(k not in s.cache for s in scorers)}
    if todo:
        joints = dict(zip(todo, motion_joints([ms.feats[i] for i in todo.values()], scorers[0].n_joints),
                          strict=True))
        for s in scorers:
            new = [k for k in todo if k not in s.cache]
            if new:
                s.add(new, [joints[k] for k in new])
    return {s.block: s.score(keys) for s in scorers}


class CoherenceScorer(JointScorer):
    """Per-motion TC and SC; a set's TC / SC: the mean over its motions."""

    block = "coherence"

    def __init__(self, parts: Parts, sc_ref: SCReference | None, c: Mapping, n_joints: int):
        super().__init__(n_joints)
        self.parts, self.sc_ref, self.c = parts, sc_ref, c

    def add(self, keys: Sequence[bytes], joints: Sequence[np.ndarray]) -> None:
        c = self.c
        tc = temporal_coherence(joints, self.parts, float(c["sigma"]), float(c["kappa"]), int(c["window"]),
                                int(c["tau_max"]), float(c["eps"]), c.get("stride"))
        sc = np.full(len(keys), np.nan)
        if self.sc_ref is not None:
            sc = spatial_coherence(joints, self.parts, self.sc_ref, float(c["beta_d"]), float(c["beta_theta"]),
                                   float(c["eps"]))
        self.cache.update({k: (float(a), float(b)) for k, a, b in zip(keys, tc, sc, strict=True)})

    def score(self, keys: Sequence[bytes]) -> dict[str, float]:
        vals = np.array([self.cache[k] for k in keys])
        out = {"tc": float(np.nanmean(vals[:, 0]))}
        if self.sc_ref is not None:
            out["sc"] = float(np.nanmean(vals[:, 1]))
        return out


class PhysicsScorer(JointScorer):
    """Per-motion (sum, count) pairs of the physical plausibility metrics
    (``party.evaluation.physics``); a set's metric pools every frame of its motions."""

    block = "physics"

    def __init__(self, setup: PhysicsSetup, n_joints: int):
        super().__init__(n_joints)
        self.setup = setup

    def add(self, keys: Sequence[bytes], joints: Sequence[np.ndarray]) -> None:
        self.cache.update(zip(keys, physics_sums(joints, self.setup), strict=True))

    def score(self, keys: Sequence[bytes]) -> dict[str, float]:
        return pooled(np.stack([self.cache[k] for k in keys]))


def run_protocol(cfg: Mapping, gt_src, embedders: dict[str, Embedder], tokenizers: dict,
                 generated: list[GeneratedSource],
                 parts: Parts | None, sc_ref: SCReference | None, n_joints: int, layout=None,
                 progress: bool = True, subsets: Mapping[str, set[str]] | None = None,
                 stream_order: list[str] | None = None, extras: bool = True,
                 mpjpe: set[str] | None = None, position: int = 0,
                 whole_stream: str | None = None, physics: PhysicsSetup | None = None,
                 interaction: InteractionSetup | None = None) -> dict[str, dict[str, dict]]:
    """-> {source: {stream|'coherence'|'physics'|'interaction'|'reconstruction': {metric: {mean, ci95, n}},
    <subset>: {stream: ...}}}

    ``subsets`` {name: clip ids}: the retrieval metrics again on the samples of those clips only
    (the same draws and embeddings; R-Precision pools within the subset, FID against the
    reference draw of the same clips), under ``[source][<name>][<stream>]`` of generated runs and ground truth.

    One call may score a share of the protocol (``party.evaluation.parallel`` runs shares side by
    side): ``embedders`` the evaluator streams scored here, ``stream_order`` every stream of the
    whole protocol (default: ``embedders``), ``extras`` whether TC/SC and MultiModality are computed
    here, ``mpjpe`` the tokenizers whose reconstruction error is computed here (None: every one).
    Each replication draws the sources from its own generator and each stream's metrics from a
    generator of its own (spawned by stream index in ``stream_order``), so the numbers do not
    depend on how the streams are shared out.

    ``whole_stream``: the whole-body stream (default: ``layout.whole_stream``); every evaluator scores
    its tokenizer's reconstructions, TC/SC score them, MultiModality reads its evaluator.

    ``physics`` (with ``cfg['physics']['enabled']``): the physical plausibility metrics
    (``party.evaluation.physics``) of every source, memoised per motion like TC/SC: ground truth
    and generated runs where the extras are computed, each tokenizer's reconstructions where its
    reconstruction error is (``mpjpe``).

    ``interaction`` (``party.evaluation.interaction``; None: off): TextIM's interaction metrics of every
    source on the interactive subset's clips, where the extras are computed (every tokenizer's
    reconstructions are then drawn there too): retrieval with the interaction text under the
    whole-body evaluator (when it is here), joint errors against the same clip's ground truth. Its
    R-Precision batches come from a generator of its own, spawned after the streams' ones."""
    rows: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    sub_rows: dict[str, dict[str, dict[str, list[dict]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    coh = cfg["coherence"]
    whole = whole_stream_of(layout, whole_stream)
    order_streams = list(stream_order or embedders)
    scorer = (CoherenceScorer(parts, sc_ref, coh, n_joints)
              if extras and coh["enabled"] and parts is not None else None)
    phys = PhysicsScorer(physics, n_joints) if physics is not None and cfg["physics"]["enabled"] else None
    whole_body = [s for s in (scorer, phys) if s is not None] if extras else []   # ground truth, generated
    inter = InteractionScorer(interaction, n_joints) if extras and interaction is not None else None
    recon_errors: dict[str, dict[bytes, tuple[float, float, int]]] = defaultdict(dict)
    seeds = np.random.SeedSequence(int(cfg["seed"])).spawn(int(cfg["replications"]))
    desc = "replications" + (f" ({', '.join(embedders)})" if list(embedders) != order_streams else "")
    for ss in tqdm(seeds, desc=desc, disable=not progress, position=position):
        rng = np.random.default_rng(ss)
        stream_seeds = ss.spawn(len(order_streams))
        gt = gt_src.draw(rng)
        gt_ref = gt_src.draw(rng)
        # name -> (motions, evaluator streams scoring them, joint scorers scoring them)
        sets: dict[str, tuple[MotionSet, list[str], list[JointScorer]]] = {}
        if cfg["sources"]["ground_truth"]:
            sets["ground_truth"] = (gt, list(embedders), whole_body)
        for stream, src in tokenizers.items():
            streams = list(embedders) if stream == whole else [s for s in embedders if s == stream]
            own_error = mpjpe is None or stream in mpjpe
            joint_scorers = [s for s, on in ((scorer, stream == whole), (phys, own_error)) if s is not None and on]
            if not (streams or own_error or joint_scorers or inter is not None):
                continue
            rec = src.reconstruct(gt)
            sets[f"recon_{stream}"] = (rec, streams, joint_scorers)
            if own_error:
                rows[f"recon_{stream}"]["reconstruction"].append(
                    reconstruction_metrics(rec, gt, layout, n_joints, cfg, recon_errors[stream], whole_stream=whole))
        for g in generated:
            sets[g.name] = (g.draw(rng), list(embedders), whole_body)
        for stream, emb in embedders.items():
            srng = np.random.default_rng(stream_seeds[order_streams.index(stream)])
            m_ref = emb.motions(gt_ref)
            ref = M.FrechetReference.of(m_ref)
            sub_refs = {}
            for k, ids in (subsets or {}).items():
                r = _rows_of(gt_ref, ids)
                if len(r) >= 2:                  # fewer clips: nothing to score on
                    sub_refs[k] = (ids, M.FrechetReference.of(m_ref[r]))
            for name, (ms, streams, _) in sets.items():
                if stream in streams:
                    m, t = emb.motions(ms), emb.texts(ms)
                    rows[name][stream].append(retrieval_metrics(t, m, ref, cfg, srng))
                    if name.startswith("recon_"):
                        continue
                    for k, (ids, sref) in sub_refs.items():
                        r = _rows_of(ms, ids)
                        sub_rows[name][k][stream].append(retrieval_metrics(t[r], m[r], sref, cfg, srng))
        for name, (ms, _, joint_scorers) in sets.items():
            if joint_scorers:
                for block, vals in score_blocks(ms, joint_scorers).items():
                    rows[name][block].append(vals)
        if inter is not None:
            irng = np.random.default_rng(ss.spawn(1)[0])
            for name, (ms, _, _) in sets.items():
                ref = gt if name == "ground_truth" or name.startswith("recon_") else None   # the crop they come from
                vals = inter(ms, ref, embedders.get(whole), cfg, irng)
                if vals:
                    rows[name][INTERACTION].append(vals)
    z = float(cfg["ci_z"])
    order = ["ground_truth"] + [f"recon_{s}" for s in tokenizers] + [g.name for g in generated]
    out = {name: {k: aggregate(v, z) for k, v in rows[name].items()} for name in order if name in rows}
    for name, subs in sub_rows.items():
        for k, by_stream in subs.items():
            out[name][k] = {s: aggregate(v, z) for s, v in by_stream.items()}
    if extras and whole in embedders:
        for g in generated:
            mm = multimodality(g, embedders[whole], cfg["multimodality"], int(cfg["seed"]))
            if mm is not None:
                out[g.name].setdefault(whole, {})["multimodality"] = mm
    return merge_results([out], order, order_streams)


def merge_results(shares: list[dict[str, dict[str, dict]]], source_order: list[str],
                  stream_order: list[str]) -> dict[str, dict[str, dict]]:
    """The results of protocol shares as one ``run_protocol`` result, in one order whatever the
    sharing: sources in ``source_order``, then per source: reconstruction, the streams in
    ``stream_order``, coherence, physics, interaction, subsets (each subset's streams in ``stream_order``)."""
    def rank(key: str) -> tuple[int, int]:
        if key in stream_order:
            return 1, stream_order.index(key)
        return {"reconstruction": (0, 0), "coherence": (2, 0), "physics": (2, 1), INTERACTION: (2, 2)}.get(key, (3, 0))

    merged: dict[str, dict[str, dict]] = {}
    for name in source_order:
        entry: dict[str, dict] = {}
        for out in shares:
            for key, val in out.get(name, {}).items():
                entry.setdefault(key, {}).update(val)
        for key, val in entry.items():
            if rank(key)[0] == 3:                                  # a subset: {stream: metrics}
                entry[key] = {st: val[st] for st in sorted(val, key=stream_order.index)}
        if entry:
            merged[name] = {k: entry[k] for k in sorted(entry, key=rank)}
    return merged


def _rows_of(ms: MotionSet, ids: set[str]) -> torch.Tensor:
    return torch.tensor([i for i, k in enumerate(ms.keys) if k in ids], dtype=torch.long)


def whole_stream_of(layout, whole_stream: str | None = None) -> str:
    """``whole_stream`` if given, else the whole-body stream of the part layout
    (``PartLayout.whole_stream``)."""
    if whole_stream is not None:
        return whole_stream
    if layout is None:
        raise ValueError("the whole-body stream is unknown: pass the part layout or whole_stream")
    return layout.whole_stream


def reconstruction_metrics(rec: MotionSet, gt: MotionSet, layout, n_joints: int, cfg: Mapping,
                           memo: dict[bytes, tuple[float, float, int]] | None = None,
                           whole_stream: str | None = None) -> dict[str, float]:
    """MPJPE (mm) over the reconstructed frames: all joints (the whole-body stream, ``whole_stream``,
    default ``layout.whole_stream``; also a reconstruction naming no stream) or the stream's joints (parts).

    ``mpjpe_mm``: root-aligned per frame (pelvis subtracted from both, the
    MoMask / T2M-GPT convention); ``mpjpe_global_mm``: positions as recovered,
    including root-trajectory drift. ``memo``: per-clip error sums keyed by the ground-truth
    crop's content (a crop's reconstruction is deterministic), reused across replications.
    """
    whole = whole_stream_of(layout, whole_stream)
    stream = rec.extra.get("stream", whole)
    scale = float(cfg["mpjpe_scale"])
    memo = {} if memo is None else memo
    err_local = err_global = 0.0
    count = 0
    for key, g_full, r_full in zip(gt.content_keys, gt.feats, rec.feats, strict=True):
        if key not in memo:
            memo[key] = _clip_errors(g_full, r_full, stream == whole, stream, layout, n_joints)
        e_local, e_global, n = memo[key]
        err_local, err_global, count = err_local + e_local, err_global + e_global, count + n
    count = max(count, 1)
    return {"mpjpe_mm": scale * err_local / count, "mpjpe_global_mm": scale * err_global / count}


def _clip_errors(g_full: np.ndarray, r_full: np.ndarray, whole: bool, stream: str, layout, n_joints: int
                 ) -> tuple[float, float, int]:
    """(sum of root-aligned errors, sum of global errors, joint-frames) of one reconstruction;
    ``whole``: ``stream`` is the whole-body stream (every joint)."""
    from party.motion import recover_from_ric

    if whole:
        T = len(r_full)
        pj = recover_from_ric(torch.from_numpy(r_full), n_joints)
        gj = recover_from_ric(torch.from_numpy(g_full[:T].astype(np.float32)), n_joints)
    else:  # stream joints, root first (PartLayout.stream_joints is sorted and holds joint 0)
        rs, gs = (torch.from_numpy(layout.slice(x, stream).astype(np.float32)) for x in (r_full, g_full[: len(r_full)]))
        pj, gj = layout.recover_stream_joints(rs, stream), layout.recover_stream_joints(gs, stream)
    err_global = float(torch.linalg.vector_norm(pj - gj, dim=-1).sum())
    err_local = float(torch.linalg.vector_norm((pj - pj[..., :1, :]) - (gj - gj[..., :1, :]), dim=-1).sum())
    return err_local, err_global, pj.shape[0] * pj.shape[1]


def multimodality(g: GeneratedSource, emb: Embedder, c: Mapping, seed: int) -> dict | None:
    times = int(c["times"])
    groups = g.repeats(times)
    if not groups:
        return None
    n_rep = min(len(v) for v in groups.values())
    ids = sorted(groups)
    vals = []
    for ss in np.random.SeedSequence(seed + 1).spawn(int(c["replications"])):
        rng = np.random.default_rng(ss)
        pick = rng.choice(len(ids), min(int(c["num_texts"]), len(ids)), replace=False)
        feats = [f for i in pick for f in groups[ids[i]][:n_rep]]
        e = emb.motions(feats).reshape(len(pick), n_rep, -1)
        vals.append({"multimodality": M.multimodality(e, times, rng=rng)})
    return aggregate(vals)["multimodality"]
