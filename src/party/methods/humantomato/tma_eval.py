"""TMA as an evaluator (``eval.retrievers: {tma: data/tma/eval}``; SPEC-humantomato §6.1).

``TMARetriever`` embeds raw motion features (normalised with the statistics TMA trained on) and
captions (the text encoder it trained with, checked by id) into L2-normalised mu: the platform's
R-Precision on them ranks by cosine similarity (Euclidean distance of unit vectors orders alike),
which is TMA-R-Precision^(B) at B = 32 and ``eval.large_batch_size`` (256), and the matching score
on them is TMA-Matching (the mean distance of a text's and its motion's unit mu). FID and Diversity
on TMA's features are reported too; the paper defines neither ("TMA-FID" is the platform's).
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from party.evaluation import retrievers
from party.methods.humantomato.tma_train import FORMAT, TextFeatures, frame_mask, load_tma, tma_text


class TMARetriever(nn.Module):
    kind = "tma"

    def __init__(self, model, meta: dict, text: TextFeatures):
        super().__init__()
        self.model, self.meta, self.text = model.eval(), dict(meta), text
        self.register_buffer("mean", torch.as_tensor(meta["mean"], dtype=torch.float32))
        self.register_buffer("std", torch.as_tensor(meta["std"], dtype=torch.float32))

    @property
    def feat_dim(self) -> int:
        return int(self.meta["feat_dim"])

    @torch.no_grad()
    def embed_motion(self, feats, lengths, normalized: bool = False) -> torch.Tensor:
        x = torch.as_tensor(feats, dtype=torch.float32, device=self.mean.device)
        if not normalized:
            x = (x - self.mean) / self.std
        mask = frame_mask(torch.as_tensor(lengths, device=x.device), x.shape[1])
        return nn.functional.normalize(self.model.encode_motion(x * mask[..., None], mask), dim=-1)

    @torch.no_grad()
    def embed_text(self, captions: Sequence[str], tokens=None) -> torch.Tensor:
        tok, mask = self.text.tokens(list(captions))
        return nn.functional.normalize(self.model.encode_text(tok.to(self.mean.device), mask.to(self.mean.device)),
                                       dim=-1)


def load(folder, cfg, ctx, device) -> TMARetriever:
    model, meta = load_tma(folder, map_location="cpu")
    return TMARetriever(model, meta, tma_text(folder, meta, cfg.text)).to(device)


retrievers.register(FORMAT, load)
