"""Convolutional encoder / decoder of the VQ-VAE (T2M-GPT / MoMask layout).

Both are stacks of *stages*; stage k has a temporal stride s_k and a dilated
residual block (``Resnet1D``). The strides multiply to the token window w
(``window_strides(8) == [2, 2, 2]``, ``window_strides(12) == [2, 2, 3]``).

- Encoder, ``downsample=True``: each stage starts with a strided conv (or an
  average pool), so the output has one feature per w frames: the conventional
  VQ-VAE (ablation baseline).
- Encoder, ``downsample=False``: the same stages with stride 1, one feature per
  frame (the Temporal-aware VQ-VAE's frame-level encoder); LTE groups them.
- Decoder: each stage upsamples (nearest, x s_k) then convolves, so one code
  becomes w frames.
"""
from __future__ import annotations

import torch
from torch import nn


def window_strides(window: int) -> list[int]:
    """Prime factors of ``window`` (ascending): the per-stage temporal strides."""
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    out, n, p = [], window, 2
    while n > 1:
        while n % p == 0:
            out.append(p)
            n //= p
        p += 1
    return out or [1]


class ResBlock(nn.Module):
    """x + conv1x1(relu(conv3_dilated(relu(x))))."""

    def __init__(self, width: int, dilation: int):
        super().__init__()
        self.conv1 = nn.Conv1d(width, width, 3, padding=dilation, dilation=dilation)
        self.conv2 = nn.Conv1d(width, width, 1)
        self.act = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(self.act(self.conv1(self.act(x))))


class Resnet1D(nn.Sequential):
    """``depth`` residual blocks with dilations growth**i, largest first (T2M-GPT)."""

    def __init__(self, width: int, depth: int, dilation_growth: int):
        dil = [dilation_growth ** i for i in range(depth)][::-1]
        super().__init__(*[ResBlock(width, d) for d in dil])


def _down(width: int, stride: int, pool: str, downsample: bool) -> nn.Module:
    """One stage's temporal conv: downsampling by exactly ``stride`` (T a multiple of it),
    or, with ``downsample=False``, the same kernel at stride 1 ('same' padding), so the
    frame-level encoder has exactly the baseline's parameters."""
    if stride == 1:
        return nn.Conv1d(width, width, 3, padding=1)
    kernel = 2 * stride - stride % 2          # 2s (s even) or 2s-1 (s odd)
    if not downsample:
        left = (kernel - 1) // 2
        return nn.Sequential(nn.ConstantPad1d((left, kernel - 1 - left), 0.0),
                             nn.Conv1d(width, width, kernel))
    if pool == "avg":
        return nn.Sequential(nn.AvgPool1d(stride, stride), nn.Conv1d(width, width, 3, padding=1))
    if pool != "conv":
        raise ValueError(f"baseline pooling must be 'conv' or 'avg', got {pool!r}")
    # padding s//2: output length T/s exactly
    return nn.Conv1d(width, width, kernel, stride=stride, padding=stride // 2)


class Encoder(nn.Module):
    """(B, T, in_dim) -> (B, T / prod(strides), out_dim); channels-last in and out."""

    def __init__(self, in_dim: int, width: int, out_dim: int, strides: list[int], depth: int,
                 dilation_growth: int, downsample: bool, pool: str = "conv"):
        super().__init__()
        self.stride = 1
        layers: list[nn.Module] = [nn.Conv1d(in_dim, width, 3, padding=1), nn.ReLU()]
        for s in strides:
            self.stride *= s if downsample else 1
            layers += [_down(width, s, pool, downsample), Resnet1D(width, depth, dilation_growth)]
        layers.append(nn.Conv1d(width, out_dim, 3, padding=1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] % self.stride:
            raise ValueError(f"encoder needs a length divisible by {self.stride}, got {x.shape[1]}")
        return self.net(x.transpose(1, 2)).transpose(1, 2)


class Decoder(nn.Module):
    """(B, n, code_dim) -> (B, n * prod(strides), out_dim): each code becomes w frames."""

    def __init__(self, code_dim: int, width: int, out_dim: int, strides: list[int], depth: int,
                 dilation_growth: int):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv1d(code_dim, width, 3, padding=1), nn.ReLU()]
        for s in reversed(strides):
            layers += [Resnet1D(width, depth, dilation_growth),
                       nn.Upsample(scale_factor=s, mode="nearest") if s > 1 else nn.Identity(),
                       nn.Conv1d(width, width, 3, padding=1)]
        layers += [nn.Conv1d(width, width, 3, padding=1), nn.ReLU(),
                   nn.Conv1d(width, out_dim, 3, padding=1)]
        self.net = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(z.transpose(1, 2)).transpose(1, 2)
