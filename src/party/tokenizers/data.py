"""Data plumbing for the tokenizers: training loader, full-length evaluation batches.

Training uses ``party.data.WindowDataset`` (random crops from features held in
memory by ``FeatureBank``). Evaluation and token extraction run whole clips;
clips are grouped into *buckets* of equal token count so a batch needs no
padding and every sequence is encoded exactly as it would be alone.
"""
from __future__ import annotations

import torch
from torch.utils.data import DataLoader, Dataset

from party.data import FeatureBank, WindowDataset
from party.data.context import StreamData


def train_loader(data: StreamData, crop: int, batch_size: int, num_workers: int, pin_memory: bool,
                 seed: int, split: str = "train", bank: FeatureBank | None = None) -> DataLoader:
    ds = WindowDataset(data.index, data.store, split, crop, data.normalizer, layout=data.layout,
                       stream=data.stream, bank=bank, channels=data.feat_index)
    if len(ds) == 0:
        raise ValueError(f"{data.index.path}: no {split} clip has {crop} frames (vqvae train crop)")
    g = torch.Generator().manual_seed(seed)
    return DataLoader(ds, batch_size=min(batch_size, len(ds)), shuffle=True, drop_last=True,
                      num_workers=num_workers, pin_memory=pin_memory, generator=g,
                      persistent_workers=num_workers > 0)


def fit_sequence(x: torch.Tensor, window: int, tail: str) -> tuple[torch.Tensor, int]:
    """One whole sequence (T, D) cut (``crop``) or padded with its last frame (``pad``) to n*w
    frames, as ``VQVAE`` does; returns it and the number of real frames kept."""
    T = len(x)
    if tail == "crop":
        n = T // window
        return x[:n * window], n * window
    n = -(-T // window)
    if n * window > T:
        x = torch.cat([x, x[-1:].expand(n * window - T, x.shape[1])], 0)
    return x, T


class BucketDataset(Dataset):
    """Whole sequences batched by token count (no cross-sequence padding).

    item = dict(x (B, n*w, D), mask (B, n*w) of real frames, keys [b <= B]).
    Every batch has exactly ``batch_size`` rows (a short batch repeats its first
    sequence; only the first ``len(keys)`` rows are real): kernels see one shape
    per bucket however the sequences are grouped, so validation, token extraction
    and ``decode_sequences`` give bit-identical results for a sequence (on CPU,
    a batch of 1 takes a different kernel path than a batch of 2+).
    Sequences shorter than one window (``crop``) are skipped: see ``skipped``.
    """

    def __init__(self, seqs: list[torch.Tensor], keys: list[str], window: int, tail: str,
                 batch_size: int):
        groups: dict[int, list[int]] = {}
        self.fitted: list[tuple[torch.Tensor, int]] = []
        self.skipped: list[str] = []
        for i, s in enumerate(seqs):
            fx, valid = fit_sequence(s, window, tail)
            self.fitted.append((fx, valid))
            if len(fx) == 0:
                self.skipped.append(keys[i])
                continue
            groups.setdefault(len(fx), []).append(i)
        self.batches = [ids[k:k + batch_size] for _, ids in sorted(groups.items())
                        for k in range(0, len(ids), batch_size)]
        self.keys, self.batch_size = keys, batch_size

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, i: int) -> dict:
        ids = self.batches[i]
        rows = ids + [ids[0]] * (self.batch_size - len(ids))
        x = torch.stack([self.fitted[j][0] for j in rows])
        lengths = torch.tensor([self.fitted[j][1] for j in rows])
        mask = torch.arange(x.shape[1])[None] < lengths[:, None]
        return {"x": x, "mask": mask, "keys": [self.keys[j] for j in ids]}


def bucket_loader(ds: BucketDataset) -> DataLoader:
    return DataLoader(ds, batch_size=None, shuffle=False, num_workers=0)


@torch.no_grad()
def decode_sequences(model, codes: list, batch_size: int) -> list[torch.Tensor]:
    """Decode code sequences (normalised features (n*w, D) each), batched exactly as
    ``BucketDataset`` batches them, so the result equals what validation decoded."""
    order: dict[int, list[int]] = {}
    for i, c in enumerate(codes):
        order.setdefault(len(c), []).append(i)
    out: list[torch.Tensor | None] = [None] * len(codes)
    dev = next(model.parameters()).device
    for _, ids in sorted(order.items()):
        for k in range(0, len(ids), batch_size):
            part = ids[k:k + batch_size]
            rows = part + [part[0]] * (batch_size - len(part))
            idx = torch.stack([torch.as_tensor(codes[j], dtype=torch.long) for j in rows]).to(dev)
            rec = model.decode(idx)
            for r, j in enumerate(part):
                out[j] = rec[r]
    return out


def eval_sequences(data: StreamData, split: str, max_clips: int | None = None,
                   bank: FeatureBank | None = None) -> tuple[list[torch.Tensor], list[str]]:
    """Whole normalised clips of a split (first ``max_clips`` in index order), sliced to the stream."""
    bank = bank or FeatureBank(data.index, split, data.normalizer, data.store)
    n = len(bank) if max_clips is None else min(len(bank), int(max_clips))
    idx = torch.as_tensor(data.feat_index)
    seqs = [bank.get(i).index_select(-1, idx) for i in range(n)]
    return seqs, [bank.clips[i]["id"] for i in range(n)]
