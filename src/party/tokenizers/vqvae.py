"""The Temporal-aware VQ-VAE (ParTY Sec. 3.1) and its conventional baseline, one code path.

    x (B,T,D) -> Encoder -> [LTE] -> [GTE] -> EMAQuantizer -> Decoder -> x_hat (B,T,D)

``lte.enabled``: frame-level encoder (no temporal downsampling) + LTE pooling of
w frames; off: strided-conv (or average-pool) encoder down to one feature per w
frames (T2M-GPT/MoMask). ``gte.enabled``: GCN over the group features.
Both off = the conventional VQ-VAE of the Tab. 4 / Tab. S12 ablations.

Lengths that are not a multiple of w (``tail``):
- ``crop`` (default, as the standard HumanML3D loaders): the last T mod w
  frames are dropped; n = T // w tokens cover frames [0, n*w).
- ``pad``: the sequence is padded to ceil(T/w)*w by repeating its last frame;
  padded frames get no LTE weight and no loss; the decoded output is cut back
  to T frames by the caller (``frame_mask``).
A batch may carry a ``mask`` (B,T) of valid frames (right padding).

Tokenizer families (``vqvae.model.family``): ``build_tokenizer`` builds the network
of the configured family (``FAMILIES``: ``temporal_vq`` = ``VQVAE``; or the dotted
path of an ``nn.Module`` class satisfying ``protocol.TokenizerModel``) and
``model.pt`` records the family, so ``load_tokenizer`` rebuilds the same class.
``model.pt`` holds tensors and plain containers only (``torch.load(weights_only=True)``).
"""
from __future__ import annotations

import logging
from typing import Any, Mapping

import torch
from torch import nn

from party.io import load_torch
from party.tokenizers.encoder import Decoder, Encoder, window_strides
from party.tokenizers.protocol import TokenizerModel
from party.tokenizers.quantizer import EMAQuantizer
from party.tokenizers.temporal import GlobalTemporalEnhancement, LocalTemporalEnhancement
from party.training import count_params

log = logging.getLogger(__name__)


