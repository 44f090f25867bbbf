"""Average inference time (AIT) per sample (paper Tab. 4); parameter counts: ``party.training.count_params``."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
import torch


def _sync() -> None:
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def measure_ait(fn: Callable, inputs: Sequence, n: int = 100, warmup: int = 5) -> dict[str, float]:
    """Average wall time of ``fn(x)`` over ``n`` samples (inputs cycled), after ``warmup`` calls.

    Each call is one sample (batch of one, as the paper's AIT); CUDA work is
    synchronised before and after every call so queued kernels are counted.
    Runs under ``torch.inference_mode``. Returns milliseconds.
    """
    if not inputs:
        raise ValueError("measure_ait needs at least one input")
    if n < 1:
        raise ValueError(f"measure_ait needs n >= 1, got {n}")
    times = []
    with torch.inference_mode():
        for i in range(warmup):
            fn(inputs[i % len(inputs)])
        _sync()
        for i in range(n):
            x = inputs[i % len(inputs)]
            t0 = time.perf_counter()
            fn(x)
            _sync()
            times.append(time.perf_counter() - t0)
    t = np.asarray(times) * 1e3
    return {"ait_ms": float(t.mean()), "ait_ms_std": float(t.std()), "n": n}
