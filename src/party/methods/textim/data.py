"""TextIM's training data: the interactive subset (SPEC-textim §1), one item per (clip, caption).

``InteractionTable`` reads what ``party cache_interactions`` wrote (``<interactions.out_dir>/``):

    interactions.json   {caption: {"parts": [six-part names], "inter": str | null, "non": str | null,
                                   "fallback": bool}}
    subset.json         {"train" | "val" | "test": [clip ids of the interactive subset], ...}

An item is the clip's normalised features cropped to ``max_len`` (a random window in training, the
first in validation), the caption, its interaction mask m over the feature channels (the union of
its parts' channels, ``dataset.parts.groups.<mask_groups>``: SPEC §2) and the indices of its caption,
c_inter and c_non in one table of text embeddings (-1: the null condition). Strings stay out of the
batches: the model gathers the vectors.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from party.data.datasets import FeatureBank
from party.io import read_json
from party.text.interactions.extract import part_mask

PRODUCER = "party cache_interactions"


class InteractionTable:
    """Per-caption interactions and the interactive subset of one ``cache_interactions`` output."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        if not (self.folder / "interactions.json").is_file():
            raise FileNotFoundError(f"{self.folder / 'interactions.json'}: not found; run `{PRODUCER}`")
        self.rows: dict = read_json(self.folder / "interactions.json", PRODUCER, "an interaction table")
        self.subset: dict = read_json(self.folder / "subset.json", PRODUCER, "an interactive subset")
        if not isinstance(self.rows, dict) or not isinstance(self.subset, dict):
            raise ValueError(f"{self.folder}: interactions.json / subset.json are not objects; rerun `{PRODUCER}`")

    def get(self, caption: str) -> dict | None:
        return self.rows.get(caption)

    def clip_ids(self, split: str) -> list[str]:
        if split not in self.subset:
            raise KeyError(f"{self.folder / 'subset.json'}: no split {split!r} (have {', '.join(self.subset)})")
        return [str(c) for c in self.subset[split]]


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
