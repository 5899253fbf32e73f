"""Integration: the three colours' temporal-pixel features -> HR RGB residual.

Step 4 of Algorithm 1. The colours' features, the sensor's reset mode (which changes what a
firing rate means) and the demosaicked TFP images of :func:`cscsr.network.base_image.lr_images` are
fused by a convolution, reconstructed by ResBlocks with a long skip, and enlarged by pixel
shuffle in x2 steps; a head after each step gives RGB, so one set of weights serves x2 and x4.
"""

import torch
import torch.nn.functional as F
from torch import nn

from cscsr.network.blocks import ResBlock, cat_channels

NETWORK_SCALES = (2, 4)  # one upsampling head each
LR_IMAGES = 6  # channels of the TFP images the trunk sees: RGB over the whole clip and over its middle
# Without them the trunk's only input was the temporal branches' features, random at first: in
# 200 steps (lite, batch 4, LR 24x24, Adam 1e-3) it gained +0.01 dB over the base; with them +0.28 dB.


class Integration(nn.Module):
    """(B, 3C, H, W) features, (B, 6, H, W) LR images, (B,) zero-reset flags -> (B, 3, sH, sW) residual.
    Mono (``colours=1``): (B, C, H, W) features, (B, 2, H, W) images -> (B, 1, sH, sW)."""

    def __init__(self, colour_features: int, features: int, blocks: int, colours: int = 3):
        super().__init__()
        self.fuse = nn.Conv2d(colours * colour_features + 1 + LR_IMAGES * colours // 3, features, 3, 1, 1)
        self.trunk = nn.Sequential(*[ResBlock(features) for _ in range(blocks)], nn.Conv2d(features, features, 3, 1, 1))
        # conv + pixel shuffle, no activation after it (as EDSR's upsampler): a ReLU there was measured to die
        # whole (0 % of the x4 features positive after 600 steps), cutting every layer before it off from the loss
        self.up = nn.ModuleList([nn.Sequential(nn.Conv2d(features, 4 * features, 3, 1, 1), nn.PixelShuffle(2))
                                 for _ in NETWORK_SCALES])
        self.heads = nn.ModuleList([nn.Conv2d(features, colours, 3, 1, 1) for _ in NETWORK_SCALES])
        for head in self.heads:  # an untrained network returns its base image: training starts there
            nn.init.zeros_(head.weight)  # a random start residual was measured to make the optimiser kill the
            nn.init.zeros_(head.bias)  # features' ReLUs to remove it, leaving the network stuck at its base

    channels_last = False  # the GPU path (cscsr.network.model.use_channels_last): the fused input written once, NHWC

    def forward(self, colours, images: torch.Tensor, zero_reset: torch.Tensor, scale: int) -> torch.Tensor:
        """``colours``: (B, 3C, H, W), or the colours' (B, C, H, W) features as a list (joined in one write)."""
        parts = list(colours) if isinstance(colours, (list, tuple)) else [colours]
        b, _, h, w = parts[0].shape
        if self.channels_last:  # the GPU path: the 0/1 flag written in the features' dtype, no cast
            reset = torch.zeros(b, dtype=parts[0].dtype, device=zero_reset.device).masked_fill_(zero_reset, 1)
            reset = reset[:, None, None, None].expand(b, 1, h, w)
        else:
            reset = zero_reset.to(parts[0].dtype)[:, None, None, None].expand(b, 1, h, w)
        joined = cat_channels([*parts, reset, 4 * images - 2], self.fuse.in_channels, self.channels_last)
        x = self.fuse(joined)  # (B, F, H, W); rates 0..1 centred
        x = x + self.trunk(x)  # long skip
        shuffled = getattr(self, "shuffled_heads", None)  # cscsr.network.padding: the heads as convolutions of the
        for step, factor in enumerate(NETWORK_SCALES):  # features before their last pixel shuffle (a ModuleList)
            if factor == scale and self.channels_last and shuffled is not None:  # the GPU path: the head before the
                # shuffle, then the shuffle of its K colours' 4 sub-pixels (not a shuffle of F features at 4x)
                sub = shuffled[step](self.up[step][0](x))  # (B, 4K padded, H', W')
                return F.pixel_shuffle(sub[:, : 4 * self.heads[step].channels], 2)  # (B, K, 2H', 2W')
            x = self.up[step](x)  # (B, F, 2^(step+1) H, 2^(step+1) W)
            if factor == scale:
                return self.heads[step](x)  # (B, 3, sH, sW)
        raise ValueError(f"scale {scale} is not one of {NETWORK_SCALES}")
