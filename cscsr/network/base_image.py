"""The cheap images the network starts from: demosaicked TFP at LR, and its bicubic HR base.

TFP (corrected for a zero-reset sensor as in :mod:`stages.reconstruction.tfp`), demosaicked bilinearly by
normalised convolution: torch versions of the classic baseline. Over the whole clip it is
the base image the network adds its residual to (a global skip, enlarged by bicubic
interpolation); over the whole clip and over the middle window it is also an input of the
integration trunk, which then starts as a plain super-resolution network on a meaningful
image while the temporal branches learn.
"""

import torch
import torch.nn.functional as F

from cscsr.network.blocks import cat_channels

_BILINEAR = torch.tensor([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]])


def tfp(spikes: torch.Tensor, zero_reset: torch.Tensor) -> torch.Tensor:
    """(B, N, H, W) spikes, (B,) bool -> (B, 1, H, W) rate alpha*I/theta."""
    rate = spikes.mean(1, keepdim=True)
    corrected = rate / (1 - rate / 2)
    return torch.where(zero_reset[:, None, None, None], corrected, rate)


def demosaic(rate: torch.Tensor, colours: torch.Tensor, kernel: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 1, H, W) mosaic, (B, 3, H, W) R/G/B masks -> (B, 3, H, W): each colour interpolated bilinearly.

    ``kernel``: the GPU path's (:func:`aligned_kernel`, from ``cscsr.network.padding``): the two 3-channel grouped
    convolutions (the colours' values and their weights) as one convolution of 8 channels, NHWC; the same sums."""
    if kernel is not None:
        joined = cat_channels([rate * colours, colours], kernel.shape[1], channels_last=True)  # (B, 8, H, W)
        sums = F.conv2d(joined, kernel, padding=1)  # (B, 8, H, W): the colours' values, their weights, 2 zeros
        return sums[:, :3] / sums[:, 3:6].clamp(min=1e-6)
    kernel = _BILINEAR.to(rate)[None, None].repeat(3, 1, 1, 1)
    values = F.conv2d(rate * colours, kernel, padding=1, groups=3)
    weights = F.conv2d(colours, kernel, padding=1, groups=3)
    return values / weights.clamp(min=1e-6)


def aligned_kernel(channels: int = 8) -> torch.Tensor:
    """(channels, channels, 3, 3) float32: the bilinear kernel on the diagonal's first 6 channels (three colours'
    values, then their weights), zeros elsewhere: :func:`demosaic`'s two grouped convolutions as one."""
    kernel = torch.zeros(channels, channels, 3, 3)
    for i in range(6):
        kernel[i, i] = _BILINEAR
    return kernel


def lr_images(spikes: torch.Tensor, colours: torch.Tensor, zero_reset: torch.Tensor, middle: int,
              kernel: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, H, W) spikes -> (B, 6, H, W): demosaicked TFP over all N frames, then over the middle
    ``middle`` frames (less motion blur, more noise). Mono ((B, 1, H, W) mask of ones): (B, 2, H, W), no
    demosaicking. ``kernel``: :func:`demosaic`'s (the GPU path's)."""
    n = spikes.shape[1]
    start = n // 2 - middle // 2
    window = spikes[:, start : start + middle]
    if colours.shape[1] == 1:
        return torch.cat([tfp(spikes, zero_reset), tfp(window, zero_reset)], 1)  # (B, 2, H, W)
    return torch.cat([demosaic(tfp(spikes, zero_reset), colours, kernel),
                      demosaic(tfp(window, zero_reset), colours, kernel)], 1)


def base_image(lr: torch.Tensor, scale: int) -> torch.Tensor:
    """(B, 3, H, W) demosaicked TFP -> (B, 3, sH, sW), bicubic x s."""
    return F.interpolate(lr, scale_factor=scale, mode="bicubic", align_corners=False)
