"""H²VQ: the Holistic Hierarchical VQ-VAE (HumanTOMATO §3.2, Fig. 2a, Alg. 1-2; SPEC-humantomato §2.2).

Two disjoint channel groups of the whole feature vector (``dataset.parts.groups.<table>``,
``vqvae.families.h2vq``): the *fine* group (the paper's hands; on a 22-joint body the arms) and the
*coarse* group (its body; here the core: root, legs, spine, head). Per training step (Alg. 1)::

    zF = EncF(mF)                      (B, T/rf, c)   fine encoder, downsampling x rf (4)
    zC = EncC(mC)                      (B, T/rc, c)   coarse encoder, x rc (2)
    qF = QF(zF)                        the fine group is quantized FIRST, on its own
    h  = Conv1d(Concat(Transform(qF), zC))          Transform: Linear c->c, nearest x rf/rc
    qC = QC(h)
    m^ = Dec(Concat(qC, up(qF)))       Conv1d(2c -> width), residual stack, nearest x rc, -> D
    L  = rec + alpha (||zF - sg(qF)||² + ||h - sg(qC)||²)      (Eq. 6; the commitment: loss_app)

A token row covers ``window`` = rf frames: rf / rc coarse codes, then one fine code; codes (B, n,
Q) with row s = [core_{2s}, core_{2s+1}, arms_s] at rates (2, 4), [core_s, arms_s] at equal rates
(4, 4). Both codebooks have ``codebook_size`` codes (one range for the protocol), EMA + dead-code
reset (``EMAQuantizer``). Padded rows are -1 at every level; in eval mode ``forward`` decodes its
own codes, so ``decode(encode(x))`` is the evaluated reconstruction bit for bit.

Decisions (SPEC §2.2; each a key of ``vqvae.families.h2vq``): ``rates`` (coarse 2, fine 4), the
Linear + nearest-upsample ``transform``, a kernel-3 fusion conv (``fusion_kernel``), T2M-GPT
encoders / decoder trunk (``vqvae.model``: width, depth, dilation growth, code_dim = c).
"""
from __future__ import annotations

from typing import Any, Mapping

import torch
from torch import nn

from party.motion.parts import group_index
from party.tokenizers.encoder import Decoder, Encoder, window_strides
from party.tokenizers.quantizer import EMAQuantizer
from party.tokenizers.vqvae import VQVAE, register_family


def _settings(cfg: Mapping[str, Any]) -> dict:
    h = cfg.get("h2vq")
    need = {"table", "fine", "rates", "transform", "fusion_kernel"}
    if not isinstance(h, Mapping) or not need <= set(h):
        raise ValueError(f"tokenizer family 'h2vq' needs its settings (vqvae.families.h2vq: "
                         f"{', '.join(sorted(need))}) in the model config; got h2vq={h!r}")
    return dict(h)


