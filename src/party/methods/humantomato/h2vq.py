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

More than two groups (``groups: core3``: torso, legs, arms; Decision, not in the paper): Alg. 1
applied down a chain. The fine group is quantized first; the others follow from the table's last
group to its first (core3: arms, then legs, then torso), each at the coarse rate, each quantized
after fusing the Transform of the fine codes and the quantized groups before it with its own
encoding (``Conv1d(Concat(Transform_g(qF), q_1 .. q_{g-1}, z_g))``, one Transform and fusion conv
per group), and the decoder reads them all concatenated. A row holds the last (coarsest) group's
rf / rc codes, then each middle group's, then the fine code: [torso x2, legs x2, arms] at rates
(2, 4), 11.25 bits per frame at K = 512. With two groups this is the network above, module for
module (the same state dict).
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
        if len(index) < 2 or h["fine"] not in index:
            raise ValueError(f"h2vq has two groups or more, a fine one quantized first and the others after it: "
                             f"the table has {list(index)}, fine {h['fine']!r}")
        self.fine = str(h["fine"])
        rest = [n for n in reversed(list(index)) if n != self.fine]     # quantized in this order, after the fine
        self.mids, self.coarse = rest[:-1], rest[-1]
        rc, rf = int(h["rates"]["coarse"]), int(h["rates"]["fine"])
        if rc < 1 or rf < rc or rf % rc:
            raise ValueError(f"h2vq rates: the fine group's downsampling must be a multiple of the coarse "
                             f"group's, got coarse {rc}, fine {rf}")
        if int(cfg["window"]) != rf:
            raise ValueError(f"h2vq: a token row spans the fine group's downsampling ({rf} frames, "
                             f"vqvae.families.h2vq.rates.fine); set the stream's window to it, got window "
                             f"{cfg['window']}")
        self.rates = (rc, rf)
        self.window = rf                     # a row: rf frames, rf / rc codes of each coarse-rate group + 1 fine code
        self.per_row = rf // rc
        self.tail = cfg.get("tail", "crop")
        if self.tail not in ("crop", "pad"):
            raise ValueError(f"vqvae tail must be 'crop' or 'pad', got {self.tail!r}")
        for name in (self.coarse, *self.mids, self.fine):
            self.register_buffer(f"idx_{name}", torch.as_tensor(index[name]), persistent=False)
        order = torch.cat([torch.as_tensor(index[n]) for n in (self.coarse, *self.mids, self.fine)])
        self.register_buffer("inverse", torch.argsort(order), persistent=False)   # decoder order -> vector order
        c, width = int(cfg["code_dim"]), int(cfg["width"])
        depth, growth = int(cfg["depth"]), int(cfg["dilation_growth"])
        pool = cfg.get("baseline_pool", "conv")
        G = 2 + len(self.mids)
        self.enc_fine = Encoder(len(index[self.fine]), width, c, window_strides(rf), depth, growth, True, pool)
        self.enc_coarse = Encoder(len(index[self.coarse]), width, c, window_strides(rc), depth, growth, True, pool)
        if h["transform"] != "linear":
            raise ValueError(f"h2vq transform must be 'linear' (Linear c->c, then nearest upsampling), got "
                             f"{h['transform']!r}")
        self.transform = nn.Linear(c, c)
        k = int(h["fusion_kernel"])
        self.fuse = nn.Conv1d(G * c, c, k, padding=k // 2)
        q = cfg["quantizer"]
        K = int(cfg["codebook_size"])
        self.q_fine = EMAQuantizer(K, c, float(q["decay"]), float(q["reset_threshold"]))
        self.q_coarse = EMAQuantizer(K, c, float(q["decay"]), float(q["reset_threshold"]))
        # the middle groups of a longer chain (none with two groups: no module, no state-dict key)
        self.enc_mid = nn.ModuleList(Encoder(len(index[n]), width, c, window_strides(rc), depth, growth, True, pool)
                                     for n in self.mids)
        self.transform_mid = nn.ModuleList(nn.Linear(c, c) for _ in self.mids)
        self.fuse_mid = nn.ModuleList(nn.Conv1d((2 + i) * c, c, k, padding=k // 2) for i in range(len(self.mids)))
        self.q_mid = nn.ModuleList(EMAQuantizer(K, c, float(q["decay"]), float(q["reset_threshold"]))
                                   for _ in self.mids)
        self.decoder = Decoder(G * c, width, in_dim, window_strides(rc), depth, growth)

    # ------------------------------------------------------------------ protocol
    @property
    def levels(self) -> int:
        return self.per_row * (1 + len(self.mids)) + 1

    @property
    def codebook_size(self) -> int:
        return self.q_fine.n_codes

    @property
    def slot_groups(self) -> list[int]:
        """The codebook of each slot of a row: the coarse slots share one (0), the fine slot has its own
        (1), each middle group's slots share theirs (2, 3, ...)."""
        return [0] * self.per_row + [2 + i for i in range(len(self.mids)) for _ in range(self.per_row)] + [1]

    def _slots(self, i: int) -> slice:
        """The row slots of coarse-rate group i (0: the coarse group, 1..: the middle groups)."""
        return slice(i * self.per_row, (i + 1) * self.per_row)

    def decode_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Code weights (B, n, Q, K) -> (B, n * window, D), differentiable in ``w`` (one-hot rows decode
        as ``decode``; zero rows from zero vectors)."""
        B, n = w.shape[:2]
        books = [self.q_coarse, *self.q_mid]
        qc, *qm = [(w[:, :, self._slots(i)] @ q.codebook.to(w.dtype)).reshape(B, n * self.per_row, -1)
                   for i, q in enumerate(books)]
        qf = w[:, :, -1] @ self.q_fine.codebook.to(w.dtype)
        return self._decode_q(qc, qf, qm)

    def group(self, x: torch.Tensor, name: str) -> torch.Tensor:
        return x[..., getattr(self, f"idx_{name}")]

    def _up(self, q: torch.Tensor) -> torch.Tensor:
        """Fine-rate (B, n, c) -> coarse rate (B, n * per_row, c), nearest."""
        return q.repeat_interleave(self.per_row, dim=1)

    def _coarse_input(self, q_fine: torch.Tensor, z_coarse: torch.Tensor, q_mids=()) -> torch.Tensor:
        """Conv1d(Concat(Transform(qF), q_mids, zC)): the coarse group's pre-quantization features."""
        t = self._up(self.transform(q_fine))
        return self.fuse(torch.cat([t, *q_mids, z_coarse], -1).transpose(1, 2)).transpose(1, 2)

    def _mid_input(self, i: int, q_fine: torch.Tensor, q_before: list, z: torch.Tensor) -> torch.Tensor:
        """Middle group i's pre-quantization features: Conv1d(Concat(Transform_i(qF), q of the middle
        groups before it, z_i))."""
        t = self._up(self.transform_mid[i](q_fine))
        return self.fuse_mid[i](torch.cat([t, *q_before, z], -1).transpose(1, 2)).transpose(1, 2)

    def _decode_q(self, q_coarse: torch.Tensor, q_fine: torch.Tensor, q_mids=()) -> torch.Tensor:
        out = self.decoder(torch.cat([q_coarse, *q_mids, self._up(q_fine)], -1))   # (B, T, D) coarse channels first
        return out[..., self.inverse]

    def _rows(self, c_idx: torch.Tensor, f_idx: torch.Tensor, mid_idx=()) -> torch.Tensor:
        """(B, n * per_row) coarse (and middle) codes and (B, n) fine codes -> rows (B, n, Q)."""
        B, n = f_idx.shape
        return torch.cat([c.reshape(B, n, self.per_row) for c in (c_idx, *mid_idx)] + [f_idx[..., None]], -1)

    @torch.no_grad()
    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None):
        """Codes (B, n, Q) (-1 at every level of a padded row) and the row mask (B, n)."""
        x, _, node_mask = self._fit_length(x, mask)
        zf = self.enc_fine(self.group(x, self.fine))
        f_idx = self.q_fine.nearest(zf)
        qf = self.q_fine.dequantize(f_idx)
        mid_idx, q_mids = [], []
        for i, name in enumerate(self.mids):
            h = self._mid_input(i, qf, q_mids, self.enc_mid[i](self.group(x, name)))
            mid_idx.append(self.q_mid[i].nearest(h))
            q_mids.append(self.q_mid[i].dequantize(mid_idx[-1]))
        h = self._coarse_input(qf, self.enc_coarse(self.group(x, self.coarse)), q_mids)
        c_idx = self.q_coarse.nearest(h)
        return self._rows(c_idx, f_idx, mid_idx).masked_fill(~node_mask[..., None], -1), node_mask

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes (B, n, Q) (a padded row: -1, decoded from zero vectors) -> (B, n * window, D)."""
        valid = (codes >= 0).all(-1)
        B, n, _ = codes.shape
        f_idx = codes[..., -1].clamp(min=0)
        qf = self.q_fine.dequantize(f_idx) * valid[..., None]
        up_valid = self._up(valid[..., None].float())
        qc, *qm = [q.dequantize(codes[..., self._slots(i)].clamp(min=0).reshape(B, n * self.per_row)) * up_valid
                   for i, q in enumerate([self.q_coarse, *self.q_mid])]
        return self._decode_q(qc, qf, qm)

    @staticmethod
    def _quantize(quantizer, z: torch.Tensor, mask: torch.Tensor) -> tuple[dict, torch.Tensor, torch.Tensor]:
        """Quantize the masked positions of z (B, n, c): the quantizer's output, q (zeros elsewhere)
        and the codes (-1 elsewhere)."""
        out = quantizer(z[mask])
        q = torch.zeros_like(z, dtype=out["q"].dtype)
        q[mask] = out["q"]
        idx = torch.full(mask.shape, -1, dtype=torch.long, device=z.device)
        idx[mask] = out["idx"]
        return out, q, idx

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
        x, frame_mask, node_mask = self._fit_length(x, mask)
        cmask = node_mask.repeat_interleave(self.per_row, dim=1)
        zf = self.enc_fine(self.group(x, self.fine))                        # (B, n, c)
        out_f, qf, f_idx = self._quantize(self.q_fine, zf, node_mask)
        outs_m, q_mids, mid_idx = [], [], []
        for i, name in enumerate(self.mids):
            h = self._mid_input(i, qf.to(zf.dtype), q_mids, self.enc_mid[i](self.group(x, name)))
            out_m, q_m, idx_m = self._quantize(self.q_mid[i], h, cmask)
            outs_m.append(out_m)
            q_mids.append(q_m.to(h.dtype))
            mid_idx.append(idx_m)
        h = self._coarse_input(qf.to(zf.dtype), self.enc_coarse(self.group(x, self.coarse)), q_mids)   # (B, n*per_row, c)
        out_c, qc, c_idx = self._quantize(self.q_coarse, h, cmask)
        idx = self._rows(c_idx, f_idx, mid_idx)
        recon = self._decode_q(qc.to(h.dtype), qf.to(h.dtype), [q.to(h.dtype) for q in q_mids]) if self.training \
            else self.decode(idx)
        outs = [out_f, *outs_m, out_c]
        loss_app = out_f["loss_app"]
        for o in outs[1:]:
            loss_app = loss_app + o["loss_app"]
        return {"recon": recon.float(), "target": x, "frame_mask": frame_mask, "node_mask": node_mask,
                "idx": idx, "alpha": None, "loss_app": loss_app,
                "loss_app_fine": out_f["loss_app"], "loss_app_coarse": out_c["loss_app"],
                **{f"loss_app_{n}": o["loss_app"] for n, o in zip(self.mids, outs_m)},
                "perplexity": (out_f["perplexity"] + sum(o["perplexity"] for o in outs_m) + out_c["perplexity"])
                / len(outs),
                "resets": sum(o["resets"] for o in outs), "usage": [out_c["usage"], *(o["usage"] for o in outs_m),
                                                                    out_f["usage"]]}


register_family("h2vq", H2VQ)
