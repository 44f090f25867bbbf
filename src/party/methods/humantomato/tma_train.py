"""Training and ground-truth retrieval of TMA (``party train_tma``; SPEC-humantomato §3, App. D).

``train_tma(cfg, name, out_dir, run)`` trains the model ``tma.models.<name>`` (its seed) on the
train split, selects the validation checkpoint with the best mean Recall@1 of protocol D (sets of
32, both directions) and writes ``out_dir`` whole: ``model.pt`` (TMA's weights, sizes, the text
encoder's id and the dataset normalisation it read, tensors and plain containers only),
``metrics.json`` (the test split's ground-truth retrieval, protocols A-D, text->motion and
motion->text, Recall@1/2/3/5/10, beside the same untrained network's and chance), ``config.yaml``.

Texts: the platform text encoder's per-token features (``text.*``, ``tma.text_backbone:
encoder``), cut to ``tma.max_text_tokens``; the negative filter compares its sentence vectors.
Both are cached per caption for the run (each caption is encoded once).
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from torch.utils.data import DataLoader

from party.evaluation.metrics import recall_at_k, retrieval_ranks
from party.methods.humantomato.tma import TMA, TMAConfig

log = logging.getLogger(__name__)
FORMAT = "party.tma/1"


class TextFeatures:
    """Token features (B, L, d) + mask and sentence vectors (B, d_s) of captions, each caption
    encoded once (kept as float16 / float32 on the CPU)."""

    def __init__(self, encoder, max_tokens: int):
        self.encoder, self.max_tokens = encoder, int(max_tokens)
        self._tok: dict[str, torch.Tensor] = {}
        self._sent: dict[str, torch.Tensor] = {}

    @property
    def dim(self) -> int:
        return int(self.tokens(["a person walks."])[0].shape[-1])

    def _fill(self, captions) -> None:
        new = list(dict.fromkeys(c for c in captions if c not in self._tok))
        if not new:
            return
        with torch.no_grad():
            if hasattr(self.encoder, "encode_with_tokens"):      # one forward pass for both (MiniLM)
                sent, feats, lens = self.encoder.encode_with_tokens(new)
            else:
                feats, lens = self.encoder.encode_tokens(new)
                sent = self.encoder.encode(new)
        feats, lens = torch.as_tensor(feats).float(), torch.as_tensor(lens).long().clamp(1, self.max_tokens)
        for i, c in enumerate(new):
            self._tok[c] = feats[i, : int(lens[i])].half().clone()
            self._sent[c] = torch.as_tensor(sent[i]).float().clone()

    def tokens(self, captions) -> tuple[torch.Tensor, torch.Tensor]:
        self._fill(captions)
        rows = [self._tok[c] for c in captions]
        L = max(len(r) for r in rows)
        out = torch.zeros(len(rows), L, rows[0].shape[-1])
        mask = torch.zeros(len(rows), L, dtype=torch.bool)
        for i, r in enumerate(rows):
            out[i, : len(r)] = r.float()
            mask[i, : len(r)] = True
        return out, mask

    def similarity(self, captions) -> torch.Tensor:
        """(B, B) cosine similarity of the captions' sentence vectors."""
        self._fill(captions)
        s = torch.nn.functional.normalize(torch.stack([self._sent[c] for c in captions]), dim=-1)
        return s @ s.t()


def frame_mask(lengths: torch.Tensor, T: int) -> torch.Tensor:
    return torch.arange(T, device=lengths.device)[None] < lengths[:, None]


@torch.no_grad()
def embed(model: TMA, text: TextFeatures, loader) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """Motion and text embeddings (mu) of every item of ``loader``, with the captions."""
    was = model.training
    model.eval()
    dev = next(model.parameters()).device
    ms, ts, caps = [], [], []
    for b in loader:
        x = b["motion"].to(dev)
        ms.append(model.encode_motion(x, frame_mask(b["length"].to(dev), x.shape[1])).float().cpu())
        tok, tmask = text.tokens(b["caption"])
        ts.append(model.encode_text(tok.to(dev), tmask.to(dev)).float().cpu())
        caps += list(b["caption"])
    model.train(was)
    return torch.cat(ms), torch.cat(ts), caps


def gt_retrieval(m: torch.Tensor, t: torch.Tensor, sim: torch.Tensor | None, ecfg) -> dict:
    """Recall@K of protocols A-D (``tma.eval``) in both directions: ``{"t2m": {"A": {k: r}}, ...}``;
    a protocol whose set is larger than the split is left out."""
    ks = [int(k) for k in ecfg.ks]
    out: dict = {"n": int(len(m))}
    for d in ("t2m", "m2t"):
        res = {"A": recall_at_k(retrieval_ranks(t, m, d), ks)}
        if sim is not None:
            res["B"] = recall_at_k(retrieval_ranks(t, m, d, text_sim=sim, threshold=float(ecfg.b_threshold)), ks)
        for proto, size in ecfg.set_sizes.items():
            if len(m) >= int(size):
                rng = np.random.default_rng(int(ecfg.seed))
                res[str(proto)] = recall_at_k(retrieval_ranks(t, m, d, int(size), rng=rng), ks)
        out[d] = res
    return out


