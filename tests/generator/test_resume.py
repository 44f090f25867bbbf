"""An interrupted generator training, resumed from its rolling checkpoint, ends with the weights of
an uninterrupted one: the batch sampler (length-bucketed or uniform) continues the epoch where the
checkpoint left it (not from the epoch's first batch) and the dropout / null-condition / corruption random
streams are restored."""
import lightning as L
import numpy as np
import pytest
import torch
from torch.utils.data import Dataset

from party.generator.data import LengthBucketBatchSampler
from party.generator.lit import GeneratorLit
from party.generator.train import _loader, fit_resumable
from party.training import AtomicCheckpoint

from .ddp_equivalence import PAD, items
from .tiny_spec import VOCAB, build

OPTIM = {"lr": 1e-3, "lr_after": 1e-4, "milestone": 4, "betas": [0.5, 0.99], "weight_decay": 0.0}


class Items(Dataset):
    """What ``_loader`` needs of a ``GeneratorDataset``: items, ``pad``, ``streams``, ``lengths``."""

    def __init__(self, n: int):
        self.items, self.pad, self.streams = items(n), PAD, ("holistic", "arms", "legs")
        for k, it in enumerate(self.items):           # varied lengths, so that bucketing sorts something
            it["lengths"]["holistic"] = n_h = 3 + k % 6
            it["codes"]["holistic"] = it["codes"]["holistic"][:n_h]

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        return self.items[i]

    def lengths(self, stream: str) -> np.ndarray:
        return np.array([it["lengths"][stream] for it in self.items])


class Seen(L.Callback):
    def __init__(self):
        self.batches = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.batches.append(tuple(batch["clip_id"]))


def _train(ds, max_steps: int, ckpt, resume=None, bucket_pool: int = 2):
    torch.manual_seed(0)
    model = build("party", seed=0, model={"dropout": 0.2, "cond_drop": 0.3})
    lit = GeneratorLit(model, OPTIM, {"enabled": True, "prob": 0.5}, VOCAB, seed=0)
    seen = Seen()
    trainer = L.Trainer(max_steps=max_steps, accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        callbacks=[AtomicCheckpoint(ckpt, 0), seen], default_root_dir=str(ckpt.parent))
    loader = _loader(ds, 2, True, 0, seed=5, bucket_pool=bucket_pool)
    fit_resumable(trainer, lit, loader, None, resume)
    return {k: v.detach().clone() for k, v in model.state_dict().items()}, seen.batches


# mid-epoch, at an epoch's end, in the second epoch; length-bucketed and uniform batches (pool 0)
@pytest.mark.parametrize("stop,pool", [(3, 2), (5, 2), (8, 2), (3, 0)])
def test_resumed_training_equals_an_uninterrupted_one(tmp_path, stop, pool):
    ds = Items(10)                                   # 5 batches of 2 per epoch
    full, full_seen = _train(ds, 9, tmp_path / "full" / "last.ckpt", bucket_pool=pool)
    _, first = _train(ds, stop, tmp_path / "cut" / "last.ckpt", bucket_pool=pool)
    resumed, rest = _train(ds, 9, tmp_path / "cut2" / "last.ckpt", resume=tmp_path / "cut" / "last.ckpt",
                           bucket_pool=pool)
    assert first + rest == full_seen and len(full_seen) == 9
    assert all(torch.equal(full[k], resumed[k]) for k in full)


def test_a_following_sampler_starts_each_iterator_at_the_step():
    s = LengthBucketBatchSampler(np.arange(12) % 5, 2, 2, seed=1, drop_last=True)     # 6 batches per epoch
    epochs = []
    for e in range(3):
        s.set_epoch(e)
        epochs.append(list(s))
    assert epochs[0] != epochs[1] != epochs[2]
    step = [0]
    s.follow(lambda: step[0])
    s.set_epoch(7)                                   # the step decides, not set_epoch
    assert list(s) == epochs[0]
    step[0] = 8
    assert list(s) == epochs[1][2:]
    step[0] = 12
    assert list(s) == epochs[2]
