"""The TextIM family (``family: textim``): TextIM's two-module part diffusion (``kind: textim``) and
its baseline MDM (``kind: mdm``, the same denoiser on the caption alone), on the prepared motion
features: no tokenizer (SPEC-textim §4-§8).

    generator:
      methods:
        textim: {family: textim, kind: textim, ...}     # conf/generator/paper.yaml, cpu.yaml
        mdm:    {family: textim, kind: mdm, ...}

Training reads the interactive subset and the per-caption interactions of ``party
cache_interactions`` (``interactions.out_dir``: parts, c_inter, c_non; ``train_clips: all`` trains on
every clip of the split instead), the caption embeddings of ``party embed_texts`` and embeds c_inter
and c_non with the same text encoder. Both modules train together, one AdamW step on the sum of
their losses (Decision: the paper trains "two modules" and says no more). The exported folder holds
``model.pt`` (spec, weights, meta), ``method.json`` (what it was trained on: the embeddings and the
interactions, ``party.provenance``), ``metrics.json`` (validation loss against the untrained
weights', and the zero prediction's: the dataset mean), ``config.json`` and ``last.ckpt``.

Generation (``TrainedMethod.sample``) reads the captions: a caption of the interaction table uses
its row, any other caption is read by ``interactions.generate_backend`` (``rules`` by default: the
oracle knows the dataset's captions only); c_inter and c_non go through the text encoder the model
was trained with; lengths are the clips' (``lengths: gt``) or ``default_seconds``.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Literal, Optional

import numpy as np
import torch
from omegaconf import MISSING
from torch.utils.data import DataLoader

from party.generator.layers import evaluating
from party.methods import register
from party.methods.base import MethodFamily, TrainedMethod
from party.schema import _off_step

log = logging.getLogger(__name__)
FORMAT = "party.generator/1+textim"


@dataclass
class TextIMMethodConfig:
    """``generator.methods.<m>`` of ``family: textim`` (SPEC-textim §4-§6, §9; MDM values where the paper
    is silent: conf/generator/paper.yaml)."""
    family: Literal["textim"] = MISSING
    kind: Literal["textim", "mdm"] = MISSING
    # the MDM trans_enc denoiser (each module's)
    dim: int = MISSING
    layers: int = MISSING
    heads: int = MISSING
    ff: int = MISSING
    dropout: float = MISSING
    cond_fusion: Literal["sum", "tokens"] = MISSING
    # diffusion
    diffusion_steps: int = MISSING
    variance: Literal["beta", "beta_tilde"] = MISSING
    cond_drop: float = MISSING
    sampler: Literal["ddpm", "ddim"] = _off_step(field(default=MISSING))
    sample_steps: Optional[int] = _off_step(field(default=MISSING))   # respacing (null: all diffusion_steps)
    guidance: float = _off_step(field(default=MISSING))
    # TextIM's modules and switches (ignored by kind: mdm)
    gcn_channels: List[int] = MISSING
    gcn_strides: List[int] = MISSING
    gcn_kernel: int = MISSING
    gcn_input: Literal["masked_inter", "full"] = MISSING
    overwrite: Literal["every_step", "final_only", "off"] = MISSING
    loss: Literal["eq5_overwritten", "plain"] = MISSING
    part_gcn: bool = MISSING
    mask_condition: bool = MISSING
    instruction_cond: bool = MISSING
    interaction_module: bool = MISSING
    share_weights: bool = MISSING
    recompute_redundant: bool = _off_step(field(default=MISSING))
    # data and optimisation
    mask_groups: str = MISSING                       # dataset.parts.groups.<name>: the parts' channels
    train_clips: Literal["subset", "all"] = MISSING
    max_len: int = MISSING
    default_seconds: float = _off_step(field(default=MISSING))
    lr: float = MISSING
    weight_decay: float = MISSING
    batch_size: int = MISSING
    max_steps: int = _off_step(field(default=MISSING))


def model_config(entry: dict, feat_dim: int, n_joints: int, text_dim: int):
    """The model's config dataclass (``TextIMConfig`` / ``MDMConfig``) of a method entry."""
    from party.methods.textim.denoiser import DenoiserConfig
    from party.methods.textim.diffusion import DiffusionConfig
    from party.methods.textim.gcn import PartGCNConfig
    from party.methods.textim.model import MDMConfig, TextIMConfig
    den = DenoiserConfig(feat_dim=feat_dim, d_model=int(entry["dim"]), layers=int(entry["layers"]),
                         heads=int(entry["heads"]), ff=int(entry["ff"]), dropout=float(entry["dropout"]),
                         cond_fusion=str(entry["cond_fusion"]))
    dif = DiffusionConfig(steps=int(entry["diffusion_steps"]), variance=str(entry["variance"]),
                          respacing=None if entry["sample_steps"] is None else int(entry["sample_steps"]),
                          sampler=str(entry["sampler"]))
    common = {"feat_dim": feat_dim, "text_dim": text_dim, "denoiser": den, "diffusion": dif,
              "cond_drop_prob": float(entry["cond_drop"]), "guidance": float(entry["guidance"])}
    if entry["kind"] == "mdm":
        return MDMConfig(**common)
    gcn = PartGCNConfig(n_joints=n_joints, channels=tuple(int(c) for c in entry["gcn_channels"]),
                        strides=tuple(int(s) for s in entry["gcn_strides"]), temporal_kernel=int(entry["gcn_kernel"]))
    return TextIMConfig(**common, n_joints=n_joints, gcn=gcn, share_weights=bool(entry["share_weights"]),
                        gcn_input=str(entry["gcn_input"]), overwrite=str(entry["overwrite"]),
                        loss=str(entry["loss"]), part_gcn=bool(entry["part_gcn"]),
                        mask_condition=bool(entry["mask_condition"]), instruction_cond=bool(entry["instruction_cond"]),
                        interaction_module=bool(entry["interaction_module"]))