class VQVAE(nn.Module):
    levels = 1      # one code per token: codes (B, n)

    def __init__(self, in_dim: int, cfg: Mapping[str, Any]):
        super().__init__()
        self.cfg = dict(cfg)
        self.window = w = int(cfg["window"])
        self.tail = cfg.get("tail", "crop")
        if self.tail not in ("crop", "pad"):
            raise ValueError(f"vqvae tail must be 'crop' or 'pad', got {self.tail!r}")
        strides = window_strides(w)
        lte, gte = cfg["lte"], cfg["gte"]
        code_dim, width = int(cfg["code_dim"]), int(cfg["width"])
        self.encoder = Encoder(in_dim, width, code_dim, strides, int(cfg["depth"]),
                               int(cfg["dilation_growth"]), downsample=not lte["enabled"],
                               pool=cfg.get("baseline_pool", "conv"))
        self.lte = LocalTemporalEnhancement(code_dim, w, int(lte["hidden"]), int(lte["layers"]),
                                            bool(lte.get("per_position", False))) \
            if lte["enabled"] else None
        self.gte = GlobalTemporalEnhancement(code_dim, int(gte["hidden"]), int(gte["layers"]),
                                             gte["adjacency"], bool(gte.get("residual", True))) \
            if gte["enabled"] else None
        q = cfg["quantizer"]
        self.quantizer = EMAQuantizer(int(cfg["codebook_size"]), code_dim, float(q["decay"]),
                                      float(q["reset_threshold"]))
        self.decoder = Decoder(code_dim, width, in_dim, strides, int(cfg["depth"]),
                               int(cfg["dilation_growth"]))
        self.in_dim = in_dim

    @property
    def codebook_size(self) -> int:
        return self.quantizer.n_codes

    # ---------------------------------------------------------------- lengths
    def n_tokens(self, length: int) -> int:
        return length // self.window if self.tail == "crop" else -(-length // self.window)

    def _fit_length(self, x: torch.Tensor, mask: torch.Tensor | None):
        """Crop or pad (B,T,D) to a multiple of w; returns x, frame mask (B,T'), node mask (B,n)."""
        B, T, _ = x.shape
        w = self.window
        lengths = mask.sum(1) if mask is not None else torch.full((B,), T, device=x.device)
        if self.tail == "crop":
            lengths = lengths // w * w
            T2 = T // w * w
            if T2 == 0:
                raise ValueError(f"sequence of {T} frames is shorter than the window {w}")
            x = x[:, :T2]
        else:
            T2 = -(-T // w) * w
            if T2 > T:
                x = torch.cat([x, x[:, -1:].expand(B, T2 - T, x.shape[2])], 1)
        frame_mask = torch.arange(T2, device=x.device)[None] < lengths[:, None]
        if mask is not None and self.tail == "pad":
            # repeat each sequence's own last valid frame into its padding
            last = (lengths - 1).clamp(min=0)
            fill = x[torch.arange(B, device=x.device), last][:, None]
            x = torch.where(frame_mask[..., None], x, fill)
        node_mask = frame_mask.reshape(B, T2 // w, w).any(-1)
        return x, frame_mask, node_mask

    # ---------------------------------------------------------------- pieces
    def encode_features(self, x: torch.Tensor, frame_mask: torch.Tensor, node_mask: torch.Tensor):
        """Pre-quantization group features (B, n, code_dim) and LTE weights (or None)."""
        f = self.encoder(x)
        alpha = None
        if self.lte is not None:
            f, alpha = self.lte(f, frame_mask)
        if self.gte is not None:
            f = self.gte(f, node_mask)
        return f, alpha

    @torch.no_grad()
    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None):
        """Codes (B, n) long ((B, n, Q) for a quantizer of Q levels; -1 on padded groups, at every
        level) and the node mask."""
        x, frame_mask, node_mask = self._fit_length(x, mask)
        z, _ = self.encode_features(x, frame_mask, node_mask)
        idx = self.quantizer.nearest(z)
        pad = ~node_mask if idx.dim() == 2 else ~node_mask[..., None]
        return idx.masked_fill(pad, -1), node_mask

    def decode(self, idx: torch.Tensor) -> torch.Tensor:
        """Codes (B, n) or (B, n, Q) (negative = padding, decoded from a zero vector) -> (B, n*w, D)."""
        valid = idx >= 0 if idx.dim() == 2 else (idx >= 0).all(-1)
        q = self.quantizer.dequantize(idx.clamp(min=0)) * valid[..., None]
        return self.decoder(q)

    def decode_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Code weights (B, n, Q, K) (one-hot rows decode as ``decode`` does; relaxed ones mix code
        vectors; zero rows decode from a zero vector) -> (B, n*w, D), differentiable in ``w``."""
        q = self.quantizer
        books = [m.codebook for m in q.quantizers] if hasattr(q, "quantizers") else [q.codebook]
        if w.shape[2] != len(books):
            raise ValueError(f"weights of {w.shape[2]} levels for a {len(books)}-level quantizer")
        return self.decoder(sum(w[:, :, i] @ b.to(w.dtype) for i, b in enumerate(books)))

    # ---------------------------------------------------------------- forward
    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
        x, frame_mask, node_mask = self._fit_length(x, mask)
        z, alpha = self.encode_features(x, frame_mask, node_mask)
        out = self.quantizer(z[node_mask])
        idx = torch.full((*node_mask.shape, *out["idx"].shape[1:]), -1, dtype=torch.long, device=x.device)
        idx[node_mask] = out["idx"]
        if self.training:
            q = torch.zeros_like(z)
            q[node_mask] = out["q"].to(z.dtype)
            recon = self.decoder(q)
        else:
            recon = self.decode(idx)      # eval: exactly what decoding the stored tokens gives
        # fp32 out of the decoder also under autocast: the losses and joint recovery stay fp32
        return {"recon": recon.float(), "target": x, "frame_mask": frame_mask, "node_mask": node_mask,
                "idx": idx, "alpha": alpha, "loss_app": out["loss_app"],
                "perplexity": out["perplexity"], "resets": out["resets"], "usage": out["usage"]}


def bits_per_frame(model) -> float:
    """Bits a tokenizer network spends per motion frame: Q levels of log2(K) bits per ``window``
    frames (VQ-512 at x4: 2.25; RVQ 512x2 at x4: 4.5; H2VQ with two coarse and one fine code per 4
    frames: 6.75). Reconstruction tables print it beside MPJPE: quantizers compared at unequal bit
    rates are not compared on equal terms (SPEC-humantomato §2.4)."""
    import math
    return int(model.levels) * math.log2(int(model.codebook_size)) / int(model.window)


# ====================================================================== families
FAMILIES: dict[str, type[nn.Module]] = {"temporal_vq": VQVAE}
LEGACY_FAMILY = "temporal_vq"   # the family of a model.pt that records none


def register_family(name: str, cls: type[nn.Module]) -> None:
    """Make ``vqvae.model.family=<name>`` build ``cls(in_dim, model_cfg)``."""
    if "." in name:
        raise ValueError(f"family name {name!r}: no dots (dotted names are import paths)")
    if name in FAMILIES and FAMILIES[name] is not cls:
        raise ValueError(f"tokenizer family {name!r} is already registered ({FAMILIES[name].__qualname__})")
    FAMILIES[name] = cls


#: modules whose import registers more built-in families (imported on the first unknown name)
BUILTIN_MODULES = ("party.methods.humantomato.h2vq",)


def family_class(name: str) -> type[nn.Module]:
    """The network class of a family: a registered name, or ``package.module.Class``."""
    if name not in FAMILIES and "." not in name:
        import importlib
        for mod in BUILTIN_MODULES:
            importlib.import_module(mod)
    if name in FAMILIES:
        return FAMILIES[name]
    if "." not in name:
        raise KeyError(f"unknown tokenizer family {name!r}: registered {sorted(FAMILIES)}, "
                       "or the dotted import path of a model class")
    from hydra.utils import get_class
    try:
        cls = get_class(name)
    except Exception as e:  # noqa: BLE001 - hydra raises ImportError / ValueError / others
        raise KeyError(f"tokenizer family {name!r}: cannot import it ({e})") from e
    if not issubclass(cls, nn.Module):
        raise TypeError(f"tokenizer family {name!r} is not an nn.Module class")
    return cls


def family_name(cls: type) -> str:
    """What ``model.pt`` records for a network class: its registered name, else its import path."""
    for name, c in FAMILIES.items():
        if c is cls:
            return name
    return f"{cls.__module__}.{cls.__qualname__}"


def build_model(in_dim: int, mcfg: Mapping[str, Any]) -> nn.Module:
    """The network of family ``mcfg["family"]`` for ``in_dim`` stream channels."""
    model = family_class(str(mcfg["family"]))(in_dim, mcfg)
    if not isinstance(model, TokenizerModel):
        raise TypeError(f"tokenizer family {mcfg['family']!r}: {type(model).__qualname__} does not "
                        "satisfy party.tokenizers.protocol.TokenizerModel")
    return model


def build_tokenizer(in_dim: int, mcfg: Mapping[str, Any], mean, std, meta: dict) -> "Tokenizer":
    """A new (untrained) tokenizer of the configured family (``mcfg`` = one stream's
    ``vqvae.model``, see ``party.tokenizers.config.stream_config``), with the stream's
    normalisation ``mean``/``std`` and ``meta`` (``StreamData.meta()``)."""
    return Tokenizer(build_model(in_dim, mcfg), mean, std, meta)


# ====================================================================== tokenizer
TOKENIZER_FORMAT = "party.tokenizer/2"    # /2: records the family; tensors + plain containers only
LEGACY_FORMATS = ("party.tokenizer/1",)   # no family (= LEGACY_FAMILY)
_PLAIN = (str, int, float, bool, type(None))


def _plain(x, where: str = "config"):
    """Plain containers (dict, list, str, int, float, bool, None) for ``model.pt``."""
    from omegaconf import DictConfig, ListConfig, OmegaConf
    if isinstance(x, (DictConfig, ListConfig)):
        x = OmegaConf.to_container(x, resolve=True)
    if isinstance(x, Mapping):
        return {str(k): _plain(v, f"{where}.{k}") for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(x)]
    if hasattr(x, "tolist") and getattr(x, "shape", None) is not None:   # numpy / torch array or scalar
        return _plain(x.tolist(), where)
    if isinstance(x, _PLAIN):
        return x
    raise TypeError(f"tokenizer {where}: {type(x).__name__} is not a plain value (str, int, float, "
                    "bool, None, list, dict); model.pt must load with weights_only=True")


class Tokenizer(nn.Module):
    """A VQ-VAE plus what it needs to be used on its own: the stream's normalisation
    statistics and where its channels/joints sit in the full feature vector.

    ``meta``: stream, feat_dim, n_joints, feat_index (stream channel -> full channel),
    stream_joints (joint ids its features determine, root first), skeleton, fps.
    """

    def __init__(self, model: nn.Module, mean, std, meta: dict):
        super().__init__()
        if not isinstance(model, TokenizerModel):
            raise TypeError(f"{type(model).__qualname__} does not satisfy "
                            "party.tokenizers.protocol.TokenizerModel")
        self.model = model
        self.meta = dict(meta)
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32).clone())
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32).clone())
        self.register_buffer("feat_index", torch.as_tensor(meta["feat_index"], dtype=torch.long),
                             persistent=False)

    @property
    def window(self) -> int:
        return self.model.window

    @property
    def tail(self) -> str:
        return self.model.tail

    @property
    def codebook_size(self) -> int:
        return int(self.model.codebook_size)

    @property
    def levels(self) -> int:
        return int(self.model.levels)

    @property
    def family(self) -> str:
        return family_name(type(self.model))

    @property
    def device(self) -> torch.device:
        return self.mean.device

    def stats(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.mean, self.std

    def n_params(self) -> int:
        return count_params(self)

    def normalize(self, raw: torch.Tensor) -> torch.Tensor:
        return (raw - self.mean) / self.std

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.std + self.mean

    def joints(self, raw: torch.Tensor) -> torch.Tensor:
        """Positions (...,T,len(stream_joints),3) of the stream's joints from raw stream features."""
        from party.motion.features import recover_from_ric
        full_dim, nj = int(self.meta["feat_dim"]), int(self.meta["n_joints"])
        if raw.shape[-1] != full_dim:
            full = raw.new_zeros(*raw.shape[:-1], full_dim)
            raw = full.index_copy(full.dim() - 1, self.feat_index.to(raw.device), raw)
        j = recover_from_ric(raw, nj)
        if len(self.meta["stream_joints"]) != nj:
            j = j[..., self.meta["stream_joints"], :]
        return j

    @torch.no_grad()
    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised stream features (B, T, D) -> codes (B, n[, Q]) (-1 on padded groups)."""
        return self.model.encode(x, mask)[0]

    @torch.no_grad()
    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes (B, n[, Q]) -> normalised stream features (B, n*w, D)."""
        return self.model.decode(codes)

    def decode_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Code weights (B, n, Q, K) -> normalised stream features (B, n*w, D), with gradients
        (relaxed codes, e.g. a generator's alignment loss through this frozen decoder)."""
        return self.model.decode_weights(w)

    @torch.no_grad()
    def tokenize(self, raw) -> torch.Tensor:
        """Raw (unnormalised) stream features (T, D) -> codes (n,) long ((n, Q) for Q levels)."""
        x = torch.as_tensor(raw, dtype=torch.float32, device=self.mean.device)
        idx, _ = self.model.encode(self.normalize(x)[None])
        return idx[0]

    @torch.no_grad()
    def detokenize(self, codes) -> torch.Tensor:
        """Codes (n,) (or (n, Q)) -> raw stream features (n*w, D)."""
        idx = torch.as_tensor(codes, dtype=torch.long, device=self.mean.device)
        return self.denormalize(self.model.decode(idx[None])[0])

    @torch.no_grad()
    def reconstruct_full(self, raw_full) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw full feature vectors (T, D_full) -> (ground truth, reconstruction), both (T', D_full):
        the stream's channels tokenized and decoded, every other channel the ground truth's
        (a part stream shown inside the ground-truth body); T' = frames the codes cover."""
        raw = torch.as_tensor(raw_full, dtype=torch.float32, device=self.mean.device)
        idx = self.feat_index.to(raw.device)
        rec = self.detokenize(self.tokenize(raw[:, idx]))
        gt = raw[:len(rec)]
        full = gt.clone()
        full[:, idx] = rec
        return gt, full

    def export(self) -> dict:
        """Tensors and plain containers only (``torch.load(weights_only=True)``)."""
        return {"format": TOKENIZER_FORMAT, "family": self.family, "in_dim": int(self.model.in_dim),
                "config": _plain(self.model.cfg), "meta": _plain(self.meta, "meta"),
                "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()}}

    @classmethod
    def from_export(cls, obj: dict, source: str = "<memory>") -> "Tokenizer":
        fmt = obj.get("format")
        if fmt == TOKENIZER_FORMAT:
            family = str(obj["family"])
        elif fmt in LEGACY_FORMATS:
            family = LEGACY_FAMILY
        else:
            raise ValueError(f"{source}: not a party tokenizer (format {fmt!r}, "
                             f"expected {TOKENIZER_FORMAT!r} or one of {LEGACY_FORMATS})")
        sd = obj["state_dict"]
        model = family_class(family)(int(obj["in_dim"]), obj["config"])
        tok = cls(model, sd["mean"], sd["std"], obj["meta"])
        tok.load_state_dict(sd)
        return tok.eval()


def save_tokenizer(tok: Tokenizer, path) -> None:
    """Write ``model.pt`` (weights + config + meta; loadable without Lightning) atomically."""
    import io as _io

    from party.io import write_bytes
    buf = _io.BytesIO()
    torch.save(tok.export(), buf)
    write_bytes(path, buf.getvalue())


def load_tokenizer(path, map_location="cpu") -> Tokenizer:
    """Load a tokenizer from its folder (``model.pt``), a ``model.pt`` or a Lightning ``.ckpt``.

    Files are read with ``torch.load(weights_only=True)`` only: a file holding other objects
    (e.g. an older writer's numpy arrays) is refused, naming ``party convert-checkpoint --trust``."""
    from pathlib import Path
    path = Path(path)
    if path.is_dir():
        path = path / "model.pt"
    obj = load_torch(path, "party train_vqvae", "tokenizer", map_location)
    if isinstance(obj, dict) and "party_tokenizer" in obj:      # Lightning checkpoint
        exp = dict(obj["party_tokenizer"])
        exp["state_dict"] = {k[len("tok."):]: v for k, v in obj["state_dict"].items() if k.startswith("tok.")}
        obj = exp
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: not a party tokenizer file")
    fmt = obj.get("format")
    if isinstance(obj.get("meta"), Mapping):     # a converted file may hold arrays as tensors
        try:
            obj = {**obj, "meta": _plain(obj["meta"], "meta")}
        except TypeError as e:
            raise ValueError(f"{path}: not a party tokenizer file ({e})") from None
    tok = Tokenizer.from_export(obj, str(path))
    log.info("%s: %s tokenizer (format %s, family %s), loaded with weights_only=True", path,
             tok.meta["stream"], fmt, tok.family)
    return tok
