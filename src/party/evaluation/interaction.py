"""TextIM's interaction metrics (``eval.interaction``; docs/evaluation.md, "Interaction metrics").

Scored on the interactive subset of the evaluation split, for every source (ground truth, each
tokenizer's reconstructions, every generated run), per replication, from the protocol's own draws:

- R-Precision top-1..k (batches of ``eval.batch_size``) and MM-Dist with the *interaction
  instruction* c_inter as the text (its ``inter_tokens``; a caption without one keeps the full
  caption and its tokens), embedded by the whole-body evaluator;
- MPJPE (every joint), HandJPE (``hand_joints``), FootJPE (``foot_joints``, with their parents,
  the ankles, under ``foot_with_ankles``) and MPVPE, the paper's *velocity* error
  mean ||(p̂_{t+1} − p̂_t) − (p_{t+1} − p_t)||, against the ground truth of the same clip: global
  joints from ``recover_from_ric``, no alignment, over the frames both motions have;
- side accuracy (not in the paper): of the captions whose interaction names one side of the arms
  (legs), the share whose named wrist (foot) travels a longer root-relative path than the other;
- boundary speed (not in the paper; SPEC-textim §11 item 10): the mean root-relative speed of the
  joints where the parts meet (``boundary_joints``: collars, shoulders, hips) over the reference's
  at the same frames, a ratio of means (1: as fast as the ground truth; a seam that jitters when
  the interacting channels are overwritten raises it);
- seam bone error (not in the paper): for the bones that join two parts (``seam_bones``: spine3 to
  the collars, pelvis to the hips, [parent, child] pairs), the mean of |L̂_t − L_t| / L_t over the
  frames both motions have and those bones, L the bone's length; 0 for a body that holds together
  where the parts meet, whatever it does (a slow sample cannot score well on it by standing still).

The reference of a sample (Decision): a generated sample is compared with the whole ground-truth
clip of its clip id (``DataContext.store``), both from their first frame, as a generator starts
each clip at its first frame; ground truth and reconstructions are crops the protocol draws
(random offset), compared with that same crop, so ground truth scores 0 by construction and a
reconstruction its own error. Each sample's numbers are its means over its frames; a draw's
number is the mean over its samples (each clip weighs the same).

Input, written by ``party cache_interactions`` under ``eval.interaction.dir``:
``interactions.json`` {caption: {"parts": [...], "inter": str | null, "inter_tokens": [...] | null,
"non": str | null, "fallback": bool}} and ``subset.json`` {"train" | "val" | "test": [clip ids],
"description": str, ...} (other keys are not read).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn.utils.rnn import pad_sequence

from party.evaluation import metrics as M
from party.evaluation.sources import MotionSet
from party.text.interactions.table import read_interactions

log = logging.getLogger(__name__)

BLOCK = "interaction"                 # results[source][BLOCK][metric]; summary.subsets[BLOCK]
POS_UNITS = {"m": (1.0, "m"), "cm": (100.0, "cm"), "mm": (1000.0, "mm")}
#: vel_unit -> (factor from metres per frame, times fps?, label)
VEL_UNITS = {"m_per_frame": (1.0, False, "m per frame"), "cm_per_frame": (100.0, False, "cm per frame"),
             "mm_per_frame": (1000.0, False, "mm per frame"), "m_per_s": (1.0, True, "m/s")}
#: per-sample values kept in the memo, in this order
_VALUES = ("mpjpe", "mpvpe", "hand_jpe", "foot_jpe", "path_left_hand", "path_right_hand", "path_left_foot",
           "path_right_foot", "boundary_speed", "boundary_speed_ref", "seam_bone")


@dataclass(frozen=True)
class Instruction:
    """One caption's entry of ``interactions.json``."""
    parts: frozenset
    inter: str | None
    inter_tokens: tuple | None

    def side(self, limb: str) -> int | None:
        """0 when the interaction names the left ``limb`` (arm | leg) alone, 1 the right alone, else None."""
        left, right = f"left_{limb}" in self.parts, f"right_{limb}" in self.parts
        return 0 if left and not right else 1 if right and not left else None


@dataclass
class InteractionData:
    """``interactions.json`` and ``subset.json`` of one folder."""
    entries: dict[str, Instruction]
    splits: dict[str, list[str]]
    description: str
    folder: Path


def load_interactions(folder: str | Path) -> InteractionData:
    """``interactions.json`` and ``subset.json`` of ``folder`` (``party.text.interactions.table``
    checks them; errors name the file)."""
    t = read_interactions(folder)
    entries = {cap: Instruction(frozenset(e["parts"]), e.get("inter") or None,
                                tuple(e["inter_tokens"]) if e.get("inter_tokens") and e.get("inter") else None)
               for cap, e in t.rows.items()}
    return InteractionData(entries, t.splits, t.description, t.folder)


