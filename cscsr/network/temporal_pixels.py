"""Temporal-pixel features: every time point's features brought to the middle one, refined, fused.

Step 3 of Algorithm 1. For one colour, each time point's BSSR features are warped by the
flow from the middle time point (sub-pixel, bilinear) and the colour's CFA mask is warped
alongside, so the network sees where real samples of that colour landed. A residual
refinement (shared by the time points) corrects what the flow got wrong, looking at the
warped features, the middle time point's features and the warped mask; the N' refined
time points are then fused into one feature map per colour.
"""

import torch
from torch import nn

from cscsr.network.blocks import ConvBlock
from cscsr.network.warp import warp


class TemporalPixels(nn.Module):
    """(B, N', C, H, W) features, (B, 1, H, W) mask, (B, N', 2, H, W) flows -> (B, C, H, W)."""

    def __init__(self, features: int, time_points: int, flow_guidance: bool = True):
        super().__init__()
        self.flow_guidance = flow_guidance
        self.refine = nn.Sequential(ConvBlock(2 * features + 1, features), nn.Conv2d(features, features, 3, 1, 1))
        self.fuse = nn.Sequential(ConvBlock(time_points * features, features, kernel=1), ConvBlock(features, features))

    def forward(self, features: torch.Tensor, mask: torch.Tensor, flows: torch.Tensor) -> torch.Tensor:
        b, t, c, h, w = features.shape
        middle = features[:, t // 2]  # (B, C, H, W)
        x = features.reshape(b * t, c, h, w)
        m = mask.repeat_interleave(t, 0)  # (B*N', 1, H, W)
        if self.flow_guidance:
            f = flows.reshape(b * t, 2, h, w)
            x = warp(x, f)  # (B*N', C, H, W) on the middle time point's grid
            m = warp(m, f, padding="zeros")  # where the colour's samples landed
        centre = middle.repeat_interleave(t, 0)
        x = x + self.refine(torch.cat([x, centre, m], 1))  # residual refinement
        return self.fuse(x.reshape(b, t * c, h, w))  # (B, C, H, W)