def selection_score(r: dict) -> float:
    """The validation score a checkpoint is selected by: mean Recall@1 of the smallest-set protocol
    (D, 32) over both directions, else of protocol A."""
    proto = "D" if "D" in r["t2m"] else "A"
    return (r["t2m"][proto][1] + r["m2t"][proto][1]) / 2


def _lit_class():
    import lightning as L

    class TMALit(L.LightningModule):
        """Trains a ``TMA``; validation: GT retrieval on the val split, the best weights kept."""

        def __init__(self, model: TMA, text: TextFeatures, tcfg):
            super().__init__()
            self.model, self.text, self.tcfg = model, text, tcfg
            self.weights = OmegaConf.to_container(tcfg.loss, resolve=True)
            self.best: dict | None = None
            self.history: list[dict] = []
            self.val_loader = None

        def training_step(self, batch, _):
            x = batch["motion"]
            tok, tmask = self.text.tokens(batch["caption"])
            sim = self.text.similarity(batch["caption"]).to(x.device)
            out = self.model.losses(x, frame_mask(batch["length"], x.shape[1]), tok.to(x.device), tmask.to(x.device),
                                    self.weights, sim)
            self.log_dict({f"train/{k}": out[k] for k in ("loss", "l_rec", "l_kl", "l_e", "l_nce")},
                          batch_size=len(x))
            return out["loss"]

        def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
            step = int(self.global_step)
            if step % int(self.tcfg.train.val_every) == 0 or step == int(self.trainer.max_steps):
                self.validate_now()

        def validate_now(self) -> None:
            m, t, caps = embed(self.model, self.text, self.val_loader)
            r = gt_retrieval(m, t, None, self.tcfg.eval)
            score = selection_score(r)
            self.history.append({"iter": int(self.global_step), "score": score, "retrieval": r})
            self.log("val/recall1", score)
            if self.best is None or score > self.best["score"]:
                self.best = {"iter": int(self.global_step), "score": score,
                             "state": {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()}}

        def configure_optimizers(self):
            o = self.tcfg.optim
            return torch.optim.AdamW(self.model.parameters(), lr=float(o.lr), betas=tuple(o.betas),
                                     weight_decay=float(o.weight_decay))

    return TMALit


def model_config(tcfg, motion_dim: int, text_dim: int) -> TMAConfig:
    mc = tcfg.model
    return TMAConfig(motion_dim=int(motion_dim), text_dim=int(text_dim), latent_dim=int(mc.latent_dim),
                     layers=int(mc.layers), heads=int(mc.heads), ff=int(mc.ff), dropout=float(mc.dropout),
                     max_len=max(int(tcfg.train.max_len), int(tcfg.max_text_tokens)), vae=bool(mc.vae))


def save_tma(path: Path, model: TMA, meta: dict) -> None:
    from party.methods.store import save_weights
    save_weights(path, FORMAT, dict(model.cfg.__dict__), meta, model.state_dict())


def load_tma(path: str | Path, map_location="cpu") -> tuple[TMA, dict]:
    """A trained TMA (``model.pt``, or its folder) and its meta, read with ``weights_only=True``."""
    from party.methods.store import load_weights
    obj = load_weights(path, FORMAT, map_location, "party train_tma", "TMA model")
    spec = obj.get("spec", obj.get("config"))       # "config": the key of models written before save_weights
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: a TMA file without its network sizes (spec); rerun `party train_tma`")
    model = TMA(TMAConfig(**spec))
    model.load_state_dict(obj["state_dict"])
    return model.eval(), obj["meta"]


def tma_text(folder, meta: dict, text_cfg) -> TextFeatures:
    """The caption features a trained TMA (``folder``, its ``meta``) reads: the text encoder of
    ``text_cfg``, which must be the one it trained with (checked by id; else a ValueError naming both)."""
    from party.text.encoders import build_text_encoder
    enc = build_text_encoder(text_cfg)
    have = getattr(enc, "id", None)
    if meta.get("text_encoder_id") and have != meta["text_encoder_id"]:
        raise ValueError(f"{folder}: this TMA read the text encoder {meta['text_encoder_id']!r}; text.* builds "
                         f"{have!r}. Use the encoder it trained with, or retrain it (party train_tma)")
    return TextFeatures(enc, meta["max_text_tokens"])


