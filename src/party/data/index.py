"""The prepared index: which clips exist, their split, frame span and captions.

Written by ``party prepare`` to ``<prepared>/index.json``; every later stage reads
the dataset through it, so a real dataset is validated once.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from party.io import read_json

INDEX_VERSION = 1


@dataclass
class Index:
    dataset: str
    root: str                     # folder in HumanML3D layout
    fps: float
    feat_dim: int
    n_joints: int
    skeleton: str
    clips_: list[dict] = field(default_factory=list)
    path: Path | None = None

    def clips(self, split: str | None = None) -> list[dict]:
        if split is None or split == "all":
            return list(self.clips_)
        return [c for c in self.clips_ if c["split"] == split]

    @property
    def splits(self) -> list[str]:
        return sorted({c["split"] for c in self.clips_})

    def motions(self, split: str | None = None) -> list[str]:
        return sorted({c["motion"] for c in self.clips(split)})

    def captions(self, split: str | None = None) -> list[str]:
        """Every distinct caption, in first-seen order."""
        return list(dict.fromkeys(cap["caption"] for c in self.clips(split) for cap in c["captions"]))

    def to_json(self) -> dict:
        return {"version": INDEX_VERSION, "dataset": self.dataset, "root": self.root, "fps": self.fps,
                "feat_dim": self.feat_dim, "n_joints": self.n_joints, "skeleton": self.skeleton,
                "clips": self.clips_}


def load_index(path: str | Path) -> Index:
    path = Path(path)
    if path.is_dir():
        path = path / "index.json"
    obj = read_json(path, "party prepare", what="prepared index")
    if obj.get("version") != INDEX_VERSION:
        raise ValueError(f"{path}: index version {obj.get('version')} != {INDEX_VERSION}; rerun `party prepare`")
    root = obj["root"]
    if not Path(root).is_absolute():   # stored relative to the index's folder
        root = str((path.parent / root).resolve())
    return Index(obj["dataset"], root, obj["fps"], obj["feat_dim"], obj["n_joints"], obj["skeleton"],
                 obj["clips"], path)
