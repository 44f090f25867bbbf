"""Evaluator matching: the optional step decay of `evaluator.train` (lr until `milestone`, then
`lr_after`; both null: a constant lr, the default)."""
from __future__ import annotations

import pytest
import torch

from party.evaluation.lit import MatchLit


class _Ev(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.text_encoder, self.text_proj = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
        self.motion_encoder, self.movement_encoder = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)


def _lrs(lit: MatchLit, steps: int) -> list[float]:
    out = lit.configure_optimizers()
    if isinstance(out, torch.optim.Optimizer):
        return [out.param_groups[0]["lr"]] * steps
    opt, sched = out["optimizer"], out["lr_scheduler"]["scheduler"]
    assert out["lr_scheduler"]["interval"] == "step"
    lrs = []
    for _ in range(steps):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    return lrs


def test_constant_by_default_and_step_decay_at_the_milestone():
    assert _lrs(MatchLit(_Ev(), 3e-4, 10.0, 0.5, True), 4) == [3e-4] * 4
    lrs = _lrs(MatchLit(_Ev(), 1e-3, 10.0, 0.5, True, lr_after=1e-4, milestone=3), 5)
    assert lrs[:3] == pytest.approx([1e-3] * 3) and lrs[3:] == pytest.approx([1e-4] * 2)
    with pytest.raises(ValueError, match="lr_after and milestone together"):
        MatchLit(_Ev(), 1e-3, 10.0, 0.5, True, milestone=3)
