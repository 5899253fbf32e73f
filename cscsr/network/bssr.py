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

from cscsr.network.blocks import ChannelAttention, to_channels_last


class BSSR(nn.Module):
    """One colour's encoder: (B, N, H, W) spikes and (B, 1, H, W) mask -> (B, N', C, H, W)."""

    channels_last = False  # the GPU path (cscsr.network.model.use_channels_last): NDHWC, gated in place
    width = None  # cscsr.network.padding: the channels the GPU path writes its output into (C and zeros after them)

    def __init__(self, features: int, length: int, stride: int, time_points: int):
        super().__init__()
        self.window = nn.Conv3d(1, features, (length, 3, 3), (stride, 1, 1), (0, 1, 1), bias=False)
        self.bias = nn.Parameter(torch.zeros(features))
        self.mix = nn.Sequential(nn.Conv3d(features, features, 3, 1, 1), nn.ReLU(inplace=True))
        self.attention = ChannelAttention(features * time_points)

    def forward(self, spikes: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, _, h, w = spikes.shape
        raw = self.windows(spikes, mask) if self.channels_last else self.windows(spikes * mask)  # (B, C, N', H, W)
        if self.channels_last:  # the GPU path: the partial convolution's scale and bias in one pass, ReLU in place
            samples = F.avg_pool2d(mask, 3, 1, 1, divisor_override=1)  # the 3x3 sum of the 0/1 mask (exact), no conv
            x = torch.addcmul(self.bias[:, None, None, None], raw, (9 / samples.clamp(min=1))[:, :, None]).relu_()
            x = to_channels_last(self.mix(x))  # (B, C, N', H, W) stored (B, N', H, W,
            # C): a no-op where the Conv3d keeps the layout (cuDNN, oneDNN's bf16); a CPU without native bf16 (AVX2)
            # returns it NCDHW, which every convolution after it would then read
        else:
            samples = F.conv2d(mask, torch.ones(1, 1, 3, 3, device=mask.device, dtype=mask.dtype), padding=1)
            x = raw * (9 / samples.clamp(min=1))[:, :, None] + self.bias[:, None, None, None]  # partial conv
            x = self.mix(torch.relu(x))  # (B, C, N', H, W)
        c, t = x.shape[1], x.shape[2]
        if self.channels_last:  # x stored (B, N', H, W, C): the same attention without the reshape's copy
            y = x.transpose(1, 2)  # (B, N', C, H, W), a view
            gate = self.attention.gate(y.mean((3, 4)).reshape(b, t * c, 1, 1)).view(b, t, c, 1, 1)  # (B, N'*C, 1, 1)
            if (self.width or c) == c:
                return y * gate  # (B, N', C, H, W) stored (B, N', H, W, C)
            # written into (B, N', W', H, W) stored (B, N', H, W, W'), zeros after C: the temporal pixels' width, with
            # a channel free for the warped mask (lite's 24 channels have none: 32)
            out = torch.empty((b, t, h, w, self.width), dtype=y.dtype, device=y.device).permute(0, 1, 4, 2, 3)
            if torch.compiler.is_compiling():  # out= into a view breaks a graph; the compiler fuses the copy
                out[:, :, :c].copy_(y * gate)
            else:
                torch.mul(y, gate, out=out[:, :, :c])
            out[:, :, c:].zero_()
            return out
        x = x.transpose(1, 2).reshape(b, t * c, h, w)  # (B, N'*C, H, W): every window's channels
        return self.attention(x).reshape(b, t, c, h, w)  # (B, N', C, H, W)

    def windows(self, spikes: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """``self.window`` (the 3D convolution) as one 2D convolution over the w frames of every time
        point: the same sums, but on PyTorch's fast 2D path (the CPU's 3D path with one input channel
        is a slow fallback, 2x the time). (B, N, H, W) -> (B, C, N', H, W)."""
        b, n, h, w = spikes.shape
        length, stride = self.window.kernel_size[0], self.window.stride[0]
        # the time points' frames by slices, not Tensor.unfold: ONNX's exporter cannot follow unfold on a padded
        # input (any side not a multiple of 16 failed to export, colour or mono); the same values
        starts = range(0, n - length + 1, stride)
        if self.channels_last:  # the GPU path: (B*N', w', H, W) NHWC, frames past w zero (w' = 16 when padded)
            return self._windows_nhwc(spikes, starts, length, mask)
        frames = torch.stack([spikes[:, t : t + length] for t in starts], 1)  # (B, N', w, H, W)
        frames = frames.reshape(-1, length, h, w)  # (B*N', w, H, W)
        raw = F.conv2d(frames, self.window.weight[:, 0], padding=1)  # (B*N', C, H, W)
        return raw.view(b, -1, raw.shape[1], h, w).transpose(1, 2)  # (B, C, N', H, W)

    def _windows_nhwc(self, spikes: torch.Tensor, starts: range, length: int, mask=None) -> torch.Tensor:
        """:meth:`windows` written once into NHWC frames, as many as the window weight takes (``window_padded``,
        (C', 16, 3, 3), from ``cscsr.network.padding``; else w), the spikes multiplied by ``mask`` (B, 1, H, W)
        on the way in: (B, N, H, W) -> (B, C', N', H, W) stored NDHWC."""
        b, _, h, w = spikes.shape
        weight = getattr(self, "window_padded", None)
        weight = self.window.weight[:, 0] if weight is None else weight  # (C', w', 3, 3)
        depth, t = weight.shape[1], len(starts)
        frames = torch.empty((b * t, depth, h, w), dtype=spikes.dtype, device=spikes.device,
                             memory_format=torch.channels_last)  # (B*N', w', H, W) stored (B*N', H, W, w')
        view = frames.view(b, t, depth, h, w)
        if mask is not None:  # every time point's frames at once: (B, N', w, H, W), a view of the spikes (overlapping)
            windows = spikes.unfold(1, length, starts.step).permute(0, 1, 4, 2, 3)  # (the GPU path is not exported)
            if torch.compiler.is_compiling():  # out= into a view breaks a graph; the compiler fuses the copy
                view[:, :, :length].copy_(windows * mask[:, None])
            else:
                torch.mul(windows, mask[:, None], out=view[:, :, :length])
        for i, start in enumerate(starts if mask is None else ()):
            view[:, i, :length].copy_(spikes[:, start : start + length])
        if depth > length:
            view[:, :, length:].zero_()
        raw = F.conv2d(frames, weight, padding=1)  # (B*N', C', H, W) NHWC
        return raw.view(b, t, raw.shape[1], h, w).transpose(1, 2)  # (B, C', N', H, W) stored (B, N', H, W, C')
