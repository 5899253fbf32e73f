"""A compact spike-flow network: two spike clips -> optical flow between their centres.

The paper uses Spike2Flow (6.6 M parameters, pretrained weights that cannot be downloaded
here); this is our own small coarse-to-fine network in its place (PWC-Net's recipe on a
three-level pyramid): each clip's frames are stacked as channels and encoded, a local
correlation volume is decoded into flow at 1/4 resolution, then the flow is upsampled
and refined at 1/2 and full resolution after warping the second clip's features by it.
Its parameters count apart from the reconstruction network's, as the paper counts them.
Input sides must be multiples of 4.
"""

import torch
import torch.nn.functional as F
from torch import nn

from cscsr.network.blocks import ConvBlock, cat_channels
from cscsr.network.warp import warp


def correlation(a: torch.Tensor, b: torch.Tensor, radius: int) -> torch.Tensor:
    """(B, C, H, W) x 2 -> (B, (2r+1)^2, H, W): mean product of a and b shifted by every offset."""
    _, c, h, w = a.shape
    padded = F.pad(b, (radius,) * 4)
    costs = [(a * padded[:, :, dy : dy + h, dx : dx + w]).mean(1)
             for dy in range(2 * radius + 1) for dx in range(2 * radius + 1)]
    return torch.stack(costs, 1)


def upsample_flow(flow: torch.Tensor) -> torch.Tensor:
    """(B, 2, H, W) -> (B, 2, 2H, 2W): twice the size, twice the displacement."""
    return 2 * F.interpolate(flow, scale_factor=2, mode="bilinear", align_corners=False)


class FlowDecoder(nn.Module):
    """Correlation, own features and the flow so far -> a flow update."""

    def __init__(self, cin: int, features: int):
        super().__init__()
        self.body = nn.Sequential(ConvBlock(cin, features), ConvBlock(features, features // 2),
                                  nn.Conv2d(features // 2, 2, 3, 1, 1))
        nn.init.zeros_(self.body[-1].weight)  # an untrained network starts from zero motion, not noise
        nn.init.zeros_(self.body[-1].bias)

    def forward(self, x):
        return self.body(x)


class SpikeFlowNet(nn.Module):
    """(B, K, h, w) clip stacks a and b -> (B, 2, h, w) flow from a's centre to b's centre."""

    RADII = (1, 2, 3)  # correlation radius at levels 1/1, 1/2, 1/4
    channels_last = False  # the GPU path (cscsr.network.model.use_channels_last): NHWC, concatenations written once
    real_widths = None  # (f0, f1, f2) before cscsr.network.padding padded the features: the correlation's mean

    def __init__(self, in_channels: int, features: int):
        super().__init__()
        f0, f1, f2 = features, features * 3 // 2, features * 2
        self.encoder = nn.ModuleList([
            nn.Sequential(ConvBlock(in_channels, f0), ConvBlock(f0, f0)),  # 1/1
            nn.Sequential(ConvBlock(f0, f1, stride=2), ConvBlock(f1, f1)),  # 1/2
            nn.Sequential(ConvBlock(f1, f2, stride=2), ConvBlock(f2, f2)),  # 1/4
        ])
        widths = (f0, f1, f2)
        self.decoders = nn.ModuleList([
            FlowDecoder((2 * r + 1) ** 2 + widths[level] + (2 if level < 2 else 0), 2 * widths[level])
            for level, r in enumerate(self.RADII)])

    def features(self, clip: torch.Tensor) -> list[torch.Tensor]:
        levels, x = [], clip
        for stage in self.encoder:
            x = stage(x)
            levels.append(x)
        return levels  # (B, f0, h, w), (B, f1, h/2, w/2), (B, f2, h/4, w/4)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        fa, fb = self.features(a), self.features(b)
        flow = None
        for level in (2, 1, 0):
            target = fb[level]
            if flow is not None:
                flow = upsample_flow(flow)  # (B, 2, size of this level)
                target = warp(target, flow)
            cost = correlation(fa[level], target, self.RADII[level])
            if self.real_widths is not None:  # a mean over the padded channels, whose features are 0: over the real
                cost = cost * (fa[level].shape[1] / self.real_widths[level])
            inputs = [cost, fa[level]] + ([flow] if flow is not None else [])
            into = self.decoders[level].body[0][0].in_channels  # or a multiple of 8 when padded
            update = self.decoders[level](cat_channels(inputs, into, self.channels_last))  # torch.cat if not padded
            flow = update if flow is None else flow + update
        return flow  # (B, 2, h, w)
