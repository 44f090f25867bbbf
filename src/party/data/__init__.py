"""Data layer: the HumanML3D/KIT-ML on-disk layout, prepared index, datasets."""
from party.data.index import Index, load_index
from party.data.datasets import (FeatureBank, MotionStore, Normalizer, TextMotionDataset,
                                 WindowDataset, collate_text_motion)

__all__ = ["Index", "load_index", "FeatureBank", "MotionStore", "Normalizer", "TextMotionDataset",
           "WindowDataset", "collate_text_motion"]
