"""TextIM's training data: the interactive subset (SPEC-textim §1), one item per (clip, caption).

The interaction table and the subset are what ``party cache_interactions`` wrote, read by
``party.text.interactions.table.read_interactions`` (``InteractionTable``).

An item is the clip's normalised features cropped to ``max_len`` (a random window in training, the
first in validation), the caption, its interaction mask m over the feature channels (the union of
its parts' channels, ``dataset.parts.groups.<mask_groups>``: SPEC §2) and the indices of its caption,
c_inter and c_non in one table of text embeddings (-1: the null condition). Strings stay out of the
batches: the model gathers the vectors.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from party.data.datasets import FeatureBank
from party.text.interactions.extract import part_mask
from party.text.interactions.table import PRODUCER, InteractionTable



class TextTable:
    """Every distinct text of a dataset (captions, c_inter, c_non) and its embedding row."""

    def __init__(self):
        self.index: dict[str, int] = {}

    def add(self, text: str | None) -> int:
        if not text:
            return -1
        return self.index.setdefault(str(text), len(self.index))

    @property
    def texts(self) -> list[str]:
        return list(self.index)


class InteractionDataset(Dataset):
    """(clip, caption) items of ``clip_ids`` with their masks and text rows (module docstring)."""

    def __init__(self, bank: FeatureBank, table: InteractionTable, clip_ids: Sequence[str],
                 groups: Mapping[str, np.ndarray], texts: TextTable, max_len: int, random_crop: bool,
                 use_interactions: bool = True):
        want = set(clip_ids)
        self.bank, self.max_len, self.random_crop = bank, int(max_len), bool(random_crop)
        self.items: list[tuple[int, str, np.ndarray, int, int, int]] = []
        dim = bank.data.shape[1]
        empty = np.zeros(dim, dtype=bool)
        for k, clip in enumerate(bank.clips):
            if clip["id"] not in want:
                continue
            for cap in clip["captions"]:
                c = cap["caption"]
                row = table.get(c) if use_interactions else None
                if use_interactions and row is None:
                    raise KeyError(f"{table.folder / 'interactions.json'}: no entry for the caption {c!r} of clip "
                                   f"{clip['id']}; rerun `{PRODUCER}`")
                parts = list(row["parts"]) if row else []
                mask = part_mask(parts, groups, dim) if parts else empty
                self.items.append((k, c, mask, texts.add(c), texts.add(row["inter"] if row else None),
                                   texts.add(row["non"] if row else None)))
        if not self.items:
            raise ValueError(f"no clip of {sorted(want)[:3]}... is in the prepared split (interactive subset "
                             f"{table.folder / 'subset.json'} against the index); rerun `{PRODUCER}`")

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        k, caption, mask, cap, inter, non = self.items[i]
        n = int(self.bank.lengths[k])
        length = min(n, self.max_len)
        slack = n - length
        start = int(torch.randint(0, slack + 1, ()).item()) if (self.random_crop and slack > 0) else 0
        return {"motion": self.bank.get(k, start, length), "length": length, "caption": caption,
                "mask": torch.from_numpy(mask), "text_rows": torch.tensor([cap, inter, non])}


def collate_interactions(batch: list[dict]) -> dict:
    """Motions padded to the longest of the batch; masks and text rows stacked."""
    lengths = torch.tensor([b["length"] for b in batch], dtype=torch.long)
    d = batch[0]["motion"].shape[-1]
    motion = torch.zeros(len(batch), int(lengths.max()), d, dtype=batch[0]["motion"].dtype)
    for i, b in enumerate(batch):
        motion[i, :b["length"]] = b["motion"]
    return {"motion": motion, "length": lengths, "mask": torch.stack([b["mask"] for b in batch]),
            "text_rows": torch.stack([b["text_rows"] for b in batch]), "caption": [b["caption"] for b in batch]}
