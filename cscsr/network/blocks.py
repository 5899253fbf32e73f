"""Building blocks named as in the supplement (Fig. 2): ConvBlock, ResBlock; and channel attention; and how the GPU
path joins channels (``cat_channels``, ``stack_channels``)."""

import torch
from torch import nn


class ConvBlock(nn.Sequential):
    """Convolution followed by ReLU."""

    def __init__(self, cin: int, cout: int, kernel: int = 3, stride: int = 1):
        super().__init__(nn.Conv2d(cin, cout, kernel, stride, kernel // 2), nn.ReLU(inplace=True))


class ResBlock(nn.Module):
    """conv-ReLU-conv plus identity, no normalisation (EDSR's residual block)."""

    def __init__(self, features: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(features, features, 3, 1, 1), nn.ReLU(inplace=True),
                                  nn.Conv2d(features, features, 3, 1, 1))

    def forward(self, x):
        return x + self.body(x)


class ChannelAttention(nn.Module):
    """Squeeze-and-excitation over channels: a global view that reweights local features."""

    def __init__(self, channels: int, reduction: int = 4):
        super().__init__()
        self.gate = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(channels, channels // reduction, 1),
                                  nn.ReLU(inplace=True), nn.Conv2d(channels // reduction, channels, 1), nn.Sigmoid())

    def forward(self, x):
        return x * self.gate(x)

# --- how the GPU path lays activations out (#53): channels-last (NHWC, NDHWC for the 3D convolution), and
# concatenations written once, straight into the channel count of the convolution that reads them (zero channels
# appended up to a multiple of 8 when cscsr.network.padding.pad_channels padded it). With neither (the default
# model on the CPU) cat_channels is torch.cat itself and stack_channels a reshape, so default outputs keep their bytes.


def cat_channels(parts: list[torch.Tensor], channels: int | None = None, channels_last: bool = False,
                 repeats: list[int] | None = None) -> torch.Tensor:
    """``torch.cat(parts, 1)`` of (B_i, C_i, H, W) tensors, zero channels appended up to ``channels``, stored
    channels-last if asked: one write of the output, no other copy. ``repeats[i] = r`` takes part i of batch
    B / r as ``part.repeat_interleave(r, 0)`` would, without making that copy. -> (B, channels, H, W)."""
    repeats = repeats or [1] * len(parts)
    total = sum(p.shape[1] for p in parts)
    channels = channels or total
    if channels == total and not channels_last and all(r == 1 for r in repeats):
        return torch.cat(parts, 1)
    first = parts[repeats.index(1)]
    b, _, h, w = first.shape
    out = torch.empty((b, channels, h, w), dtype=first.dtype, device=first.device,
                      memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    start = 0
    for part, r in zip(parts, repeats):
        end = start + part.shape[1]
        if r == 1:
            out[:, start:end].copy_(part)
        else:  # (B/r, r, C_i, H, W) view of the output, the part broadcast over r
            out.view(b // r, r, channels, h, w)[:, :, start:end].copy_(part[:, None])
        start = end
    if start < channels:
        out[:, start:].zero_()
    return out


def to_channels_last(x: torch.Tensor) -> torch.Tensor:
    """A 4-D tensor stored NHWC, a 5-D one NDHWC (a no-op if it already is)."""
    return x.contiguous(memory_format=torch.channels_last if x.dim() == 4 else torch.channels_last_3d)


def stack_channels(x: torch.Tensor, channels: int | None = None, channels_last: bool = False) -> torch.Tensor:
    """(B, G, K, H, W) -> (B, G*K, H, W) as ``reshape`` gives it, zero channels appended up to ``channels``,
    stored channels-last if asked: one write (the reshape of a slice copies anyway)."""
    b, g, k, h, w = x.shape
    channels = channels or g * k
    if channels == g * k and not channels_last:
        return x.reshape(b, g * k, h, w)
    out = torch.empty((b, channels, h, w), dtype=x.dtype, device=x.device,
                      memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    out[:, : g * k].view(b, g, k, h, w).copy_(x)
    if channels > g * k:
        out[:, g * k :].zero_()
    return out
