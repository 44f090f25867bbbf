"""Body-part views of the feature vector (SPEC §0, ParCo's split).

A *part* (root, left/right leg, backbone, left/right arm) and a *stream*
(``dataset.parts.streams``: holistic, arms, legs) are both index lists into the
D-dim feature vector:

- root: root data (4) + local velocity of joint 0 (3);
- a limb/backbone part: per joint ric (3) + rot6d (6) + local vel (3), plus the
  part's foot contacts for a leg;
- a group stream (``dataset.parts.group_streams``: name -> ``<table>.<group>`` of
  ``dataset.parts.groups``) is one disjoint channel group (``group_index``): HumanTOMATO's
  per-group tokenizers, whose decoded groups ``merge`` back exactly;
- a part stream (one with members in ``dataset.parts.stream_parts``: arms, legs)
  is the root part followed by the union of its parts' features (a joint shared
  by two parts, such as spine3 in both arms, appears once); the one stream with
  no members there (holistic) is the whole vector.

``merge`` is the exact inverse of slicing: overlapping copies (joint 9 in three
parts, the root in both part streams) are averaged, which leaves identical
copies bit-exact.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from party.motion.features import feature_slices

ROOT = "root"       # the implicit part: root data + joint-0 velocity, in every part stream


def _joint_feature_idx(j: int, n_joints: int) -> list[int]:
    s = feature_slices(n_joints)
    out = []
    if j > 0:
        out += list(range(s.ric.start + 3 * (j - 1), s.ric.start + 3 * j))
        out += list(range(s.rot.start + 6 * (j - 1), s.rot.start + 6 * j))
    out += list(range(s.vel.start + 3 * j, s.vel.start + 3 * j + 3))
    return out


class PartLayout:
    """Index tables for parts, streams and coherence parts of one skeleton."""

    def __init__(self, n_joints: int, parts: Mapping[str, Mapping], streams: Sequence[str],
                 stream_parts: Mapping[str, Sequence[str]], coherence: Mapping[str, Sequence[int]],
                 aliases: Mapping[str, str] | None = None, group_streams: Mapping[str, str] | None = None,
                 groups: Mapping[str, Mapping] | None = None):
        self.n_joints = n_joints
        self.feat_dim = 12 * n_joints - 1
        sl = feature_slices(n_joints)
        contacts = {"left": [sl.contacts.start, sl.contacts.start + 1],
                    "right": [sl.contacts.start + 2, sl.contacts.start + 3]}
        self.part_joints: dict[str, list[int]] = {ROOT: [0]}
        self.part_index: dict[str, np.ndarray] = {
            ROOT: np.array(list(range(sl.root.start, sl.root.stop)) + _joint_feature_idx(0, n_joints))}
        for name, spec in parts.items():
            joints = [int(j) for j in spec["joints"]]
            idx = [i for j in joints for i in _joint_feature_idx(j, n_joints)]
            if spec.get("contacts"):
                idx += contacts[spec["contacts"]]
            self.part_joints[name] = joints
            self.part_index[name] = np.array(idx)
        covered = np.unique(np.concatenate(list(self.part_index.values())))
        if len(covered) != self.feat_dim:
            raise ValueError(f"part table covers {len(covered)} of {self.feat_dim} feature channels")
        self.streams = [str(s) for s in streams]
        stray = [s for s in stream_parts if s not in self.streams]
        whole = [s for s in self.streams if s not in stream_parts]
        if stray or len(whole) != 1 or len(set(self.streams)) != len(self.streams):
            raise ValueError(f"streams {self.streams} / stream_parts {list(stream_parts)}: every stream_parts "
                             "entry must be a stream, and exactly one stream (the whole vector) has none")
        self.whole_stream = whole[0]
        self.part_streams = [s for s in self.streams if s in stream_parts]
        self.stream_parts: dict[str, list[str]] = {}
        self.stream_index: dict[str, np.ndarray] = {}
        self._stream_joints: dict[str, list[int]] = {}
        for name in self.streams:
            if name == self.whole_stream:
                self.stream_parts[name] = list(self.part_index)
                self.stream_index[name] = np.arange(self.feat_dim)
                self._stream_joints[name] = list(range(n_joints))
                continue
            members = [ROOT] + [m for m in stream_parts[name] if m != ROOT]
            idx = list(dict.fromkeys(i for m in members for i in self.part_index[m].tolist()))
            self.stream_parts[name] = members
            self.stream_index[name] = np.array(idx)
            self._stream_joints[name] = sorted({j for m in members for j in self.part_joints[m]})
        self.coherence_parts = {k: [int(j) for j in v] for k, v in coherence.items()}
        # other names of a stream (its channels, tokenized by another tokenizer): no stream of their own
        self.aliases = {str(a): str(s) for a, s in (aliases or {}).items()}
        for a, s in self.aliases.items():
            if s not in self.streams or a in self.stream_index or a in self.part_index:
                raise ValueError(f"dataset.parts.aliases: {a!r} -> {s!r}: an alias names a stream ({self.streams}) "
                                 f"and is neither a stream nor a part itself")
        # one channel group each (no stream of the generation order, no evaluator)
        self.group_index: dict[str, np.ndarray] = {}
        for name, ref in (group_streams or {}).items():
            table, _, group = str(ref).partition(".")
            if not (groups or {}).get(table) or group not in groups[table]:
                raise ValueError(f"dataset.parts.group_streams: {name!r} -> {ref!r} is not <table>.<group> of "
                                 f"dataset.parts.groups ({ {t: list(g) for t, g in (groups or {}).items()} })")
            if name in self.stream_index or name in self.part_index or name in self.aliases:
                raise ValueError(f"dataset.parts.group_streams: {name!r} is already a stream, part or alias")
            self.group_index[name] = group_index(n_joints, groups[table])[group]
            # root first, as a part alone: without the root channels its joints are recovered root-relative
            self._stream_joints[name] = [0] + [int(j) for j in groups[table][group]["joints"] if int(j) != 0]

    @classmethod
    def from_config(cls, parts_cfg: Mapping, n_joints: int) -> "PartLayout":
        """From ``dataset.parts`` (``parts``, ``streams``, ``stream_parts``, ``coherence``; when given,
        ``part_tokenizers`` must be the root and every part, once each)."""
        layout = cls(n_joints, parts_cfg["parts"], parts_cfg["streams"], parts_cfg["stream_parts"],
                     parts_cfg["coherence"], parts_cfg.get("aliases"), parts_cfg.get("group_streams"),
                     parts_cfg.get("groups"))
        if "part_tokenizers" in parts_cfg:
            pt = [str(p) for p in parts_cfg["part_tokenizers"]]
            if sorted(pt) != sorted(layout.part_index) or len(set(pt)) != len(pt):
                raise ValueError(f"dataset.parts.part_tokenizers {pt} must list the root and every part "
                                 f"({list(layout.part_index)}) once each")
        return layout

    # ------------------------------------------------------------------ slicing
    def index(self, name: str) -> np.ndarray:
        name = self.aliases.get(name, name)
        if name in self.stream_index:
            return self.stream_index[name]
        if name in self.part_index:
            return self.part_index[name]
        if name in self.group_index:
            return self.group_index[name]
        raise KeyError(f"unknown part/stream {name!r}; streams {list(self.stream_index)}, "
                       f"parts {list(self.part_index)}, aliases {list(self.aliases)}")

    def stream_dim(self, name: str) -> int:
        return len(self.index(name))

    def stream_joints(self, name: str) -> list[int]:
        """Joint ids whose positions a stream or a part determines, root first. A part alone
        (``root``, ``left_arm``, ...: a ParCo-like tokenizer's stream) lists the root too: without
        the root channels its joints are recovered root-relative, the root at the origin."""
        name = self.aliases.get(name, name)
        if name in self._stream_joints:
            return self._stream_joints[name]
        if name in self.part_joints:
            return [0] + [j for j in self.part_joints[name] if j != 0]
        raise KeyError(f"unknown part/stream {name!r}; streams {list(self.stream_index)}, "
                       f"parts {list(self.part_index)}, aliases {list(self.aliases)}")

    def slice(self, x, name: str):
        idx = self.index(name)
        if isinstance(x, torch.Tensor):
            return x[..., torch.as_tensor(idx, device=x.device)]
        return x[..., idx]

    def split(self, x, names: Sequence[str] | None = None) -> dict:
        """Slices of ``names`` (default: every part, the root first)."""
        return {n: self.slice(x, n) for n in (self.part_index if names is None else names)}

    def merge(self, pieces: Mapping, base=None):
        """Scatter part/stream slices back into full vectors; overlaps averaged.

        Channels no piece covers come from ``base`` (else a ValueError).
        """
        first_name = next(iter(pieces))
        ref = pieces[first_name]
        is_torch = isinstance(ref, torch.Tensor)
        lib_zeros = (lambda s: torch.zeros(s, dtype=ref.dtype, device=ref.device)) if is_torch \
            else (lambda s: np.zeros(s, dtype=ref.dtype))
        shape = tuple(ref.shape[:-1]) + (self.feat_dim,)
        first = lib_zeros(shape)
        delta = lib_zeros(shape)
        count = np.zeros(self.feat_dim, dtype=np.int64)
        seen = np.zeros(self.feat_dim, dtype=bool)
        for name, val in pieces.items():
            idx = self.index(name)
            if val.shape[-1] != len(idx):
                raise ValueError(f"{name}: expected width {len(idx)}, got {val.shape[-1]}")
            new = ~seen[idx]
            if new.any():
                first[..., idx[new]] = val[..., new]
            old = ~new
            if old.any():
                delta[..., idx[old]] = delta[..., idx[old]] + (val[..., old] - first[..., idx[old]])
            seen[idx] = True
            count[idx] += 1
        cnt = torch.as_tensor(np.maximum(count, 1), dtype=ref.dtype, device=ref.device) if is_torch \
            else np.maximum(count, 1).astype(ref.dtype)
        out = first + delta / cnt
        if not seen.all():
            if base is None:
                raise ValueError(f"pieces {list(pieces)} leave {int((~seen).sum())} channels uncovered "
                                 "and no base was given")
            miss = np.nonzero(~seen)[0]
            out[..., miss] = base[..., miss]
        return out

    # ------------------------------------------------------------- positions
    def recover_stream_joints(self, stream_feats: torch.Tensor, stream: str) -> torch.Tensor:
        """Positions (...,T,len(stream_joints),3) of a stream's joints from its features alone."""
        from party.motion.features import recover_from_ric
        full = stream_feats.new_zeros(*stream_feats.shape[:-1], self.feat_dim)
        idx = torch.as_tensor(self.index(stream), device=stream_feats.device)
        full = full.index_copy(full.dim() - 1, idx, stream_feats)
        joints = recover_from_ric(full, self.n_joints)
        return joints[..., self.stream_joints(stream), :]


def group_index(n_joints: int, groups: Mapping[str, Mapping]) -> dict[str, np.ndarray]:
    """Channel indices of disjoint groups of the feature vector (``dataset.parts.groups.<table>``):
    a group is its joints' channels (ric + rot6d + local velocity), with ``root`` the root data
    and joint 0's velocity, and ``contacts`` (left / right) those feet's contact channels. The
    groups must cover every channel exactly once (a ValueError names what overlaps or is left out),
    so ``merge_groups(split_groups(x))`` is ``x`` bit for bit."""
    sl = feature_slices(n_joints)
    feet = {"left": [sl.contacts.start, sl.contacts.start + 1], "right": [sl.contacts.start + 2, sl.contacts.start + 3]}
    out: dict[str, np.ndarray] = {}
    for name, g in groups.items():
        idx = list(range(sl.root.start, sl.root.stop)) + _joint_feature_idx(0, n_joints) if g.get("root") else []
        for j in g["joints"]:
            if not 0 < int(j) < n_joints:
                raise ValueError(f"group {name!r}: joint {j} is not a joint of a {n_joints}-joint skeleton "
                                 "(1..n-1; joint 0 is the root: root: true)")
            idx += _joint_feature_idx(int(j), n_joints)
        for side in g.get("contacts") or []:
            if side not in feet:
                raise ValueError(f"group {name!r}: contacts {side!r} must be left or right")
            idx += feet[side]
        out[name] = np.array(idx, dtype=np.int64)
    allidx = np.concatenate(list(out.values())) if out else np.zeros(0, np.int64)
    dim = 12 * n_joints - 1
    seen, counts = np.unique(allidx, return_counts=True)
    twice = seen[counts > 1]
    missing = np.setdiff1d(np.arange(dim), allidx)
    if len(twice) or len(missing) or len(allidx) != dim:
        raise ValueError(f"groups {list(out)} must cover the {dim} channels once each: {len(twice)} channels in two "
                         f"groups (first {twice[:5].tolist()}), {len(missing)} in none (first {missing[:5].tolist()})")
    return out


def split_groups(x, index: Mapping[str, np.ndarray]) -> dict:
    """The groups' slices of full vectors (..., D)."""
    if isinstance(x, torch.Tensor):
        return {n: x[..., torch.as_tensor(i, device=x.device)] for n, i in index.items()}
    return {n: x[..., i] for n, i in index.items()}


def merge_groups(pieces: Mapping, index: Mapping[str, np.ndarray]):
    """Full vectors from every group's slice (the exact inverse of ``split_groups``)."""
    ref = next(iter(pieces.values()))
    dim = sum(len(i) for i in index.values())
    if isinstance(ref, torch.Tensor):
        out = ref.new_empty(*ref.shape[:-1], dim)
        for n, i in index.items():
            out[..., torch.as_tensor(i, device=ref.device)] = pieces[n]
        return out
    out = np.empty((*ref.shape[:-1], dim), dtype=ref.dtype)
    for n, i in index.items():
        out[..., i] = pieces[n]
    return out
