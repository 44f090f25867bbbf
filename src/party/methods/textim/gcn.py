"""Part-GCN spatial feature S of TextIM's module 2 (SPEC-textim §6, paper §3.4 Eq. 4).

Graph (Decision, SPEC §6): SMPL-22, K = 7 adjacency subsets, each symmetric-normalised D^−1/2 A D^−1/2
(isolated nodes get 0): the identity, one subset per part (torso with the pelvis, left/right arm, left/right
leg; 17 intra-part edges) and one inter-part subset (4 edges). 21 edges in all, the SMPL-22 tree. Temporal
edges are realised by temporal convolutions (ST-GCN style).

Node features (13 per joint and frame), read from the 263-d HumanML3D vector (layout of
``party.motion.features.feature_slices``): root-relative position (ric) 3 — joint 0: (0, root height, 0);
rot6d 6 — joint 0: the identity (1, 0, 0, 0, 1, 0); local velocity 3; and a 1/0 flag "joint given". Positions,
rotations and velocities are z-normalised with per-node statistics (``set_feature_stats`` derives them from the
263-d mean/std: each node channel takes its source channel's statistics, the constants of joint 0 map to 0), then
set to 0 where not given and at frames beyond a row's length.

``given`` is a 0/1 channel mask over the 263 channels (B, D) or (B, T, D): a node channel is given when its source
channel is (joint 0's constants follow joint 0's root channels); a joint's flag is 1 when any of its channels is.
Under ``gcn_input: masked_inter`` the model passes m, so channels outside m never reach S.

Network: three blocks [graph conv Σ_k A_k F W_k (Eq. 4) → BN → ReLU → temporal Conv2d (9, 1), stride 1/2/2 → BN
→ ReLU], channels 64/64/128, features zeroed beyond each row's (strided) length after every block; a masked mean
over the valid frames gives F (B, 22, 128); S = F_norm F_normᵀ with F_norm = F/‖F‖ per joint (cosine
similarity). S is symmetric with a unit diagonal (a joint whose feature vector is 0 has similarity 0 with the
others and 1 with itself) and clamped to [−1, 1]. The S condition is its upper triangle without the diagonal
(231 values); the model's denoiser applies Linear(231→d) to it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import nn

from party.motion.features import feature_slices

N_JOINTS = 22
NODE_CHANNELS = 13            # ric 3 + rot6d 6 + local velocity 3 + the given flag
ROT6D_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)

#: the GCN's five parts (the pelvis 0 in the torso), SMPL-22 joint ids
GCN_PARTS: dict[str, tuple[int, ...]] = {
    "torso": (0, 3, 6, 9, 12, 15),
    "left_arm": (13, 16, 18, 20),
    "right_arm": (14, 17, 19, 21),
    "left_leg": (1, 4, 7, 10),
    "right_leg": (2, 5, 8, 11),
}
#: anatomical edges inside each part (17)
INTRA_PART_EDGES: dict[str, tuple[tuple[int, int], ...]] = {
    "torso": ((0, 3), (3, 6), (6, 9), (9, 12), (12, 15)),
    "left_arm": ((13, 16), (16, 18), (18, 20)),
    "right_arm": ((14, 17), (17, 19), (19, 21)),
    "left_leg": ((1, 4), (4, 7), (7, 10)),
    "right_leg": ((2, 5), (5, 8), (8, 11)),
}
#: anatomical edges between parts (4): pelvis-hips and spine3-collars
INTER_PART_EDGES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (9, 13), (9, 14))


def normalize_adjacency(a: torch.Tensor) -> torch.Tensor:
    """D^−1/2 A D^−1/2 (rows/columns of isolated nodes stay 0)."""
    deg = a.sum(-1)
    inv = torch.where(deg > 0, deg.clamp_min(1e-12).rsqrt(), torch.zeros_like(deg))
    return inv[:, None] * a * inv[None, :]


def adjacency_subsets(n_joints: int = N_JOINTS, normalize: bool = True) -> torch.Tensor:
    """(K = 7, J, J): identity, the five intra-part subsets (``GCN_PARTS`` order), the inter-part subset."""
    subsets = [torch.eye(n_joints)]
    for edges in [*INTRA_PART_EDGES.values(), INTER_PART_EDGES]:
        a = torch.zeros(n_joints, n_joints)
        for i, j in edges:
            a[i, j] = a[j, i] = 1.0
        subsets.append(a)
    out = torch.stack(subsets)
    return torch.stack([normalize_adjacency(a) for a in out]) if normalize else out


def _node_source_index(n_joints: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(J, 12) source channel per node channel (-1 for a constant), the constants, and joint 0's root channels."""
    sl = feature_slices(n_joints)
    src = torch.full((n_joints, 12), -1, dtype=torch.long)
    const = torch.zeros(n_joints, 12)
    for j in range(1, n_joints):
        src[j, 0:3] = torch.arange(sl.ric.start + 3 * (j - 1), sl.ric.start + 3 * j)
        src[j, 3:9] = torch.arange(sl.rot.start + 6 * (j - 1), sl.rot.start + 6 * j)
    for j in range(n_joints):
        src[j, 9:12] = torch.arange(sl.vel.start + 3 * j, sl.vel.start + 3 * j + 3)
    src[0, 1] = 3                                    # root height; x, z are 0
    const[0, 3:9] = torch.tensor(ROT6D_IDENTITY)
    return src, const, torch.arange(sl.root.start, sl.root.stop)


