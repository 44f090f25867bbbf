"""HumanTOMATO Tab. 9's representations (``vqvae.model.representation``; SPEC-humantomato §1): a
tokenizer reads the stream's channels of the chosen kinds only (h3d 263, no_rot 137, no_rot_no_vel 71
on 22 joints), its positions come from root + ric alone, so MPJPE and the rest are measured as for
h3d, and no token store or generator reads such a tokenizer."""
import json
import math

import numpy as np
import pytest
import torch

from party.motion.features import REPRESENTATIONS, feature_slices, recover_from_ric, representation_channels


def test_channel_counts_and_kinds():
    sl = feature_slices(22)
    h3d, no_rot, no_rv = (representation_channels(22, r) for r in ("h3d", "no_rot", "no_rot_no_vel"))
    assert (len(h3d), len(no_rot), len(no_rv)) == (263, 137, 71)             # SPEC §1: 4 + 63 + 66 + 4, 4 + 63 + 4
    assert np.array_equal(h3d, np.arange(263)) and np.all(np.diff(no_rot) > 0)
    rot = np.arange(sl.rot.start, sl.rot.stop)
    vel = np.arange(sl.vel.start, sl.vel.stop)
    assert not np.isin(rot, no_rot).any() and np.isin(vel, no_rot).all()
    assert not np.isin(vel, no_rv).any() and np.isin(np.arange(sl.ric.start, sl.ric.stop), no_rv).all()
    assert set(REPRESENTATIONS) == {"h3d", "no_rot", "no_rot_no_vel"}
    with pytest.raises(ValueError, match="representation must be one of"):
        representation_channels(22, "no_root")


def test_positions_need_only_root_and_ric():
    """What the tokenizer's joints() recovers from a representation's channels alone (the rest zero)
    is what the whole vector gives: the errors of Tab. 9 are measured on the same positions."""
    x = torch.randn(2, 10, 263, dtype=torch.float64)
    for r in ("no_rot", "no_rot_no_vel"):
        keep = torch.as_tensor(representation_channels(22, r))
        part = torch.zeros_like(x)
        part[..., keep] = x[..., keep]
        assert torch.equal(recover_from_ric(part, 22), recover_from_ric(x, 22))


def test_the_tab9_grid_reads_each_representation():
    from pathlib import Path

    from party.config import compose
    from party.sweep import apply_overrides, expand, load_sweep
    from party.tokenizers.config import stream_config

    cfg = compose([], Path("conf"))
    reps = {}
    for p in expand(load_sweep("tomato_representation", Path("conf/sweep"))):
        model = stream_config(apply_overrides(cfg, p["overrides"]).vqvae, "holistic")["model"]
        assert (model["family"], model["window"], model["codebook_size"]) == ("vq", 4, 512)
        reps[p["label"]] = len(representation_channels(22, model["representation"]))
    assert reps == {"h3d": 263, "no_rot_no_vel": 71, "no_rot": 137}


@pytest.mark.parametrize("rep,dim", [("no_rot", 137), ("no_rot_no_vel", 71)])
def test_a_tokenizer_trains_on_a_representation_and_no_token_store_reads_it(tiny_prepared, tmp_path, rep, dim):
    from party.stages import extract_tokens
    from party.tokenizers import load_tokenizer
    from party.tokenizers.train import train_tokenizer
    from tok_helpers import tiny_cfg

    c = tiny_cfg(tmp_path, tiny_prepared, **{"vqvae.tokenizers.holistic.family": "vq", "vqvae.streams": "[holistic]",
                                             "vqvae.model.representation": rep, "vqvae.model.lte.enabled": False,
                                             "vqvae.model.gte.enabled": False})
    train_tokenizer(c, "holistic", tmp_path / "tokenizers/holistic")
    m = json.loads((tmp_path / "tokenizers/holistic/metrics.json").read_text())
    assert all(math.isfinite(m[k]) for k in ("val/mpjpe_mm", "val/pa_mpjpe_mm", "val/accel_mm"))
    tok = load_tokenizer(tmp_path / "tokenizers/holistic")
    assert tok.model.in_dim == dim and tok.meta["representation"] == rep
    assert tok.meta["feat_index"] == representation_channels(22, rep).tolist()
    with pytest.raises(ValueError, match=f"reads the {rep} representation"):
        extract_tokens.run(c)
