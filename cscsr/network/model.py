"""CSCSR: a clip of N LR Bayer spike frames -> one HR RGB image at its middle frame.

Algorithm 1 of the paper, one module per step:

    spikes (B, N, H, W), CFA per clip
      -> BSSR per colour R, G, B          (B, N', C, H, W) each          cscsr.network.bssr
      -> joint motion estimation          (B, N', 2, H, W) flows         cscsr.network.motion_estimation
      -> temporal-pixel features          (B, C, H, W) per colour        cscsr.network.temporal_pixels
      -> integration, pixel shuffle x s   (B, 3, sH, sW) residual        cscsr.network.integration
         (also fed the demosaicked TFP over the clip and its middle w frames, (B, 6, H, W))
      +  demosaicked bicubic TFP base     (B, 3, sH, sW)                 cscsr.network.base_image

Values are firing rates alpha*I/theta (what TFP estimates), so exposure stays the
pipeline's business. Any even H, W: the clip is padded (by reflection, which keeps the
Bayer phase) to a multiple of 16 and the output cropped back.
"""

import torch
import torch.nn.functional as F
from torch import nn

from cscsr.network.base_image import base_image, lr_images
from cscsr.network.bayer import cell_masks, check_cfa, colour_masks
from cscsr.network.blocks import ResBlock
from cscsr.network.bssr import BSSR
from cscsr.network.config import CSCSRConfig
from cscsr.network.integration import NETWORK_SCALES, Integration
from cscsr.network.motion_estimation import MotionEstimation
from cscsr.network.spike_flow import FlowDecoder
from cscsr.network.temporal_pixels import TemporalPixels
from cscsr.network.warp import SharedFlow
from stages.errors import InputError

MULTIPLE = 16  # LR sides the network runs at: half resolution, then the flow pyramid's 1/4


class CSCSR(nn.Module):
    def __init__(self, config: CSCSRConfig):
        super().__init__()
        self.config = config.check()
        c, t, k = config.colour_features, config.time_points, config.colours  # k: R, G, B, or mono's one
        self.bssr = nn.ModuleList([BSSR(c, config.length, config.stride, t) for _ in range(k)])
        self.motion = MotionEstimation(config) if config.flow_guidance else None
        self.temporal = nn.ModuleList([TemporalPixels(c, t, config.flow_guidance) for _ in range(k)])
        self.integration = Integration(c, config.features, config.blocks, k)
        self.channels_last = False  # memory format of the activations (``use_channels_last``); default NCHW
        initialise(self)

    def forward(self, spikes: torch.Tensor, cfa: str | list[str], zero_reset=False, scale: int = 4) -> dict:
        """(B, N, H, W) 0/1 spikes -> {"image": (B, 3, sH, sW), "flows": middle->first and ->last
        (B, 2, H, W) each or None, "base": (B, 3, sH, sW)}. A mono network takes cfa "mono" and gives its grey
        image as three equal channels."""
        b, n, h, w = self.check_input(spikes, scale)
        mono = self.config.mono
        cfas = [check_cfa(cfa, mono)] * b if isinstance(cfa, str) else [check_cfa(c, mono) for c in cfa]
        if len(cfas) != b:
            raise InputError(f"{len(cfas)} CFA patterns for a batch of {b} clips")
        zero = torch.as_tensor(zero_reset, device=spikes.device).expand(b).bool()

        x = pad_keeping_phase(spikes.to(self.dtype), MULTIPLE, phase=not mono)  # (B, N, Hp, Wp), weights' dtype
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)  # (B, N, Hp, Wp) stored as (B, Hp, Wp, N)
        cells = cell_masks(cfas, x.shape[-2], x.shape[-1], x.device, x.dtype)  # (B, 4, Hp, Wp) R, G1, G2, B (mono:
        # phases), in the network's dtype
        colours = colour_masks(cells, mono)  # (B, 3, Hp, Wp) R, G, B; mono (B, 1, Hp, Wp) ones
        if self.motion is not None:
            flows, key_flows = self.motion(x, cells)  # (B, N', 2, Hp, Wp)
        else:
            flows, key_flows = None, None
        k = self.config.colours
        warped = [None] * k  # the colours' masks warped by the flows (the GPU path: all k in one pass)
        if flows is not None:  # every colour warps by the same flows: one sampling plan for all (bf16 GPU path)
            flows = SharedFlow(flows.flatten(0, 1))  # (B*N', 2, Hp, Wp)
            if self.channels_last:
                masks = flows.warp(per_time_point(colours, self.config.time_points), padding="zeros")
                warped = [masks[:, c : c + 1] for c in range(k)]  # k x (B*N', 1, Hp, Wp)
        features = [self.temporal[c](self.bssr[c](x, colours[:, c : c + 1]), colours[:, c : c + 1], flows, warped[c])
                    for c in range(k)]  # k x (B, C, Hp, Wp)
        kernel = getattr(self, "demosaic_kernel", None)  # the GPU path's (cscsr.network.padding): one aligned conv
        images = lr_images(x, colours, zero, self.config.length, kernel)  # (B, 2k, Hp, Wp)
        residual = self.integration(features, images, zero, scale)  # (B, k, s*Hp, s*Wp)
        base = base_image(images[:, :k], scale)  # (B, k, s*Hp, s*Wp)
        image = (base + residual)[..., : scale * h, : scale * w]
        if mono:  # grey as the video store's three equal channels: export, evaluate, open_video need no case
            image, base = image.expand(-1, 3, -1, -1), base.expand(-1, 3, -1, -1)  # (B, 3, sH, sW) views
        if key_flows is not None:
            key_flows = tuple(f[..., :h, :w] for f in key_flows)
        return {"image": image, "flows": key_flows, "base": base[..., : scale * h, : scale * w]}

    @property
    def dtype(self) -> torch.dtype:
        """The network's arithmetic without autocast: its weights' dtype (float32; bfloat16 on the GPU path)."""
        return self.integration.fuse.weight.dtype

    def check_input(self, spikes: torch.Tensor, scale: int) -> tuple[int, int, int, int]:
        if spikes.ndim != 4:
            raise InputError(f"spikes must be (batch, frames, height, width), got shape {tuple(spikes.shape)}")
        b, n, h, w = spikes.shape
        if n != self.config.frames:
            raise InputError(f"the {self.config.name} network takes {self.config.frames} frames per clip, got {n}")
        if not self.config.mono and (h % 2 or w % 2 or h < 2 or w < 2):  # mono: any side, 1 too (padded)
            raise InputError(f"a Bayer clip needs even height and width, got {h}x{w}")
        if scale not in NETWORK_SCALES:
            raise InputError(f"the CSCSR network upsamples by {' or '.join(map(str, NETWORK_SCALES))}, not {scale}")
        return b, n, h, w

    def parameter_counts(self) -> dict[str, int]:
        """Trainable parameters: the reconstruction network (as the paper counts) and the flow network."""
        flow = sum(p.numel() for p in self.motion.parameters()) if self.motion is not None else 0
        total = sum(p.numel() for p in self.parameters())
        return {"network": total - flow, "flow": flow, "total": total}