def valid_frames(lengths: torch.Tensor | None, n_frames: int, device) -> torch.Tensor:
    """(B, T) bool, True at frames < length (all frames when ``lengths`` is None: callers pass B)."""
    return torch.arange(n_frames, device=device)[None] < lengths.to(device)[:, None]


@dataclass
class PartGCNConfig:
    """``textim.gcn.*`` (SPEC §6)."""
    n_joints: int = N_JOINTS
    channels: tuple[int, ...] = (64, 64, 128)
    strides: tuple[int, ...] = (1, 2, 2)
    temporal_kernel: int = 9

    def __post_init__(self):
        if len(self.channels) != len(self.strides):
            raise ValueError(f"gcn.channels {self.channels} and gcn.strides {self.strides} differ in length")
        if self.temporal_kernel % 2 != 1:
            raise ValueError(f"gcn.temporal_kernel must be odd, got {self.temporal_kernel}")

    @property
    def s_dim(self) -> int:
        return self.n_joints * (self.n_joints - 1) // 2


class GCNOutput(NamedTuple):
    s: torch.Tensor          # (B, J, J) cosine similarity
    upper: torch.Tensor      # (B, J(J−1)/2) upper triangle without the diagonal: the S condition
    features: torch.Tensor   # (B, J, C) F before normalisation


