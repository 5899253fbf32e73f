"""Bayer spike stream representation (BSSR): a clip of one colour -> features per time point.

Step 1 of Algorithm 1. The colour's samples are picked out with its CFA mask; a temporal
sliding window of length w and stride s (a 3D convolution with kernel (w, 3, 3), stride
(s, 1, 1)) encodes N frames into N' = (N - w + s) / s time points. The convolution is
mask-aware (a partial convolution): it is normalised by the number of real samples of the
colour under its 3x3 footprint, so a colour seen at 1 pixel in 4 and one seen at 2 in 4
give features on the same scale, densely. A 3D ConvBlock mixes neighbouring time points
and channel attention over all time points' channels gives each window a global view.
"""

import torch
import torch.nn.functional as F
from torch import nn

from cscsr.network.blocks import ChannelAttention


class BSSR(nn.Module):
    """One colour's encoder: (B, N, H, W) spikes and (B, 1, H, W) mask -> (B, N', C, H, W)."""

    def __init__(self, features: int, length: int, stride: int, time_points: int):
        super().__init__()
        self.window = nn.Conv3d(1, features, (length, 3, 3), (stride, 1, 1), (0, 1, 1), bias=False)
        self.bias = nn.Parameter(torch.zeros(features))
        self.mix = nn.Sequential(nn.Conv3d(features, features, 3, 1, 1), nn.ReLU(inplace=True))
        self.attention = ChannelAttention(features * time_points)

    def forward(self, spikes: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, _, h, w = spikes.shape
        raw = self.windows(spikes * mask)  # (B, C, N', H, W)
        samples = F.conv2d(mask, torch.ones(1, 1, 3, 3, device=mask.device, dtype=mask.dtype), padding=1)
        x = raw * (9 / samples.clamp(min=1))[:, :, None] + self.bias[:, None, None, None]  # partial conv
        x = self.mix(torch.relu(x))  # (B, C, N', H, W)
        c, t = x.shape[1], x.shape[2]
        x = x.transpose(1, 2).reshape(b, t * c, h, w)  # (B, N'*C, H, W): every window's channels
        return self.attention(x).reshape(b, t, c, h, w)  # (B, N', C, H, W)

    def windows(self, spikes: torch.Tensor) -> torch.Tensor:
        """``self.window`` (the 3D convolution) as one 2D convolution over the w frames of every time
        point: the same sums, but on PyTorch's fast 2D path (the CPU's 3D path with one input channel
        is a slow fallback, 2x the time). (B, N, H, W) -> (B, C, N', H, W)."""
        b, n, h, w = spikes.shape
        length, stride = self.window.kernel_size[0], self.window.stride[0]
        # the time points' frames by slices, not Tensor.unfold: ONNX's exporter cannot follow unfold on a padded
        # input (any side not a multiple of 16 failed to export, colour or mono); the same values
        frames = torch.stack([spikes[:, t : t + length] for t in range(0, n - length + 1, stride)], 1)  # (B, N', w, H, W)
        frames = frames.reshape(-1, length, h, w)  # (B*N', w, H, W)
        raw = F.conv2d(frames, self.window.weight[:, 0], padding=1)  # (B*N', C, H, W)
        return raw.view(b, -1, raw.shape[1], h, w).transpose(1, 2)  # (B, C, N', H, W)
