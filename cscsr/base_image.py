"""The cheap HR base image the network adds its output to: demosaicked, bicubic TFP.

TFP over the whole clip (corrected for a zero-reset sensor as in :mod:`stages.tfp`),
demosaicked bilinearly by normalised convolution, enlarged by bicubic interpolation:
differentiable torch versions of the classic baseline, so the network only learns the
residual (a global skip).
"""

import torch
import torch.nn.functional as F

_BILINEAR = torch.tensor([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]])


def tfp(spikes: torch.Tensor, zero_reset: torch.Tensor) -> torch.Tensor:
    """(B, N, H, W) spikes, (B,) bool -> (B, 1, H, W) rate alpha*I/theta."""
    rate = spikes.mean(1, keepdim=True)
    corrected = rate / (1 - rate / 2)
    return torch.where(zero_reset[:, None, None, None], corrected, rate)


def demosaic(rate: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) mosaic, (B, 3, H, W) R/G/B masks -> (B, 3, H, W): each colour interpolated bilinearly."""
    kernel = _BILINEAR.to(rate)[None, None].repeat(3, 1, 1, 1)
    values = F.conv2d(rate * colours, kernel, padding=1, groups=3)
    weights = F.conv2d(colours, kernel, padding=1, groups=3)
    return values / weights.clamp(min=1e-6)


def base_image(spikes: torch.Tensor, colours: torch.Tensor, zero_reset: torch.Tensor, scale: int) -> torch.Tensor:
    """-> (B, 3, sH, sW) demosaicked TFP, bicubic x s."""
    lr = demosaic(tfp(spikes, zero_reset), colours)  # (B, 3, H, W)
    return F.interpolate(lr, scale_factor=scale, mode="bicubic", align_corners=False)