@dataclass
class InteractionSetup:
    """What the scorer reads: the data, the scored clips, the joints and the units."""
    data: InteractionData
    clips: frozenset                            # the evaluation split's clips of the subset
    gt_clip: Callable[[str], np.ndarray]        # clip id -> raw features of the whole ground-truth clip
    hands: tuple[int, int]                      # (left, right) wrists
    feet: tuple[int, int]                       # (left, right) feet
    foot_jpe: tuple[int, ...]                   # FootJPE's joints
    boundary: tuple[int, ...]                   # the joints where the parts meet (boundary speed)
    seams: tuple[tuple[int, int], ...]          # the bones joining two parts, (parent, child) (seam bone error)
    pos_scale: float                            # joint units -> pos_unit
    vel_scale: float                            # joint units per frame -> vel_unit
    description: str                            # the subset's, its clip count and the units: the table's title

    @classmethod
    def from_config(cls, c: Mapping, ctx, split: str, length_unit: float = 1.0) -> InteractionSetup:
        """``c``: ``eval.interaction``; ``ctx`` the data context; ``split`` ``eval.split``;
        ``length_unit`` metres per joint-position unit (``eval.physics.length_unit``)."""
        from party.motion import get_skeleton

        data = load_interactions(c["dir"])
        spath = data.folder / "subset.json"
        if split not in data.splits:
            raise ValueError(f"{spath}: no {split!r} list (eval.split); it has {sorted(data.splits)}")
        by_id = {cl["id"]: cl for cl in ctx.index.clips(split)}
        ids = data.splits[split]
        unknown = [i for i in ids if i not in by_id]
        if unknown:
            raise ValueError(f"{spath}: {len(unknown)} clip(s) of its {split!r} list are not {split!r} clips of "
                             f"{ctx.index.path} (e.g. {unknown[:3]}); rerun `party cache_interactions`")
        n_joints = int(ctx.n_joints)
        pairs = {}
        for key in ("hand_joints", "foot_joints"):
            j = [int(x) for x in c[key]]
            if len(j) != 2 or not all(0 <= x < n_joints for x in j):
                raise ValueError(f"eval.interaction.{key}: [left, right], two joints of the {n_joints}-joint "
                                 f"skeleton, got {list(c[key])}")
            pairs[key] = (j[0], j[1])
        feet = pairs["foot_joints"]
        foot_jpe = feet
        if c["foot_with_ankles"]:
            parents = get_skeleton(ctx.index.skeleton).parents
            foot_jpe = (*feet, *(parents[f] for f in feet if parents[f] >= 0))
        boundary = tuple(int(x) for x in c["boundary_joints"])
        if not all(0 <= x < n_joints for x in boundary):
            raise ValueError(f"eval.interaction.boundary_joints: joints of the {n_joints}-joint skeleton, "
                             f"got {list(c['boundary_joints'])}")
        seams = tuple(tuple(int(x) for x in bone) for bone in c["seam_bones"])
        if not all(len(b) == 2 and b[0] != b[1] and all(0 <= x < n_joints for x in b) for b in seams):
            raise ValueError(f"eval.interaction.seam_bones: [parent, child] pairs of two joints of the {n_joints}-joint "
                             f"skeleton, got {[list(x) for x in c['seam_bones']]}")
        if c["pos_unit"] not in POS_UNITS or c["vel_unit"] not in VEL_UNITS:
            raise ValueError(f"eval.interaction: pos_unit one of {list(POS_UNITS)}, vel_unit one of "
                             f"{list(VEL_UNITS)}; got {c['pos_unit']!r}, {c['vel_unit']!r}")
        pos, pos_label = POS_UNITS[c["pos_unit"]]
        vel, per_s, vel_label = VEL_UNITS[c["vel_unit"]]
        vel_scale = float(length_unit) * vel * (float(ctx.index.fps) if per_s else 1.0)
        return cls(data, frozenset(ids), lambda cid: ctx.store.clip_features(by_id[cid]), pairs["hand_joints"],
                   feet, tuple(foot_jpe), boundary, seams, float(length_unit) * pos, vel_scale,
                   f"{data.description} ({len(set(ids))} {split} clips; positions in {pos_label}, "
                   f"velocities in {vel_label})")


def _joints(feats: Sequence[np.ndarray], n_joints: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, T_max, J, 3) global joints of the (zero-padded) feature sequences and their lengths."""
    from party.motion import recover_from_ric

    x = pad_sequence([torch.from_numpy(np.asarray(f, dtype=np.float64)) for f in feats], batch_first=True)
    return recover_from_ric(x, n_joints), torch.tensor([len(f) for f in feats])


def _masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean over dim 1 of (N, T) ``x`` where ``valid``; NaN for a row with no valid entry."""
    return torch.where(valid, x, 0.0).sum(1) / valid.sum(1)


