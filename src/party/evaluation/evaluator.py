"""Text-motion matching evaluator of Guo et al. 2022 (T2M ``text_mot_match``).

Module names, parameter names and shapes follow the reference
``networks/modules.py`` so that ``text_mot_match/model/finest.tar`` (keys
``text_encoder``, ``motion_encoder``, ``movement_encoder``) loads with
``load_state_dict(strict=True)``. Reference sizes for HumanML3D: word 300,
POS 15, text hidden 512, co-embedding 512, movement hidden 512 / latent 512,
motion hidden 1024, input = 263 - 4 features (foot contacts dropped).

``Evaluator`` bundles the three encoders with their input adapters: which
feature channels to read (a stream's channels, contacts dropped), the
normalisation statistics, the text featuriser and an optional projection of
text-encoder features to the word width. It takes *raw* (de-normalised)
features, so every motion source is compared through the same pipeline.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn as nn
from torch.nn.utils.rnn import pack_padded_sequence


def init_weight(m: nn.Module) -> None:
    if isinstance(m, (nn.Conv1d, nn.Linear, nn.ConvTranspose1d)):
        nn.init.xavier_normal_(m.weight)
        if m.bias is not None:
            nn.init.constant_(m.bias, 0)


class MovementConvEncoder(nn.Module):
    """Two stride-2 convolutions: (B, T, D) -> (B, T/4, latent)."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int, dropout: float = 0.2):
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, 4, 2, 1), nn.Dropout(dropout), nn.LeakyReLU(0.2),
            nn.Conv1d(hidden_size, output_size, 4, 2, 1), nn.Dropout(dropout), nn.LeakyReLU(0.2),
        )  # fmt: skip
        self.out_net = nn.Linear(output_size, output_size)
        self.main.apply(init_weight)
        self.out_net.apply(init_weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out_net(self.main(x.permute(0, 2, 1)).permute(0, 2, 1))


class MovementConvDecoder(nn.Module):
    """Mirror of the encoder (used only to pre-train it as an autoencoder, as the reference does)."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int):
        super().__init__()
        self.main = nn.Sequential(
            nn.ConvTranspose1d(input_size, hidden_size, 4, 2, 1), nn.LeakyReLU(0.2),
            nn.ConvTranspose1d(hidden_size, output_size, 4, 2, 1), nn.LeakyReLU(0.2),
        )  # fmt: skip
        self.out_net = nn.Linear(output_size, output_size)
        self.main.apply(init_weight)
        self.out_net.apply(init_weight)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.out_net(self.main(z.permute(0, 2, 1)).permute(0, 2, 1))


class _BiGRUCo(nn.Module):
    """Shared body: input_emb -> BiGRU (learned initial state) -> output_net on the final states."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int):
        super().__init__()
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = nn.Sequential(
            nn.Linear(hidden_size * 2, hidden_size), nn.LayerNorm(hidden_size), nn.LeakyReLU(0.2),
            nn.Linear(hidden_size, output_size),
        )  # fmt: skip
        self.input_emb.apply(init_weight)
        self.output_net.apply(init_weight)
        self.hidden_size = hidden_size
        self.hidden = nn.Parameter(torch.randn((2, 1, hidden_size)))

    def _encode(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        h0 = self.hidden.repeat(1, x.shape[0], 1)
        lengths = torch.as_tensor(lengths).long().cpu().clamp(min=1, max=x.shape[1])
        packed = pack_padded_sequence(self.input_emb(x), lengths, batch_first=True, enforce_sorted=False)
        _, last = self.gru(packed, h0)  # (2, B, H), back in input order
        return self.output_net(torch.cat([last[0], last[1]], dim=-1))


class TextEncoderBiGRUCo(_BiGRUCo):
    def __init__(self, word_size: int = 300, pos_size: int = 15, hidden_size: int = 512, output_size: int = 512):
        super().__init__(word_size, hidden_size, output_size)
        self.pos_emb = nn.Linear(pos_size, word_size)
        self.pos_emb.apply(init_weight)

    def forward(self, word_embs: torch.Tensor, pos_onehot: torch.Tensor, cap_lens) -> torch.Tensor:
        return self._encode(word_embs + self.pos_emb(pos_onehot), cap_lens)


class MotionEncoderBiGRUCo(_BiGRUCo):
    def forward(self, movements: torch.Tensor, m_lens) -> torch.Tensor:
        return self._encode(movements, m_lens)


MotionEncoderBiGRU = MotionEncoderBiGRUCo  # name used in the issue text


class Evaluator(nn.Module):
    """Text and motion encoders plus input adapters; embeds captions and raw feature sequences."""

    def __init__(self, channels: Sequence[int], mean: np.ndarray, std: np.ndarray, featurizer,
                 text_in_dim: int | None = None, word_size: int = 300, pos_size: int = 15,
                 text_hidden: int = 512, coemb: int = 512, movement_hidden: int = 512,
                 movement_latent: int = 512, motion_hidden: int = 1024, unit_length: int = 4,
                 dropout: float = 0.2, stream: str = "holistic", kind: str = "trained", pad_to: int = 196):
        super().__init__()
        self.stream, self.kind, self.unit_length, self.pad_to = stream, kind, unit_length, pad_to
        self.featurizer = featurizer
        self.register_buffer("channels", torch.as_tensor(list(channels), dtype=torch.long))
        self.register_buffer("mean", torch.as_tensor(np.asarray(mean), dtype=torch.float32))
        std = torch.as_tensor(np.asarray(std), dtype=torch.float32)
        self.register_buffer("std", torch.where(std > 0, std, torch.ones_like(std)))
        project = bool(text_in_dim) and text_in_dim != word_size
        self.text_proj = nn.Linear(text_in_dim, word_size) if project else nn.Identity()
        self.text_encoder = TextEncoderBiGRUCo(word_size, pos_size, text_hidden, coemb)
        self.movement_encoder = MovementConvEncoder(len(channels), movement_hidden, movement_latent, dropout)
        self.motion_encoder = MotionEncoderBiGRUCo(movement_latent, motion_hidden, coemb)

    @property
    def device(self) -> torch.device:
        return self.mean.device

    @property
    def feat_dim(self) -> int:
        return self.mean.shape[0]

    def motion_input(self, feats: torch.Tensor, lengths, normalized: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw (B, T, D) -> normalised, channel-selected, zero beyond each length (cropped to units).

        The reference loaders pad every motion to 196 frames (``pad_to``): the convolutions
        then see zeros past a clip's end whatever the batch's longest clip, so an embedding
        does not depend on its batch. The embedding reads the movement codes of a clip's own
        units only, and those see at most 3 frames past its end (two k=4, s=2, p=1
        convolutions), so the batch is padded (or trimmed) to its longest clip plus one unit
        instead: the same embeddings, without convolving up to 196 - T frames of zeros.
        Clips longer than ``pad_to`` are kept whole, as before.
        """
        x = torch.as_tensor(feats, dtype=torch.float32, device=self.device)
        if x.shape[-1] != self.feat_dim:
            raise ValueError(f"{self.stream} evaluator expects {self.feat_dim}-dim features, got {x.shape[-1]}")
        lengths = torch.as_tensor(lengths, dtype=torch.long, device=self.device)
        lengths = (lengths // self.unit_length) * self.unit_length
        if (lengths < self.unit_length).any():
            raise ValueError(f"motion shorter than one evaluator unit ({self.unit_length} frames)")
        if x.shape[1] <= self.pad_to:
            need = min(self.pad_to, int(lengths.max()) + self.unit_length)
            x = torch.nn.functional.pad(x, (0, 0, 0, need - x.shape[1])) if x.shape[1] < need else x[:, :need]
        if not normalized:
            x = (x - self.mean) / self.std
        x = x[..., self.channels]
        mask = torch.arange(x.shape[1], device=self.device)[None, :] < lengths[:, None]
        return x * mask[..., None], lengths

    def embed_motion(self, feats, lengths, normalized: bool = False) -> torch.Tensor:
        x, lengths = self.motion_input(feats, lengths, normalized)
        movements = self.movement_encoder(x)
        return self.motion_encoder(movements, lengths // self.unit_length)

    def embed_text(self, captions: Sequence[str], tokens: Sequence[Sequence[str] | None]) -> torch.Tensor:
        word, pos, lens = self.featurizer(captions, tokens)
        word, pos = word.to(self.device), pos.to(self.device)
        return self.text_encoder(self.text_proj(word), pos, lens)

    def reference_state(self) -> dict:
        """State dicts under the reference checkpoint's keys."""
        return {"text_encoder": self.text_encoder.state_dict(), "motion_encoder": self.motion_encoder.state_dict(),
                "movement_encoder": self.movement_encoder.state_dict()}