def use_channels_last(model: CSCSR, on: bool = True) -> CSCSR:
    """Store the 4-D weights and the input channels-last (NHWC), so convolutions run on that layout (faster on
    GPUs' tensor cores, measured on the CPU in docs/performance.md); the same result within float rounding,
    not bit for bit. ``on=False`` goes back to the default layout. Returns the model."""
    model.channels_last = on
    for module in model.modules():
        if hasattr(type(module), "channels_last"):  # the network's steps that lay their own tensors out (#53)
            module.channels_last = on
        for name, tensor in [*module.named_parameters(recurse=False), *module.named_buffers(recurse=False)]:
            if tensor.dim() in (4, 5):  # the 3D convolutions' weights NDHWC
                layout = (torch.channels_last if tensor.dim() == 4 else torch.channels_last_3d) if on \
                    else torch.contiguous_format
                tensor.data = tensor.data.contiguous(memory_format=layout)
    return model


def per_time_point(x: torch.Tensor, t: int) -> torch.Tensor:
    """(B, K, H, W) -> (B*t, K, H, W) as ``x.repeat_interleave(t, 0)``, stored channels-last: one write."""
    b, k, h, w = x.shape
    out = torch.empty((b, t, h, w, k), dtype=x.dtype, device=x.device)
    out.copy_(x.permute(0, 2, 3, 1)[:, None])  # broadcast over the t time points
    return out.view(b * t, h, w, k).permute(0, 3, 1, 2)


def initialise(model: nn.Module) -> None:
    """He initialisation for every convolution (PyTorch's default shrinks activations layer by layer,
    which left a 40-layer network learning nothing in hundreds of steps), residual branches scaled
    by 0.1 so the trunk starts near identity. Layers that must start at zero keep their own init."""
    keep = set()
    for module in model.modules():
        if isinstance(module, FlowDecoder):
            keep.add(module.body[-1])
        if isinstance(module, Integration):
            keep.update(module.heads)
    for module in model.modules():
        if isinstance(module, (nn.Conv2d, nn.Conv3d)) and module not in keep:
            nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
            if module.bias is not None:
                nn.init.zeros_(module.bias)
    for module in model.modules():
        if isinstance(module, ResBlock):
            module.body[-1].weight.data.mul_(0.1)


def pad_keeping_phase(x: torch.Tensor, multiple: int, phase: bool = True) -> torch.Tensor:
    """Pad the bottom and right by reflection to a multiple of ``multiple``.

    An even pad of an even side by reflection puts every padded row and column on a row
    and column of the same parity, so the Bayer pattern continues unbroken. ``phase=False`` (mono: no
    pattern to keep) reflects by any amount, so an odd side pads too.
    """
    h, w = x.shape[-2:]
    ph, pw = -h % multiple, -w % multiple
    for axis, pad in ((-2, ph), (-1, pw)):
        while pad:  # a small frame may need several reflections
            size = x.shape[axis]
            step = min(pad, size - 1) // 2 * 2 if phase else min(pad, size - 1)
            mode = "reflect" if step else "circular"  # a 2-pixel side: repeat the whole 2x2 cell
            step = step or min(pad, size)
            x = F.pad(x, (0, step, 0, 0) if axis == -1 else (0, 0, 0, step), mode=mode)
            pad -= step
    return x