def joint_values(samples: Sequence[np.ndarray], refs: Sequence[np.ndarray], n_joints: int,
                 hands: tuple[int, int], feet: tuple[int, int], foot_jpe: Sequence[int],
                 boundary: Sequence[int] = (), seams: Sequence[tuple[int, int]] = ()) -> np.ndarray:
    """(N, 11) per-sample values in ``_VALUES`` order, in joint units (per frame for MPVPE): MPJPE,
    MPVPE, HandJPE, FootJPE against ``refs`` over the first min(T̂, T) frames (global joints, no
    alignment), then the root-relative path lengths of the left / right hand and foot over the
    sample's own frames, then the mean root-relative speed of the ``boundary`` joints in the sample
    and in its reference over those shared frames (NaN without boundary joints), then the mean
    relative length error of the ``seams`` bones over those frames (NaN without seam bones)."""
    p, n_p = _joints(samples, n_joints)
    g, n_g = _joints(refs, n_joints)
    n = torch.minimum(n_p, n_g)
    T = int(n.max())
    pc, gc = p[:, :T], g[:, :T]
    frames = torch.arange(T)[None]
    valid = frames < n[:, None]                                         # (N, T)
    d = torch.linalg.vector_norm(pc - gc, dim=-1)                       # (N, T, J)
    dv = torch.linalg.vector_norm(pc.diff(dim=1) - gc.diff(dim=1), dim=-1)   # (N, T-1, J)
    out = [_masked_mean(d.mean(-1), valid), _masked_mean(dv.mean(-1), frames[:, 1:] < n[:, None]),
           _masked_mean(d[..., list(hands)].mean(-1), valid), _masked_mean(d[..., list(foot_jpe)].mean(-1), valid)]
    rel = p - p[..., :1, :]                                             # root-relative, world axes
    step = torch.linalg.vector_norm(rel.diff(dim=1), dim=-1)            # (N, T_max-1, J)
    own = torch.arange(step.shape[1])[None] < (n_p - 1)[:, None]
    path = torch.where(own[..., None], step, 0.0).sum(1)                # (N, J)
    out += [path[:, hands[0]], path[:, hands[1]], path[:, feet[0]], path[:, feet[1]]]
    shared = frames[:, 1:] < n[:, None]
    for x in (pc, gc):
        if boundary:
            sp = torch.linalg.vector_norm((x - x[..., :1, :])[:, :, list(boundary)].diff(dim=1), dim=-1)
            out.append(_masked_mean(sp.mean(-1), shared))
        else:
            out.append(torch.full((len(n),), float("nan"), dtype=pc.dtype))
    if seams:
        par, child = [a for a, _ in seams], [b for _, b in seams]
        length_p = torch.linalg.vector_norm(pc[:, :, child] - pc[:, :, par], dim=-1)     # (N, T, bones)
        length_g = torch.linalg.vector_norm(gc[:, :, child] - gc[:, :, par], dim=-1)
        err = (length_p - length_g).abs() / length_g.clamp_min(1e-9)
        out.append(_masked_mean(err.mean(-1), valid))
    else:
        out.append(torch.full((len(n),), float("nan"), dtype=pc.dtype))
    return torch.stack(out, 1).numpy()