class H2VQ(nn.Module):
    """The H²VQ tokenizer network (``TokenizerModel``) over the whole feature vector."""

    _fit_length = VQVAE._fit_length          # crop / pad to whole rows, the frame and row masks

    def __init__(self, in_dim: int, cfg: Mapping[str, Any]):
        super().__init__()
        self.cfg = dict(cfg)
        h = _settings(cfg)
        self.in_dim = in_dim
        if (in_dim + 1) % 12:
            raise ValueError(f"h2vq reads the whole HumanML3D-style vector (12 J - 1 channels), got {in_dim} "
                             "channels: train it on the whole-body stream")
        index = group_index((in_dim + 1) // 12, h["table"])
        if len(index) != 2 or h["fine"] not in index:
            raise ValueError(f"h2vq has two groups, a fine one quantized first and a coarse one: the table "
                             f"has {list(index)}, fine {h['fine']!r}")
        self.fine = str(h["fine"])
        self.coarse = next(n for n in index if n != self.fine)
        rc, rf = int(h["rates"]["coarse"]), int(h["rates"]["fine"])
        if rc < 1 or rf < rc or rf % rc:
            raise ValueError(f"h2vq rates: the fine group's downsampling must be a multiple of the coarse "
                             f"group's, got coarse {rc}, fine {rf}")
        if int(cfg["window"]) != rf:
            raise ValueError(f"h2vq: a token row spans the fine group's downsampling ({rf} frames, "
                             f"vqvae.families.h2vq.rates.fine); set the stream's window to it, got window "
                             f"{cfg['window']}")
        self.rates = (rc, rf)
        self.window = rf                     # a row: rf frames, rf / rc coarse codes + 1 fine code
        self.per_row = rf // rc
        self.tail = cfg.get("tail", "crop")
        if self.tail not in ("crop", "pad"):
            raise ValueError(f"vqvae tail must be 'crop' or 'pad', got {self.tail!r}")
        for name in (self.coarse, self.fine):
            self.register_buffer(f"idx_{name}", torch.as_tensor(index[name]), persistent=False)
        order = torch.cat([torch.as_tensor(index[self.coarse]), torch.as_tensor(index[self.fine])])
        self.register_buffer("inverse", torch.argsort(order), persistent=False)   # decoder order -> vector order
        c, width = int(cfg["code_dim"]), int(cfg["width"])
        depth, growth = int(cfg["depth"]), int(cfg["dilation_growth"])
        pool = cfg.get("baseline_pool", "conv")
        self.enc_fine = Encoder(len(index[self.fine]), width, c, window_strides(rf), depth, growth, True, pool)
        self.enc_coarse = Encoder(len(index[self.coarse]), width, c, window_strides(rc), depth, growth, True, pool)
        if h["transform"] != "linear":
            raise ValueError(f"h2vq transform must be 'linear' (Linear c->c, then nearest upsampling), got "
                             f"{h['transform']!r}")
        self.transform = nn.Linear(c, c)
        k = int(h["fusion_kernel"])
        self.fuse = nn.Conv1d(2 * c, c, k, padding=k // 2)
        q = cfg["quantizer"]
        K = int(cfg["codebook_size"])
        self.q_fine = EMAQuantizer(K, c, float(q["decay"]), float(q["reset_threshold"]))
        self.q_coarse = EMAQuantizer(K, c, float(q["decay"]), float(q["reset_threshold"]))
        self.decoder = Decoder(2 * c, width, in_dim, window_strides(rc), depth, growth)

    # ------------------------------------------------------------------ protocol
    @property
    def levels(self) -> int:
        return self.per_row + 1

    @property
    def codebook_size(self) -> int:
        return self.q_fine.n_codes

    @property
    def slot_groups(self) -> list[int]:
        """The codebook of each slot of a row: the coarse slots share one (0), the fine slot has its own (1)."""
        return [0] * self.per_row + [1]

    def decode_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Code weights (B, n, Q, K) -> (B, n * window, D), differentiable in ``w`` (one-hot rows decode
        as ``decode``; zero rows from zero vectors)."""
        B, n = w.shape[:2]
        qc = (w[:, :, :-1] @ self.q_coarse.codebook.to(w.dtype)).reshape(B, n * self.per_row, -1)
        qf = w[:, :, -1] @ self.q_fine.codebook.to(w.dtype)
        return self._decode_q(qc, qf)

    def group(self, x: torch.Tensor, name: str) -> torch.Tensor:
        return x[..., getattr(self, f"idx_{name}")]

    def _up(self, q: torch.Tensor) -> torch.Tensor:
        """Fine-rate (B, n, c) -> coarse rate (B, n * per_row, c), nearest."""
        return q.repeat_interleave(self.per_row, dim=1)

    def _coarse_input(self, q_fine: torch.Tensor, z_coarse: torch.Tensor) -> torch.Tensor:
        """Conv1d(Concat(Transform(qF), zC)): the coarse group's pre-quantization features."""
        t = self._up(self.transform(q_fine))
        return self.fuse(torch.cat([t, z_coarse], -1).transpose(1, 2)).transpose(1, 2)

    def _decode_q(self, q_coarse: torch.Tensor, q_fine: torch.Tensor) -> torch.Tensor:
        out = self.decoder(torch.cat([q_coarse, self._up(q_fine)], -1))     # (B, T, D) coarse channels first
        return out[..., self.inverse]

    def _rows(self, c_idx: torch.Tensor, f_idx: torch.Tensor) -> torch.Tensor:
        """(B, n * per_row) coarse and (B, n) fine codes -> rows (B, n, per_row + 1)."""
        B, n = f_idx.shape
        return torch.cat([c_idx.reshape(B, n, self.per_row), f_idx[..., None]], -1)

    @torch.no_grad()
    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None):
        """Codes (B, n, Q) (-1 at every level of a padded row) and the row mask (B, n)."""
        x, _, node_mask = self._fit_length(x, mask)
        zf = self.enc_fine(self.group(x, self.fine))
        f_idx = self.q_fine.nearest(zf)
        h = self._coarse_input(self.q_fine.dequantize(f_idx), self.enc_coarse(self.group(x, self.coarse)))
        c_idx = self.q_coarse.nearest(h)
        return self._rows(c_idx, f_idx).masked_fill(~node_mask[..., None], -1), node_mask

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes (B, n, Q) (a padded row: -1, decoded from zero vectors) -> (B, n * window, D)."""
        valid = (codes >= 0).all(-1)
        B, n, _ = codes.shape
        f_idx = codes[..., -1].clamp(min=0)
        c_idx = codes[..., :-1].clamp(min=0).reshape(B, n * self.per_row)
        qf = self.q_fine.dequantize(f_idx) * valid[..., None]
        qc = self.q_coarse.dequantize(c_idx) * self._up(valid[..., None].float())
        return self._decode_q(qc, qf)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
        x, frame_mask, node_mask = self._fit_length(x, mask)
        cmask = node_mask.repeat_interleave(self.per_row, dim=1)
        zf = self.enc_fine(self.group(x, self.fine))                        # (B, n, c)
        out_f = self.q_fine(zf[node_mask])
        qf = torch.zeros_like(zf, dtype=out_f["q"].dtype)
        qf[node_mask] = out_f["q"]
        h = self._coarse_input(qf.to(zf.dtype), self.enc_coarse(self.group(x, self.coarse)))   # (B, n*per_row, c)
        out_c = self.q_coarse(h[cmask])
        qc = torch.zeros_like(h, dtype=out_c["q"].dtype)
        qc[cmask] = out_c["q"]
        f_idx = torch.full(node_mask.shape, -1, dtype=torch.long, device=x.device)
        f_idx[node_mask] = out_f["idx"]
        c_idx = torch.full(cmask.shape, -1, dtype=torch.long, device=x.device)
        c_idx[cmask] = out_c["idx"]
        idx = self._rows(c_idx, f_idx)
        recon = self._decode_q(qc.to(h.dtype), qf.to(h.dtype)) if self.training else self.decode(idx)
        return {"recon": recon.float(), "target": x, "frame_mask": frame_mask, "node_mask": node_mask,
                "idx": idx, "alpha": None, "loss_app": out_f["loss_app"] + out_c["loss_app"],
                "loss_app_fine": out_f["loss_app"], "loss_app_coarse": out_c["loss_app"],
                "perplexity": (out_f["perplexity"] + out_c["perplexity"]) / 2,
                "resets": out_f["resets"] + out_c["resets"], "usage": [out_c["usage"], out_f["usage"]]}


register_family("h2vq", H2VQ)
