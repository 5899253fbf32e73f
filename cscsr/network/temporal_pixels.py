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

from cscsr.network.blocks import ConvBlock, cat_channels
from cscsr.network.warp import SharedFlow


class TemporalPixels(nn.Module):
    """(B, N', C, H, W) features, (B, 1, H, W) mask, (B, N', 2, H, W) flows -> (B, C, H, W)."""

    channels_last = False  # the GPU path (cscsr.network.model.use_channels_last): NHWC, concatenations written once
    mask_slot = None  # cscsr.network.padding: the first padded channel of x, where the warped mask goes (split refine;
    # lite's 24 features have no padded channel: the BSSR then writes 32, cscsr.network.padding's ``width``)

    def __init__(self, features: int, time_points: int, flow_guidance: bool = True):
        super().__init__()
        self.flow_guidance = flow_guidance
        self.refine = nn.Sequential(ConvBlock(2 * features + 1, features), nn.Conv2d(features, features, 3, 1, 1))
        self.fuse = nn.Sequential(ConvBlock(time_points * features, features, kernel=1), ConvBlock(features, features))

    def forward(self, features: torch.Tensor, mask: torch.Tensor, flows, warped_mask=None) -> torch.Tensor:
        """``flows``: (B, N', 2, H, W), or a :class:`SharedFlow` of them as (B*N', 2, H, W) (every colour's
        warps then share one sampling plan); ``warped_mask``: (B*N', 1, H, W), the mask warped already (with
        zeros outside: the GPU path warps every colour's at once)."""
        b, t, c, h, w = features.shape
        middle = features[:, t // 2]  # (B, C, H, W)
        x = features.reshape(b * t, c, h, w)
        m = mask.repeat_interleave(t, 0) if warped_mask is None else warped_mask  # (B*N', 1, H, W)
        if self.flow_guidance:
            shared = flows if isinstance(flows, SharedFlow) else SharedFlow(flows.reshape(b * t, 2, h, w))
            x = shared.warp(x)  # (B*N', C, H, W) on the middle time point's grid
            if warped_mask is None:
                m = shared.warp(m, padding="zeros")  # where the colour's samples landed
        into = self.refine[0][0].in_channels  # 2C + 1, or a multiple of 8 when padded (cscsr.network.padding)
        if self.channels_last and self.flow_guidance and self.mask_slot is not None:  # refine's first conv split:
            x[:, self.mask_slot : self.mask_slot + 1].copy_(m)  # x's (warped: its own) padded channel <- the mask
            inner = self.refine_x(x)  # (B*N', C, H, W): the warped features' and mask's part, no concatenation
            inner.view(b, t, *inner.shape[1:]).add_(self.refine_c(middle)[:, None]).relu_()  # + middle's, once a clip
            refined = self.refine[1](inner)
        elif self.channels_last:  # the middle time point broadcast into the concatenation, not repeated first
            refined = self.refine(cat_channels([x, middle, m], into, channels_last=True, repeats=[1, t, 1]))
        else:
            joined = cat_channels([x, middle.repeat_interleave(t, 0), m], into)  # torch.cat when not padded
        if self.channels_last:  # the residual sum written straight into (B, N'*C, H, W) NHWC: no reshape copy
            c = refined.shape[1]  # x may be wider (lite: the mask's channel after C): its first C, a view
            total = x[:, :c].view(b, t, c, h, w), refined.view(b, t, c, h, w)  # residual refinement (a mask in x's
            if torch.compiler.is_compiling() or torch.is_grad_enabled():  # padding weighs 0 next); out= into a view
                fused = torch.add(*total).permute(0, 3, 4, 1, 2).contiguous()  # breaks a graph (the compiler fuses)
                # and autograd
            else:
                fused = torch.empty((b, h, w, t, c), dtype=x.dtype, device=x.device)  # stored as the fuse reads it
                torch.add(*total, out=fused.permute(0, 3, 4, 1, 2))
            return self.fuse(fused.view(b, h, w, t * c).permute(0, 3, 1, 2))  # (B, C, H, W)
        x = x + self.refine(joined)  # residual refinement
        return self.fuse(x.reshape(b, t * c, h, w))  # (B, C, H, W)
