"""Joint motion estimation: flows from the middle time point to every BSSR time point.

Step 2 of Algorithm 1. The clip is split into four half-resolution channels R, G1, G2, B
(no missing pixels); the spike-flow network sees a clip of ``flow_frames`` frames around
the middle frame and around the first and last motion time points (frames 11 and 29 of
41) and estimates flows middle -> last, and middle -> first on the time-reversed clips
(the supplement's "reverse" operation). ``joint``: all four channels feed one flow;
``assembled`` (the ablation's case E): each channel alone, and the four flows are put
back on the Bayer grid they came from. Flows are doubled from half to full LR resolution
and scaled linearly (constant velocity within the clip) to every time point's centre.
"""

import torch
import torch.nn.functional as F
from torch import nn

from cscsr.network.bayer import pick_half, split_half
from cscsr.network.blocks import stack_channels
from cscsr.network.config import CSCSRConfig
from cscsr.network.spike_flow import SpikeFlowNet


class MotionEstimation(nn.Module):
    """(B, N, H, W) spikes, (B, 4, H, W) cell masks -> flows (B, N', 2, H, W), and the two key flows."""

    channels_last = False  # the GPU path (cscsr.network.model.use_channels_last): clips stacked NHWC in one write

    def __init__(self, config: CSCSRConfig):
        super().__init__()
        self.config = config
        channels = 4 if config.motion == "joint" else 1
        self.flow = SpikeFlowNet(channels * config.flow_frames, config.flow_features)

    def _clip(self, half: torch.Tensor, centre: int, reverse: bool) -> torch.Tensor:
        """(B, 4, N, h, w) -> (B, 4, K, h, w): the K frames around ``centre``, reversed in time if asked."""
        k = self.config.flow_frames // 2
        clip = half[:, :, centre - k : centre + k + 1]
        return clip.flip(2) if reverse else clip

    def _flow(self, a: torch.Tensor, b: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
        """Two (B, 4, K, h, w) clips -> (B, 2, 2h, 2w) flow at full LR resolution."""
        bsz, _, k, h, w = a.shape
        into = self.flow.encoder[0][0][0].in_channels  # 4K (1K assembled), or a multiple of 8 when padded

        def stacked(clip):  # (B, 4, K, h, w) -> (B, 4K, h, w), or assembled (4B, K, h, w): the reshape, padded
            clip = clip if self.config.motion == "joint" else clip.reshape(bsz * 4, 1, k, h, w)
            return stack_channels(clip, into, self.channels_last)

        if self.config.motion == "joint":
            half_flow = self.flow(stacked(a), stacked(b))  # (B, 2, h, w)
            return 2 * F.interpolate(half_flow, scale_factor=2, mode="bilinear", align_corners=False)
        per_channel = self.flow(stacked(a), stacked(b))  # (4B, 2, h, w)
        per_channel = 2 * per_channel.reshape(bsz, 4, 2, h, w)
        return assemble(per_channel, cells)

    def forward(self, spikes: torch.Tensor, cells: torch.Tensor) -> tuple[torch.Tensor, tuple]:
        cfg = self.config
        middle = cfg.frames // 2
        pick = pick_half if self.channels_last else split_half  # the GPU path: a gather, the same values (0/1 spikes)
        half = pick(spikes, cells)  # (B, 4, N, H/2, W/2)
        forward = self._flow(self._clip(half, middle, False), self._clip(half, middle + cfg.flow_span, False), cells)
        backward = self._flow(self._clip(half, middle, True), self._clip(half, middle - cfg.flow_span, True), cells)
        flows = [(t - middle) / cfg.flow_span * (forward if t > middle else backward) if t != middle
                 else torch.zeros_like(forward) for t in cfg.centres()]
        return torch.stack(flows, 1), (backward, forward)  # (B, N', 2, H, W); middle->first, middle->last


def assemble(per_channel: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """(B, 4, 2, h, w) flows of R, G1, G2, B and (B, 4, 2h, 2w) cell masks -> (B, 2, 2h, 2w).

    Each LR pixel takes the flow of the channel it belongs to (supplement, Fig. 5).
    """
    nearest = per_channel.repeat_interleave(2, -1).repeat_interleave(2, -2)  # (B, 4, 2, 2h, 2w)
    return (nearest * cells[:, :, None]).sum(1)