class InteractionScorer:
    """The interaction block of one source's draw (``__call__``); per-sample joint values memoised
    by (the sample's content, its reference: the crop's content or the clip id), like ``JointScorer``."""

    block = BLOCK

    def __init__(self, setup: InteractionSetup, n_joints: int, batch_size: int = 256):
        self.setup, self.n_joints, self.batch_size = setup, n_joints, batch_size
        self.cache: dict[tuple[bytes, bytes], np.ndarray] = {}
        self._unknown: set[str] = set()

    def instruction(self, caption: str) -> Instruction | None:
        e = self.setup.data.entries.get(caption)
        if e is None and caption not in self._unknown:
            self._unknown.add(caption)
            if len(self._unknown) == 1:
                log.warning("%s: no entry for caption %r (and perhaps others): scored with the full caption, "
                            "left out of side accuracy; rerun `party cache_interactions`",
                            self.setup.data.folder / "interactions.json", caption)
        return e

    def texts(self, ms: MotionSet) -> MotionSet:
        """``ms`` with each caption replaced by its interaction instruction (and its tokens); a caption
        without one (or without an entry) kept with its own tokens."""
        caps, toks = [], []
        for cap, tok in zip(ms.captions, ms.tokens, strict=True):
            e = self.instruction(cap)
            if e is not None and e.inter:
                caps.append(e.inter), toks.append(list(e.inter_tokens) if e.inter_tokens else None)
            else:
                caps.append(cap), toks.append(tok)
        return MotionSet(list(ms.keys), caps, toks, ms.feats, extra={"_keys": ms.content_keys})

    def values(self, ms: MotionSet, ref: MotionSet | None) -> np.ndarray:
        """(N, 8) joint values of ``ms``'s samples against ``ref`` (row-aligned crops) or, when None,
        against the whole ground-truth clip of each key."""
        keys = ms.content_keys
        rkeys = ref.content_keys if ref is not None else [b"clip:" + k.encode() for k in ms.keys]
        pair = list(zip(keys, rkeys, strict=True))
        todo = list({p: i for i, p in reversed(list(enumerate(pair))) if p not in self.cache}.values())
        s = self.setup
        for b in range(0, len(todo), self.batch_size):          # padded batches: bounded memory
            idx = todo[b : b + self.batch_size]
            refs = [ref.feats[i] if ref is not None else s.gt_clip(ms.keys[i]) for i in idx]
            vals = joint_values([ms.feats[i] for i in idx], refs, self.n_joints, s.hands, s.feet, s.foot_jpe,
                                s.boundary, s.seams)
            self.cache.update({pair[i]: v for i, v in zip(idx, vals, strict=True)})
        return np.stack([self.cache[p] for p in pair]) if pair else np.zeros((0, len(_VALUES)))

    def __call__(self, ms: MotionSet, ref: MotionSet | None, emb, cfg: Mapping,
                 rng: np.random.Generator) -> dict[str, float]:
        """The metrics of the draw ``ms`` on the subset's clips ({} when it holds none): joint errors
        against ``ref`` (see ``values``), retrieval with the interaction text when ``emb`` (the
        whole-body ``Embedder``) is given, R-Precision only with at least ``cfg['batch_size']`` samples."""
        rows = [i for i, k in enumerate(ms.keys) if k in self.setup.clips]
        if not rows:
            return {}
        sub = _take(ms, rows)
        out: dict[str, float] = {}
        if emb is not None:
            t, m = emb.texts(self.texts(sub)), emb.motions(sub)
            bs, k = int(cfg["batch_size"]), int(cfg["top_k"])
            if len(rows) >= bs:
                rp = M.r_precision(t, m, bs, k, rng=rng)
                out.update({f"top{i + 1}": float(rp[i]) for i in range(k)})
            out["mm_dist"] = M.matching_score(t, m)
        v = self.values(sub, _take(ref, rows) if ref is not None else None)
        s = self.setup
        ok = np.isfinite(v[:, :4])                 # MPVPE: NaN for a sample sharing one frame with its reference
        n = ok.sum(0)
        means = np.where(n > 0, np.where(ok, v[:, :4], 0.0).sum(0) / np.maximum(n, 1), np.nan)
        out.update({name: float(x * (s.vel_scale if name == "mpvpe" else s.pos_scale))
                    for name, x in zip(_VALUES[:4], means, strict=True) if np.isfinite(x)})
        out.update(side_accuracy([self.instruction(c) for c in sub.captions], v))
        b = v[:, 8:10]
        b = b[np.isfinite(b).all(1)]
        if len(b) and b[:, 1].sum() > 0:
            out["boundary_speed"] = float(b[:, 0].sum() / b[:, 1].sum())
        seam = v[:, 10][np.isfinite(v[:, 10])]
        if len(seam):
            out["seam_bone"] = float(seam.mean())
        return out


def side_accuracy(instructions: Sequence[Instruction | None], values: np.ndarray) -> dict[str, float]:
    """{side_acc_arms, side_acc_legs}: of the samples whose instruction names one side of the limb,
    the share whose named wrist (foot) has the longer root-relative path; a key is left out when no
    sample names one side of that limb. ``values``: ``joint_values`` rows."""
    out = {}
    for limb, col in (("arm", 4), ("leg", 6)):
        side = np.array([-1 if e is None or e.side(limb) is None else e.side(limb) for e in instructions])
        named = side >= 0
        if named.any():
            rows = np.nonzero(named)[0]
            mine = values[rows, col + side[named]]
            other = values[rows, col + 1 - side[named]]
            out[f"side_acc_{limb}s"] = float((mine > other).mean())
    return out


def _take(ms: MotionSet, rows: Sequence[int]) -> MotionSet:
    keys = ms.content_keys
    return MotionSet([ms.keys[i] for i in rows], [ms.captions[i] for i in rows], [ms.tokens[i] for i in rows],
                     [ms.feats[i] for i in rows], extra={"_keys": [keys[i] for i in rows]})
