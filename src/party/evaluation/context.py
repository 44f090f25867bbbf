"""What the evaluation stages need from the prepared dataset, in one place."""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from party.data import FeatureBank, MotionStore, Normalizer, load_index
from party.data.index import Index
from party.motion.parts import PartLayout

log = logging.getLogger(__name__)


def cfg_get(cfg, dotted: str, default=None):
    v = OmegaConf.select(cfg, dotted, default=default) if isinstance(cfg, DictConfig) else default
    return default if v is None else v


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


def load_context(cfg: DictConfig) -> DataContext:
    prepared = Path(cfg_get(cfg, "paths.prepared", "data/prepared"))
    index = load_index(prepared)
    parts_cfg = cfg_get(cfg, "dataset.parts")
    if parts_cfg is None:
        raise ValueError("config has no dataset.parts (part table of the skeleton); see conf/dataset/parts/")
    if isinstance(parts_cfg, DictConfig):
        parts_cfg = OmegaConf.to_container(parts_cfg, resolve=True)
    layout = PartLayout.from_config(parts_cfg, index.n_joints)
    if layout.feat_dim != index.feat_dim:
        raise ValueError(f"{index.path}: feat_dim {index.feat_dim} does not match the part table "
                         f"({layout.feat_dim} channels for {index.n_joints} joints)")
    return DataContext(index, MotionStore(index.root, index.feat_dim), Normalizer.load(index.root, index.feat_dim),
                       layout, parts_cfg)


def stream_channels(layout: PartLayout, stream: str, feat_dim: int, drop_contacts: bool) -> list[int]:
    """Feature channels an evaluator of ``stream`` reads (the last 4 = foot contacts dropped, as the reference)."""
    idx = [int(i) for i in layout.index(stream)]
    if drop_contacts:
        idx = [i for i in idx if i < feat_dim - 4]
    return idx


def resolve_accelerator(name: str | None) -> torch.device:
    if name in (None, "auto", "gpu", "cuda"):
        if torch.cuda.is_available():
            return torch.device("cuda")
        if name in ("gpu", "cuda"):
            log.warning("accelerator %s requested but CUDA is not available; using the CPU", name)
        return torch.device("cpu")
    return torch.device("cpu" if name == "cpu" else name)


@contextlib.contextmanager
def tracking_run(cfg: DictConfig, stage: str, enabled: bool):
    """``party.tracking.start_run`` (itself a no-op run when ``tracking.enabled`` is false);
    a ``NullRun`` when the stage's own switch is off. The run has ``log_metrics``,
    ``log_file``, ``log_text``, ``log_json`` in either case."""
    from party import tracking

    if not enabled:
        yield tracking.NullRun(stage)
        return
    with tracking.start_run(cfg, stage) as run:
        yield run


def log_metrics_flat(metrics: dict, prefix: str = "") -> dict[str, float]:
    """Flatten nested metric dicts to MLflow-friendly keys (a/b/c), numbers only."""
    out: dict[str, float] = {}
    for k, v in metrics.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(log_metrics_flat(v, key + "/"))
        elif isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool) and np.isfinite(v):
            out[key] = float(v)
    return out