def build_model(spec: dict):
    """The TextIM / MDM module of a saved spec (``{"kind", "config": asdict(model config)}``)."""
    from party.methods.textim.denoiser import DenoiserConfig
    from party.methods.textim.diffusion import DiffusionConfig
    from party.methods.textim.gcn import PartGCNConfig
    from party.methods.textim.model import MDM, TextIM, MDMConfig, TextIMConfig
    c = dict(spec["config"])
    c["denoiser"] = DenoiserConfig(**c["denoiser"])
    c["diffusion"] = DiffusionConfig(**c["diffusion"])
    if spec["kind"] == "mdm":
        return MDM(MDMConfig(**c))
    g = dict(c["gcn"])
    c["gcn"] = PartGCNConfig(**{**g, "channels": tuple(g["channels"]), "strides": tuple(g["strides"])})
    return TextIM(TextIMConfig(**c))


class TextIMNet(torch.nn.Module):
    """The model in training: gathers each row's caption, c_inter and c_non vectors from one table of
    embeddings (row -1, and any missing text: the null condition, a zero vector) and computes the
    family's losses (``losses(batch)``: ``loss`` and, for TextIM, each module's)."""

    def __init__(self, model, kind: str, table: torch.Tensor):
        super().__init__()
        self.model, self.kind = model, kind
        self.table = table                      # (n texts, text_dim): not a buffer, not in the weights

    def _emb(self, rows: torch.Tensor) -> torch.Tensor:
        table = self.table.to(rows.device)
        out = table[rows.clamp(min=0)]
        return torch.where((rows >= 0)[:, None], out, torch.zeros((), dtype=out.dtype, device=out.device))

    def losses(self, batch: dict, generator: torch.Generator | None = None) -> dict:
        x0, lengths, rows = batch["motion"], batch["length"], batch["text_rows"]
        cap = self._emb(rows[:, 0])
        if self.kind == "mdm":
            return {"loss": self.model.training_loss(x0, lengths, cap, generator)}
        return self.model.training_losses(x0, lengths, batch["mask"], cap, self._emb(rows[:, 1]),
                                          self._emb(rows[:, 2]), generator)

    def zero_losses(self, batch: dict) -> dict:
        """The same losses of the zero prediction x̂0 = 0 (the dataset's mean motion, in normalised
        features): the trivial baseline the trained denoisers must beat."""
        from party.methods.textim.model import masked_mse, module1_loss, module2_loss
        x0, lengths = batch["motion"], batch["length"]
        valid = torch.arange(x0.shape[1])[None] < lengths[:, None]
        z = torch.zeros_like(x0)
        if self.kind == "mdm":
            return {"loss": masked_mse(z, x0, valid)}
        cfg, m = self.model.cfg, batch["mask"].bool()
        rows = m.any(-1)
        l1 = x0.new_zeros(())
        if self.model.module1 is not None and bool(rows.any()):
            l1 = module1_loss(z[rows], x0[rows], (m[:, None, :] & valid[..., None])[rows])
        l2 = (module2_loss(z, x0, valid, m) if cfg.loss == "eq5_overwritten" and cfg.interaction_module
              else masked_mse(z, x0, valid))
        return {"loss": l1 + l2, "loss_module1": l1, "loss_module2": l2}

    def param_counts(self) -> dict:
        from party.training import count_params
        out = {"total": count_params(self.model)}
        for name in ("module1", "module2", "gcn", "denoiser"):
            sub = getattr(self.model, name, None)
            if isinstance(sub, torch.nn.Module):
                out[name] = count_params(sub)
        return out


