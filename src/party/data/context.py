"""The one data context every stage reads the prepared dataset through.

``load_context(cfg)`` opens ``<paths.prepared>/index.json``, the feature store, the
dataset's normaliser (``Mean.npy``/``Std.npy``) and the part layout of
``dataset.parts`` (checked against the index's feature width). ``ctx.for_stream(name)``
is the same context seen through one stream (holistic, arms, legs): its feature
channels, their statistics and the tokenizer metadata.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from party.data.datasets import FeatureBank, MotionStore, Normalizer
from party.data.index import Index, load_index
from party.motion.parts import PartLayout


@dataclass
class DataContext:
    index: Index
    store: MotionStore
    normalizer: Normalizer
    layout: PartLayout
    parts_cfg: dict

    @property
    def feat_dim(self) -> int:
        return int(self.index.feat_dim)

    @property
    def n_joints(self) -> int:
        return int(self.index.n_joints)

    def bank(self, split: str, min_len: int) -> FeatureBank:
        return FeatureBank(self.index, split, self.normalizer, self.store, min_len=min_len)

    def for_stream(self, name: str, representation: str = "h3d") -> "StreamData":
        self.layout.index(name)        # unknown stream -> clear KeyError
        return StreamData(self.index, self.store, self.normalizer, self.layout, self.parts_cfg, name, representation)


@dataclass
class StreamData(DataContext):
    """A ``DataContext`` seen through one stream; ``representation`` (``vqvae.model.representation``,
    HumanTOMATO Tab. 9): only the stream's channels of those kinds (``h3d``: all of them)."""
    stream: str = ""
    representation: str = "h3d"

    @property
    def feat_index(self) -> np.ndarray:
        idx = self.layout.index(self.stream)
        if self.representation == "h3d":
            return idx
        from party.motion.features import representation_channels
        return idx[np.isin(idx, representation_channels(self.n_joints, self.representation))]

    @property
    def in_dim(self) -> int:
        return len(self.feat_index)

    def meta(self) -> dict:
        idx = self.index
        return {"stream": self.stream, "dataset": idx.dataset, "skeleton": idx.skeleton,
                "fps": idx.fps, "feat_dim": idx.feat_dim, "n_joints": idx.n_joints,
                "feat_index": [int(i) for i in self.feat_index], "representation": self.representation,
                "stream_joints": [int(j) for j in self.layout.stream_joints(self.stream)]}

    def stats(self) -> tuple[np.ndarray, np.ndarray]:
        return self.normalizer.mean[self.feat_index], self.normalizer.std[self.feat_index]


def load_context(cfg: DictConfig) -> DataContext:
    index = load_index(Path(cfg.paths.prepared))
    parts_cfg = cfg.dataset.parts
    if isinstance(parts_cfg, DictConfig):
        parts_cfg = OmegaConf.to_container(parts_cfg, resolve=True)
    layout = PartLayout.from_config(parts_cfg, index.n_joints)
    if layout.feat_dim != index.feat_dim:
        raise ValueError(f"{index.path}: feat_dim {index.feat_dim} does not match the part table "
                         f"({layout.feat_dim} channels for {index.n_joints} joints)")
    return DataContext(index, MotionStore(index.root, index.feat_dim), Normalizer.load(index.root, index.feat_dim),
                       layout, parts_cfg)


def load_stream_data(cfg: DictConfig, stream: str, representation: str = "h3d") -> StreamData:
    """``load_context(cfg).for_stream(stream, representation)``."""
    return load_context(cfg).for_stream(stream, representation)
