"""DDP on 2 CPU processes (gloo) gives the weights of one process with the same global batch."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).with_name("ddp_equivalence.py")


def _train(devices: int, out: Path) -> dict:
    env = os.environ | {"PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    res = subprocess.run([sys.executable, str(SCRIPT), str(devices), "8", str(out)], capture_output=True, text=True,
                         timeout=600, env=env, cwd=out.parent)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-5000:]
    if devices > 1:
        assert "distributed_backend=gloo" in res.stderr + res.stdout
    return torch.load(out, weights_only=True)


@pytest.mark.slow
def test_two_process_ddp_weights_equal_one_process(tmp_path):
    (tmp_path / "one").mkdir()
    (tmp_path / "two").mkdir()
    one = _train(1, tmp_path / "one" / "w.pt")
    two = _train(2, tmp_path / "two" / "w.pt")
    from generator.tiny_spec import build
    init = build("party", seed=0, model={"dropout": 0.0}).state_dict()
    moved = [k for k in one if not torch.equal(one[k], init[k])]
    assert len(moved) > 0.5 * len(one)                      # the two steps changed the weights
    for k in one:
        torch.testing.assert_close(two[k], one[k], rtol=1e-4, atol=1e-5, msg=k)
