"""Helpers of the evaluation stages over the data context (``party.data.context``)."""

from __future__ import annotations

import logging

import numpy as np

from party.motion.parts import PartLayout

log = logging.getLogger(__name__)


def stream_channels(layout: PartLayout, stream: str, feat_dim: int, drop_contacts: bool) -> list[int]:
    """Feature channels an evaluator of ``stream`` reads (the last 4 = foot contacts dropped, as the reference)."""
    idx = [int(i) for i in layout.index(stream)]
    if drop_contacts:
        idx = [i for i in idx if i < feat_dim - 4]
    return idx


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
