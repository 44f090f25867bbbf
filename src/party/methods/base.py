"""What a method family provides, and what a trained method gives the stages.

A **family** (``MethodFamily`` subclass, registered with ``party.methods.register``):

- ``name``: the value of ``family:`` in ``generator.methods.<m>``;
- ``Config``: a dataclass, the schema of that entry (``Literal`` fields for enums; checked
  by ``party.schema.validate``);
- ``consumes``: what its training reads besides captions (``"tokens"``: the token stores of
  ``token_streams``, by default ``generator.streams``; ``"features"``: the prepared motion
  features; ``()``: nothing);
- ``train(cfg, method, out_dir, run, callbacks)``: train ``generator.methods.<method>`` and
  write ``out_dir`` whole (``method.json`` with ``party.methods.store.write_method_json``
  plus the family's own files); returns the metrics dict;
- ``load(folder, map_location)`` -> a ``TrainedMethod``;
- ``recognizes(folder)``: whether a folder without ``method.json`` was written by it.

A **trained method** (``TrainedMethod``) is what generation uses: ``bind`` it to the data
context (normalisation, part layout) and the tokenizers folder where it decodes codes (checked
against the digests recorded in ``meta["built_from"]`` at training, ``party.provenance``), then
``sample(text_emb, lengths, gcfg, generator)`` gives raw features (T, D) per row; a method whose
``reads_captions`` is true embeds the captions itself and is called with ``texts=`` (the captions
of the rows) too (``party.generator.generate.generate_batches``). Lengths are
the method's own business: ``gt_lengths`` (from the ground-truth clips) and ``frame_lengths``
(from requested frame counts) return a dict of (B,) tensors that the stages slice per batch
and hand back to ``sample``.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
import torch


class TrainedMethod:
    """A trained generator of one family, ready to sample (see the module docstring)."""

    #: whether its output depends on the text (the trivial baselines' does not)
    reads_text: ClassVar[bool] = True
    #: the folder it was loaded from (``party.provenance.attach``), None for a model in training
    source: str | None = None
    #: whether ``sample`` needs the captions themselves (``texts=``) beside their embeddings
    reads_captions: bool = False
    #: a registry package's folder of the files ``package_files`` named (``party.generator.package``)
    files_dir: str | None = None

    def __init__(self, meta: Mapping[str, Any]):
        self.meta = dict(meta)

    @property
    def method(self) -> str:
        return str(self.meta.get("method", "?"))

    # --------------------------------------------------------------- decoding context
    def bind(self, ctx, tokenizers_dir=None, allow_mismatch: bool = False) -> "TrainedMethod":
        """Prepare decoding against the data context ``ctx`` (``party.data.context.DataContext``)
        and, for token methods, the tokenizers folder (None: the one the method was trained with),
        whose tokenizers must be the ones it recorded (``party.provenance``; ``allow_mismatch``:
        a warning instead of the error)."""
        self.ctx = ctx
        return self

    def package_files(self) -> dict:
        """Files besides its folder and tokenizers that generation reads ({relative name: path}): a
        registry package copies them and sets ``files_dir`` to where they are."""
        return {}

    def tokenizer_streams(self, whole_stream: str) -> list[str]:
        """The tokenizers its codes decode with (a registry package copies them); none by default."""
        return []

    # --------------------------------------------------------------- lengths
    def gt_lengths(self, cfg, clip_ids: Sequence[str]) -> dict[str, torch.Tensor] | None:
        """Target lengths of the ground-truth clips ``clip_ids`` ({key: (B,)}), or None."""
        return None

    def frame_lengths(self, frames: Sequence[int | None] | None) -> dict[str, torch.Tensor] | None:
        """Target lengths for requested frame counts ({key: (B,)}), None when none is given."""
        return None

    # --------------------------------------------------------------- generation
    def sample(self, text_emb: torch.Tensor, lengths: Mapping[str, torch.Tensor] | None, gcfg,
               generator: torch.Generator) -> list[np.ndarray]:
        """Raw features (T, D) for every row of ``text_emb`` (B, D_text); ``gcfg`` is
        ``generator.generate``; ``generator`` the seeded random stream. A method that
        ``reads_captions`` takes ``texts`` (the B captions) as a keyword too."""
        raise NotImplementedError

    def param_counts(self) -> dict[str, int]:
        return {"total": 0}

    def index_fields(self, method_cfg: Mapping) -> dict:
        """Extra fields of a generated run's ``index.json`` (e.g. ablation switches)."""
        return {}


class MethodFamily:
    """A family of generator methods (see the module docstring)."""

    name: ClassVar[str] = ""
    Config: ClassVar[type] = object
    consumes: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def train(cls, cfg, method: str, out_dir, run, callbacks: list | None = None) -> dict:
        raise NotImplementedError

    @classmethod
    def load(cls, folder, map_location: str = "cpu") -> TrainedMethod:
        raise NotImplementedError

    @classmethod
    def recognizes(cls, folder) -> bool:
        return False

    @classmethod
    def token_streams(cls, cfg, method: str) -> list[str]:
        """The token stores a token method of this family trains on (default ``generator.streams``)."""
        return [str(s) for s in cfg.generator.streams]

    @classmethod
    def describe(cls, cfg, method: str) -> dict:
        """What tells this method apart within its family (metrics.json, ``party.<key>`` run tags)."""
        return {}

    @classmethod
    def step_config(cls, entry: Mapping) -> dict:
        """The part of ``generator.methods.<m>`` that changes a training step (its resume key)."""
        from party.schema import step_keys
        return step_keys(cls.Config, dict(entry))