def _lit_class():
    from party.generator.lit import GeneratorLit

    class TextIMLit(GeneratorLit):
        """``GeneratorLit``'s optimiser, schedule and saved random streams, on the diffusion losses."""

        def _inputs(self, batch: dict) -> dict:
            return batch

        @staticmethod
        def _scalars(out: dict) -> dict[str, float]:
            return {k: float(v.detach()) for k, v in out.items() if k.startswith("loss")}

    return TextIMLit


@torch.no_grad()
def _evaluate(net: TextIMNet, loader, seed: int) -> dict[str, float]:
    """Validation losses in eval mode at fixed noise and timesteps (``seed``), and the zero prediction's
    (``zero_*``: the dataset mean, the trivial baseline) on the same batches."""
    gen = torch.Generator().manual_seed(int(seed))
    tot: dict[str, float] = {}
    n = 0
    with evaluating(net):
        for b in loader:
            out = net.losses(b, gen)
            out.update({f"zero_{k}": v for k, v in net.zero_losses(b).items()})
            k = len(b["caption"])
            for key, v in out.items():
                tot[key] = tot.get(key, 0.0) + float(v) * k
            n += k
    return {f"val/{k}": v / max(n, 1) for k, v in tot.items()}


@register
class TextIMFamily(MethodFamily):
    name = "textim"
    Config = TextIMMethodConfig
    consumes = ("features",)

    @classmethod
    def describe(cls, cfg, method: str) -> dict:
        from party.methods import method_config
        return {"kind": str(method_config(cfg.generator, method).kind)}

    @classmethod
    def train(cls, cfg, method: str, out_dir, run, callbacks: list | None = None) -> dict:
        from party import provenance, tracking
        from party.config import plain
        from party.data.context import load_context
        from party.generator.generate import embed_texts
        from party.io import write_json
        from party.methods import method_config
        from party.methods.store import save_weights, write_method_json
        from party.methods.textim.data import InteractionDataset, TextTable, collate_interactions
        from party.text.interactions.table import read_interactions
        from party.motion.parts import group_index
        from party.schema import step_keys
        from party.training import (AtomicCheckpoint, TrainingSession, build_trainer, config_key, data_identity,
                                    file_sha, precision_identity, start_training, trainer_kwargs)
        from party.generator.train import fit_resumable
        from party.text.store import EmbeddingStore

        g, t = cfg.generator, cfg.generator.train
        entry = plain(method_config(g, method))
        start_training(cfg.seed, t.threads)
        ctx = load_context(cfg)
        groups = group_index(ctx.n_joints, ctx.parts_cfg["groups"][entry["mask_groups"]])
        inter_dir = Path(cfg.interactions.out_dir)
        table = read_interactions(inter_dir)
        texts = TextTable()
        data = {}
        for split in ("train", t.val_split):
            ids = (table.clip_ids(split) if entry["train_clips"] == "subset"
                   else [c["id"] for c in ctx.index.clips(split)])
            bank = ctx.bank(split, 1)
            data[split] = InteractionDataset(bank, table, ids, groups, texts, entry["max_len"],
                                             random_crop=split == "train")
        emb = torch.from_numpy(np.asarray(embed_texts(cfg, texts.texts), dtype=np.float32))
        text_dim = int(emb.shape[1])
        mcfg = model_config(entry, ctx.feat_dim, ctx.n_joints, text_dim)
        model = build_model({"kind": entry["kind"], "config": dataclasses.asdict(mcfg)})
        if hasattr(model, "set_feature_stats"):
            model.set_feature_stats(torch.from_numpy(ctx.normalizer.mean), torch.from_numpy(ctx.normalizer.std))
        net = TextIMNet(model, entry["kind"], emb)
        collate = collate_interactions
        val_loader = DataLoader(data[t.val_split], batch_size=min(int(entry["batch_size"]), len(data[t.val_split])),
                                shuffle=False, collate_fn=collate)
        untrained = _evaluate(net, val_loader, cfg.seed)
        torch.manual_seed(cfg.seed)
        steps = int(entry["max_steps"])
        optim = {"lr": float(entry["lr"]), "betas": [0.9, 0.999], "weight_decay": float(entry["weight_decay"]),
                 "milestone": steps + 1, "lr_after": float(entry["lr"])}
        lit = _lit_class()(net, optim, {"enabled": False}, {}, cfg.seed)
        built_from = provenance.record({"embeddings": ("embeddings", cfg.text.embeddings_dir),
                                        "interactions": ("interactions", inter_dir)})
        precision = trainer_kwargs(cfg, g.trainer)["precision"]
        key = config_key({"method": step_keys(TextIMMethodConfig, entry), "seed": cfg.seed,
                          "val_split": t.val_split, **precision_identity(precision)},
                         {**data_identity(ctx.index.path, ctx.index.root),
                          "interactions": provenance.digest("interactions", inter_dir),
                          "embeddings": [file_sha(p) for p in sorted(Path(cfg.text.embeddings_dir)
                                                                     .rglob("embeddings.npy"))]})
        tags = {"party.method": method, "party.family": cls.name, "party.kind": entry["kind"]}
        train_loader = DataLoader(data["train"], batch_size=min(int(entry["batch_size"]), len(data["train"])),
                                  shuffle=True, drop_last=True, collate_fn=collate, num_workers=t.num_workers,
                                  generator=torch.Generator().manual_seed(cfg.seed))
        with TrainingSession(run, g.resume_dir, method, key, t.resume, "generator.train.resume", tags,
                             max_steps=steps) as session:
            counts = net.param_counts()
            run.log_params({"n_params": counts["total"], "train_samples": len(data["train"]),
                            "val_samples": len(data[t.val_split]), "precision": precision})
            t0 = time.time()
            trainer = build_trainer(cfg, max_steps=steps, logger=tracking.lightning_logger(cfg, run),
                                    callbacks=[AtomicCheckpoint(session.ckpt, t.ckpt_every), *(callbacks or [])],
                                    section=g.trainer, val_check_interval=min(t.val_every, steps),
                                    check_val_every_n_epoch=None, default_root_dir=str(session.dir),
                                    gradient_clip_val=g.optim.grad_clip or None)
            fit_resumable(trainer, lit, train_loader, val_loader, session.resume_from)
            final = _evaluate(net, val_loader, cfg.seed)
            meta = {"method": method, "kind": entry["kind"], "resume_key": key, "text_dim": text_dim,
                    "encoder": str(cfg.text.embeddings_dir), "text": plain(cfg.text),
                    "encoder_id": EmbeddingStore.open(cfg.text.embeddings_dir).encoder_id,
                    "interactions_dir": str(inter_dir), "interactions": _generation_interactions(cfg),
                    "mask_groups": {k: [int(i) for i in v] for k, v in groups.items()},
                    "fps": float(ctx.index.fps), "max_len": int(entry["max_len"]),
                    "default_seconds": float(entry["default_seconds"]), "sample_steps": entry["sample_steps"],
                    "sampler": entry["sampler"], "guidance": float(entry["guidance"]),
                    "recompute_redundant": bool(entry["recompute_redundant"]),
                    "steps_trained": int(trainer.global_step), provenance.KEY: built_from}
            metrics = {"method": method, "family": cls.name, "kind": entry["kind"], "step": int(trainer.global_step),
                       "params": counts, "final": final, "untrained": untrained, "precision": precision,
                       "learned": bool(final["val/loss"] < t.untrained_loss_ratio * untrained["val/loss"]),
                       "beats_zero_prediction": bool(final["val/loss"] < final["val/zero_loss"]),
                       "train_seconds_this_run": round(time.time() - t0, 1)}
            spec = {"kind": entry["kind"], "config": dataclasses.asdict(mcfg)}
            if trainer.is_global_zero:
                def write(tmp: Path) -> None:
                    save_weights(tmp / "model.pt", FORMAT, spec, meta, model.state_dict())
                    write_method_json(tmp, cls.name, method, built_from)
                    write_json(tmp / "config.json", {"method": method, **entry, "meta": meta})
                    write_json(tmp / "metrics.json", metrics)
                session.export(out_dir, write, ["method.json", "model.pt", "metrics.json"], "generator",
                               t.log_checkpoint)
        run.log_metrics({f"final/{k.split('/', 1)[1]}": v for k, v in final.items()}, step=int(trainer.global_step))
        run.log_metrics({f"untrained/{k.split('/', 1)[1]}": v for k, v in untrained.items()})
        print(f"train_generator[{method}]: step {metrics['step']} val loss {final['val/loss']:.4f} (untrained "
              f"{untrained['val/loss']:.4f}, zero prediction {final['val/zero_loss']:.4f}); "
              f"{counts['total'] / 1e6:.2f}M params")
        return metrics

    @classmethod
    def load(cls, folder, map_location: str = "cpu") -> "TextIMMethod":
        from party.methods.store import load_weights
        obj = load_weights(folder, FORMAT, map_location)
        model = build_model(obj["spec"])
        model.load_state_dict(obj["state_dict"])
        model.eval()
        return TextIMMethod(model, obj["meta"])


