"""What the rest of ParTY may use of a tokenizer, as ``typing.Protocol``s.

- ``Tokenizer``: a trained tokenizer as token extraction (``party extract_tokens``)
  and evaluation (``party.evaluation.sources``) use it. ``party.tokenizers.Tokenizer``
  (any family, see ``party.tokenizers.vqvae.build_tokenizer``) satisfies it.
- ``Codec``: the least a reconstruction source accepts (window, encode, decode on
  features normalised with the dataset's statistics), e.g. a test double.
- ``TokenizerModel``: the network a tokenizer *family* builds, ``cls(in_dim, cfg)``
  (``VQVAE`` for ``temporal_vq``); ``party.tokenizers.Tokenizer`` wraps one.

Codes: (B, n) long for one code level, (B, n, Q) for Q > 1 levels (residual /
hierarchical quantizers, level 0 first); a group that covers only padding holds -1
(every level). ``valid_groups`` gives the groups that hold codes.

Members are methods and properties (no tensor attributes): from Python 3.12 on
``isinstance`` looks members up statically, and an ``nn.Module``'s buffers are not.
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch


@runtime_checkable
class Codec(Protocol):
    @property
    def window(self) -> int:
        """Frames per token."""

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised features (B, T, D) -> codes (B, T // window[, Q])."""

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes (B, n[, Q]) -> normalised features (B, n * window, D)."""


@runtime_checkable
class Tokenizer(Protocol):
    """A trained tokenizer of one stream, with its own normalisation statistics."""

    meta: dict
    """stream, dataset, feat_dim, n_joints, feat_index (stream channel -> full-vector channel),
    stream_joints, skeleton, fps."""

    @property
    def window(self) -> int:
        """Frames per token (w)."""

    @property
    def tail(self) -> str:
        """``crop`` (a last partial group of frames is dropped) | ``pad`` (padded)."""

    @property
    def codebook_size(self) -> int:
        """Codes are in [0, codebook_size) at every level."""

    @property
    def levels(self) -> int:
        """Code levels per token (Q); 1: codes (B, n), Q > 1: codes (B, n, Q)."""

    @property
    def family(self) -> str:
        """The tokenizer family (``vqvae.model.family``), e.g. ``temporal_vq``."""

    @property
    def device(self) -> torch.device:
        """Where inputs of ``encode`` / ``normalize`` must be."""

    def stats(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, std) (D,) of the stream's raw features, as trained."""

    def normalize(self, raw: torch.Tensor) -> torch.Tensor:
        """Raw stream features (..., D) -> normalised."""

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised stream features (..., D) -> raw."""

    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised features (B, T, D) (+ mask (B, T) of real frames) -> codes (B, n[, Q]),
        -1 on groups of padding only; n = number of tokens for T frames under ``tail``."""

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes (B, n[, Q]) -> normalised features (B, n * window, D)."""

    def n_params(self) -> int:
        """Parameter count (efficiency tables)."""

    def to(self, *args: Any, **kwargs: Any) -> Any:
        """Move to a device (``nn.Module.to``); returns the tokenizer."""

    def eval(self) -> Any:
        """Inference mode (``nn.Module.eval``); returns the tokenizer."""


@runtime_checkable
class TokenizerModel(Protocol):
    """The network of a tokenizer family: built as ``cls(in_dim, cfg)`` from ``vqvae.model``
    (plus the stream's overrides), saved as its ``state_dict`` with ``cfg`` and ``in_dim``."""

    window: int
    tail: str
    in_dim: int
    cfg: dict

    @property
    def codebook_size(self) -> int: ...

    @property
    def levels(self) -> int: ...

    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised (B, T, D) -> (codes (B, n[, Q]) with -1 on padded groups, node mask (B, n))."""

    def decode(self, codes: torch.Tensor) -> torch.Tensor: ...


def valid_groups(codes: torch.Tensor) -> torch.Tensor:
    """(B, n) bool: the token groups of codes (B, n) or (B, n, Q) that are not padding."""
    valid = codes >= 0
    return valid if valid.dim() == 2 else valid.all(-1)