def train_tma(cfg, name: str, out_dir: str | Path, run) -> dict:
    """Train ``tma.models.<name>`` and write ``out_dir`` (module docstring); returns the metrics."""
    from party import tracking
    from party.data import TextMotionDataset, collate_text_motion
    from party.data.context import load_context
    from party.io import atomic_dir, write_json, write_text
    from party.text.encoders import build_text_encoder
    from party.training import build_trainer, count_params, start_training

    tcfg = cfg.tma
    if name not in tcfg.models:
        raise ValueError(f"tma.which={name!r} is not one of tma.models ({', '.join(tcfg.models)})")
    if tcfg.text_backbone != "encoder":
        raise ValueError(f"tma.text_backbone must be 'encoder' (the platform text encoder, text.*), got "
                         f"{tcfg.text_backbone!r}")
    seed = int(tcfg.models[name])
    start_training(seed, tcfg.train.threads)
    ctx = load_context(cfg)
    enc = build_text_encoder(cfg.text)
    text = TextFeatures(enc, tcfg.max_text_tokens)
    model = TMA(model_config(tcfg, ctx.feat_dim, text.dim))
    untrained = TMA(model.cfg)
    untrained.load_state_dict(model.state_dict())
    tr = tcfg.train
    mk = dict(max_len=int(tr.max_len), unit_len=int(tr.unit_len))
    train_ds = TextMotionDataset(ctx.index, ctx.store, "train", ctx.normalizer, bank=ctx.bank("train", int(tr.unit_len)), **mk)
    split = cfg.evaluator.val_split
    val_ds = TextMotionDataset(ctx.index, ctx.store, split, ctx.normalizer, captions="first", random_crop=False,
                               bank=ctx.bank(split, int(tr.unit_len)), **mk)
    workers = int(cfg.trainer.num_workers)
    train_loader = DataLoader(train_ds, batch_size=min(int(tr.batch_size), len(train_ds)), shuffle=True,
                              drop_last=True, collate_fn=collate_text_motion, num_workers=workers,
                              persistent_workers=workers > 0)
    lit = _lit_class()(model, text, tcfg)
    lit.val_loader = DataLoader(val_ds, batch_size=256, shuffle=False, collate_fn=collate_text_motion)
    t0 = time.time()
    trainer = build_trainer(cfg, max_steps=int(tr.max_steps), logger=tracking.lightning_logger(cfg, run),
                            section=tcfg.trainer, max_epochs=-1, limit_val_batches=0, num_sanity_val_steps=0)
    trainer.fit(lit, train_loader)
    if lit.best is not None:
        model.load_state_dict(lit.best["state"])
    model.cpu().eval()
    test_split = cfg.evaluator.test_split
    test_ds = TextMotionDataset(ctx.index, ctx.store, test_split, ctx.normalizer, captions="first",
                                random_crop=False, bank=ctx.bank(test_split, int(tr.unit_len)), **mk)
    test_loader = DataLoader(test_ds, batch_size=256, shuffle=False, collate_fn=collate_text_motion)
    m, t, caps = embed(model, text, test_loader)
    sim = text.similarity(caps)
    m0, t0_, _ = embed(untrained, text, test_loader)
    sizes = {str(k): int(v) for k, v in tcfg.eval.set_sizes.items()}
    metrics = {"name": name, "seed": seed, "steps": int(trainer.global_step),
               "train_seconds": round(time.time() - t0, 1), "params": count_params(model),
               "best": {k: v for k, v in (lit.best or {}).items() if k != "state"},
               f"{test_split}_gt": gt_retrieval(m, t, sim, tcfg.eval),
               f"{test_split}_gt_untrained": gt_retrieval(m0, t0_, sim, tcfg.eval),
               "chance": {p: {int(k): min(1.0, int(k) / s) for k in tcfg.eval.ks} for p, s in sizes.items()},
               "val_history": [{k: h[k] for k in ("iter", "score")} for h in lit.history]}
    run.log_metrics({f"tma/{name}/{d}_{p}_r{k}": v for d in ("t2m", "m2t")
                     for p, ks in metrics[f"{test_split}_gt"][d].items() for k, v in ks.items()})
    if not tracking.is_rank_zero():
        return metrics
    meta = {"name": name, "seed": seed, "text_encoder_id": getattr(enc, "id", None),
            "max_text_tokens": int(tcfg.max_text_tokens), "dataset": ctx.index.dataset,
            "feat_dim": int(ctx.feat_dim), "steps_trained": int(trainer.global_step),
            "mean": np.asarray(ctx.normalizer.mean, dtype=np.float64).tolist(),
            "std": np.asarray(ctx.normalizer.std, dtype=np.float64).tolist()}
    with atomic_dir(out_dir) as tmp:
        save_tma(tmp / "model.pt", model, meta)
        write_json(tmp / "metrics.json", metrics)
        write_text(tmp / "config.yaml", OmegaConf.to_yaml(tcfg, resolve=True))
    run.log_file(Path(out_dir) / "metrics.json")
    log.info("TMA %s: %s", name, json.dumps(metrics[f"{test_split}_gt"]["m2t"]))
    return metrics