def _generation_interactions(cfg) -> dict:
    """The extractor settings generation uses for captions outside the interaction table: the
    ``generate_backend``, else the stage's backend, the rules in place of the oracle (no secrets: keys
    stay in the environment, ``party.secrets``)."""
    from party.config import plain
    icfg = plain(cfg.interactions)
    backend = icfg.get("generate_backend") or icfg["backend"]
    return {**icfg, "backend": "rules" if backend == "oracle" else backend}     # the oracle knows its captions only


class TextIMMethod(TrainedMethod):
    """A trained TextIM or MDM, sampling raw features (see the module docstring)."""

    reads_captions = True

    def __init__(self, model, meta: dict):
        super().__init__(meta)
        self.model = model
        self.kind = str(meta["kind"])
        self._texts: dict[str, np.ndarray] = {}
        self._encoder = None
        self._extractor = None
        self.table = None

    def bind(self, ctx, tokenizers_dir=None, allow_mismatch: bool = False) -> "TextIMMethod":
        from party import provenance
        from party.text.interactions.table import read_interactions
        self.ctx = ctx
        folder = Path(self.files_dir) / "interactions" if self.files_dir else Path(self.meta["interactions_dir"])
        if self.kind != "mdm":
            provenance.check_generator(self, {"interactions": ("interactions", folder)}, allow_mismatch)
            self.table = read_interactions(folder)
        return self

    def package_files(self) -> dict:
        if self.kind == "mdm":
            return {}
        folder = Path(self.meta["interactions_dir"])
        return {f"interactions/{n}": folder / n for n in ("interactions.json", "subset.json")}

    # ------------------------------------------------------------------ lengths
    def gt_lengths(self, cfg, clip_ids):
        frames = {c["id"]: int(c["end"]) - int(c["start"]) for c in self.ctx.index.clips()}
        return {"frames": torch.tensor([min(frames[c], int(self.meta["max_len"])) for c in clip_ids])}

    def frame_lengths(self, frames):
        if frames is None or all(f is None for f in frames):
            return None
        if any(f is None or int(f) < 1 for f in frames):
            raise ValueError(f"generate.frames: give a positive length for every text, got {list(frames)}")
        return {"frames": torch.tensor([min(int(f), int(self.meta["max_len"])) for f in frames])}

    # ------------------------------------------------------------------ texts
    def _interaction(self, caption: str) -> dict:
        row = self.table.get(caption) if self.table is not None else None
        if row is not None:
            return row
        if self._extractor is None:
            from party.text.interactions import build_extractor
            self._extractor = build_extractor(self.meta["interactions"])
        return self._extractor(caption)

    def _embed(self, texts: list[str | None]) -> torch.Tensor:
        """Text vectors of the embedding store the model trained with where it holds them, else through
        the encoder it trained with (memoised); None: a zero row (the null condition)."""
        todo = sorted({t for t in texts if t and t not in self._texts})
        store = Path(self.meta.get("encoder") or "")
        if todo and self.meta.get("encoder") and store.is_dir():
            from party.text.store import EmbeddingStore
            st = EmbeddingStore.open(store)
            if st.encoder_id == self.meta.get("encoder_id", st.encoder_id):
                have = [t for t in todo if t in st]
                if have:
                    self._texts.update(zip(have, np.asarray(st.get(have), dtype=np.float32)))
                todo = [t for t in todo if t not in self._texts]
        if todo:
            if self._encoder is None:
                from omegaconf import OmegaConf

                from party.text.encoders import build_text_encoder
                enc = build_text_encoder(OmegaConf.create(self.meta["text"]))
                if self.meta.get("encoder_id") and enc.id != self.meta["encoder_id"]:
                    raise ValueError(f"method {self.method!r} was trained with the text encoder "
                                     f"{self.meta['encoder_id']}; the text config it recorded builds {enc.id}")
                self._encoder = enc
            vecs = self._encoder.encode(todo).numpy().astype(np.float32)
            self._texts.update(zip(todo, vecs))
        dim = int(self.meta["text_dim"])
        return torch.from_numpy(np.stack([self._texts[t] if t else np.zeros(dim, np.float32) for t in texts]))

    # ------------------------------------------------------------------ generation
    @torch.no_grad()
    def sample(self, text_emb, lengths, gcfg, generator, texts=None):
        if texts is None:
            raise ValueError(f"method {self.method!r} reads the captions: call it with texts=")
        b = len(text_emb)
        n = (lengths["frames"].long() if lengths is not None else
             torch.full((b,), int(round(float(self.meta["default_seconds"]) * float(self.meta["fps"])))))
        n = n.clamp(1, int(self.meta["max_len"]))
        cap = torch.as_tensor(text_emb, dtype=torch.float32)
        steps, scale = self.meta.get("sample_steps"), float(self.meta["guidance"])
        if self.kind == "mdm":
            x = self.model.sample(cap, n, generator, steps=steps, guidance=scale)
        else:
            from party.text.interactions.extract import part_mask
            rows = [self._interaction(t) for t in texts]
            groups, d = self.meta["mask_groups"], int(self.ctx.feat_dim)
            mask = torch.from_numpy(np.stack([part_mask(r.get("parts") or (), groups, d) for r in rows]))
            inter = self._embed([r.get("inter") for r in rows])
            non = self._embed([r.get("non") for r in rows])
            x = self.model.sample(cap, inter, non, mask, n, generator, steps=steps, guidance=scale).motion
        out = [self.ctx.normalizer.denorm(x[i, :int(n[i])].numpy()).astype(np.float32) for i in range(b)]
        if self.meta.get("recompute_redundant"):
            from party.motion.features import joints_to_features_np, recover_from_ric_np
            out = [_refeaturize(f, self.ctx.n_joints, recover_from_ric_np, joints_to_features_np) for f in out]
        return out

    def param_counts(self) -> dict:
        return TextIMNet(self.model, self.kind, torch.zeros(0, 1)).param_counts()

    def index_fields(self, method_cfg) -> dict:
        return {"kind": self.kind}


def _refeaturize(f: np.ndarray, n_joints: int, recover, featurize) -> np.ndarray:
    """SPEC §2 ``post.recompute_redundant``: the features recomputed from the motion's joints (the
    velocities then agree with the regenerated root); one frame is lost, the last one repeated."""
    g = featurize(recover(f, n_joints))
    return np.concatenate([g, g[-1:]], 0).astype(np.float32) if len(g) < len(f) else g.astype(np.float32)