class PartGraphConv(nn.Module):
    """Eq. 4 without the activation: Σ_k A_k F W_k, as one 1×1 conv to K·C_out channels and an einsum."""

    def __init__(self, c_in: int, c_out: int, adjacency: torch.Tensor):
        super().__init__()
        self.k = adjacency.shape[0]
        self.c_out = c_out
        self.register_buffer("A", adjacency.clone(), persistent=False)
        self.conv = nn.Conv2d(c_in, self.k * c_out, kernel_size=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:          # (B, C, T, V)
        b, _, t, v = x.shape
        y = self.conv(x).view(b, self.k, self.c_out, t, v)
        return torch.einsum("bkctv,kvw->bctw", y, self.A.to(y.dtype))


class STBlock(nn.Module):
    """[Part graph conv → BN → ReLU → temporal Conv2d (kernel, 1) → BN → ReLU]."""

    def __init__(self, c_in: int, c_out: int, adjacency: torch.Tensor, kernel: int, stride: int):
        super().__init__()
        self.stride = stride
        self.kernel = kernel
        self.gcn = PartGraphConv(c_in, c_out, adjacency)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.tcn = nn.Conv2d(c_out, c_out, (kernel, 1), stride=(stride, 1), padding=(kernel // 2, 0))
        self.bn2 = nn.BatchNorm2d(c_out)
        self.relu = nn.ReLU()

    def out_lengths(self, lengths: torch.Tensor) -> torch.Tensor:
        pad = self.kernel // 2
        return torch.div(lengths + 2 * pad - self.kernel, self.stride, rounding_mode="floor") + 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.relu(self.bn1(self.gcn(x)))
        return self.relu(self.bn2(self.tcn(x)))


class PartGCN(nn.Module):
    """Motion features (B, T, 263), a given-channel mask and lengths → ``GCNOutput`` (S, its 231-d upper
    triangle, F)."""

    def __init__(self, cfg: PartGCNConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or PartGCNConfig()
        j = cfg.n_joints
        self.feat_dim = 12 * j - 1
        src, const, root = _node_source_index(j)
        self.register_buffer("node_src", src, persistent=False)
        self.register_buffer("node_const", const, persistent=False)
        self.register_buffer("root_channels", root, persistent=False)
        self.register_buffer("node_mean", torch.zeros(j, 12))
        self.register_buffer("node_std", torch.ones(j, 12))
        self.register_buffer("A", adjacency_subsets(j), persistent=False)
        iu = torch.triu_indices(j, j, offset=1)
        self.register_buffer("triu", iu, persistent=False)
        blocks, c_in = [], NODE_CHANNELS
        for c_out, stride in zip(cfg.channels, cfg.strides):
            blocks.append(STBlock(c_in, c_out, self.A, cfg.temporal_kernel, stride))
            c_in = c_out
        self.blocks = nn.ModuleList(blocks)

    @torch.no_grad()
    def set_feature_stats(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Per-node z-normalisation from the 263-d feature mean/std (constants of joint 0 → mean = constant,
        std = 1, so they normalise to 0)."""
        mean = torch.as_tensor(mean, dtype=torch.float32).to(self.node_mean.device)
        std = torch.as_tensor(std, dtype=torch.float32).to(self.node_std.device)
        is_const = self.node_src < 0
        idx = self.node_src.clamp_min(0)
        self.node_mean.copy_(torch.where(is_const, self.node_const, mean[idx]))
        self.node_std.copy_(torch.where(is_const, torch.ones_like(self.node_const), std[idx]))

    def node_features(self, x: torch.Tensor, given: torch.Tensor, lengths: torch.Tensor | None = None
                      ) -> torch.Tensor:
        """(B, T, J, 13) z-normalised node features, 0 where not given or beyond the length, plus the flag."""
        b, n, d = x.shape
        if d != self.feat_dim:
            raise ValueError(f"expected {self.feat_dim}-d features for {self.cfg.n_joints} joints, got {d}")
        given = given.to(device=x.device).bool()
        if given.dim() == 2:
            given = given[:, None, :].expand(b, n, d)
        is_const = self.node_src < 0
        idx = self.node_src.clamp_min(0)
        raw = torch.where(is_const, self.node_const.to(x.dtype), x[..., idx])            # (B, T, J, 12)
        root_given = given[..., self.root_channels].any(-1)                                # (B, T)
        ch_given = torch.where(is_const, root_given[..., None, None], given[..., idx])     # (B, T, J, 12)
        if lengths is not None:
            ch_given = ch_given & valid_frames(lengths, n, x.device)[:, :, None, None]
        z = (raw - self.node_mean.to(x.dtype)) / self.node_std.to(x.dtype)
        z = torch.where(ch_given, z, torch.zeros((), dtype=x.dtype, device=x.device))
        flag = ch_given.any(-1, keepdim=True).to(x.dtype)
        return torch.cat([z, flag], dim=-1)

    def forward(self, x: torch.Tensor, given: torch.Tensor, lengths: torch.Tensor | None = None) -> GCNOutput:
        b, n, _ = x.shape
        if lengths is None:
            lengths = torch.full((b,), n, dtype=torch.long, device=x.device)
        lengths = lengths.to(x.device).long()
        h = self.node_features(x, given, lengths).permute(0, 3, 1, 2)                     # (B, 13, T, J)
        cur = lengths
        for block in self.blocks:
            h = block(h)
            cur = block.out_lengths(cur)
            keep = valid_frames(cur, h.shape[2], x.device)[:, None, :, None]
            h = h * keep.to(h.dtype)
        cnt = cur.clamp_min(1).to(h.dtype)[:, None, None]
        feats = h.sum(2).transpose(1, 2) / cnt                                             # (B, J, C)
        norm = feats / feats.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        s = norm @ norm.transpose(1, 2)
        s = (0.5 * (s + s.transpose(1, 2))).clamp(-1.0, 1.0)                               # exactly symmetric
        eye = torch.eye(s.shape[-1], dtype=torch.bool, device=s.device)
        s = torch.where(eye, torch.ones((), dtype=s.dtype, device=s.device), s)
        return GCNOutput(s, s[:, self.triu[0], self.triu[1]], feats)
