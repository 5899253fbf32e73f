"""Channel counts zero-padded to multiples of 8 when the weights load for the GPU path (#53): the same function.

Tensor cores take channel counts in multiples of 8; ``full``'s 50 colour features (and the 101, 157 and 84
channels of what they feed) are not, and those convolutions carried 45 % of its FLOPs. :func:`pad_channels`
rebuilds every convolution with its channel counts rounded up to a multiple of 8: the real weights in place,
zeros elsewhere, so every padded feature channel is exactly 0 (zero weights and zero bias, then ReLU or
sigmoid gates multiplying 0) and no real output changes. The places that join channels write the padding in
(``cscsr.network.blocks.cat_channels``, ``stack_channels``: their width is read from the padded convolution
that consumes them), the convolutions whose outputs are not features (the flow decoders' 2 channels, the RGB
heads) keep their first channels (:class:`Narrow`), and the flow network's correlation averages over the real
channels (``SpikeFlowNet.real_widths``). The weight files are untouched: this runs on the loaded model.
fp32 outputs equal the unpadded model's within float rounding (tested: within 1e-5).
"""

import torch
from torch import nn

from cscsr.network.base_image import aligned_kernel

MULTIPLE = 8


def padded(n: int) -> int:
    return -(-n // MULTIPLE) * MULTIPLE


class Narrow(nn.Module):
    """A convolution with padded outputs, giving its first ``channels`` (a view: nothing moves)."""

    def __init__(self, conv: nn.Module, channels: int):
        super().__init__()
        self.conv, self.channels = conv, channels

    def forward(self, x):
        return self.conv(x)[:, : self.channels]


def _conv(conv, in_index: list[int], in_total: int, out_index: list[int], out_total: int):
    """``conv`` rebuilt with ``in_total`` inputs and ``out_total`` outputs, its weights at those positions."""
    kind = type(conv)
    new = kind(in_total, out_total, conv.kernel_size, conv.stride, conv.padding, bias=conv.bias is not None)
    new = new.to(conv.weight.device, conv.weight.dtype)
    with torch.no_grad():
        new.weight.zero_()
        rows = torch.as_tensor(out_index, device=conv.weight.device)
        cols = torch.as_tensor(in_index, device=conv.weight.device)
        new.weight[rows[:, None], cols[None, :]] = conv.weight
        if conv.bias is not None:
            new.bias.zero_()
            new.bias[rows] = conv.bias
    return new


def _part(conv, inputs: list[int], bias: bool):
    """A convolution of some of ``conv``'s inputs, with or without its bias."""
    part = type(conv)(len(inputs), conv.out_channels, conv.kernel_size, conv.stride, conv.padding, bias=bias)
    part = part.to(conv.weight.device, conv.weight.dtype)
    with torch.no_grad():
        part.weight.copy_(conv.weight[:, inputs])
        if bias:
            part.bias.copy_(conv.bias)
    return part


def _prefix(conv, n_in: int, n_out: int):
    """A convolution whose inputs and outputs are features padded at the end (the real ones first)."""
    return _conv(conv, list(range(n_in)), padded(n_in), list(range(n_out)), padded(n_out))


def _per_time(t: int, c: int) -> list[int]:
    """Where time point i's channel j of (N'*C) channels lands among N'*C' padded ones."""
    return [i * padded(c) + j for i in range(t) for j in range(c)]


def pad_channels(model: nn.Module) -> nn.Module:
    """Pad ``model``'s (a :class:`cscsr.network.model.CSCSR`) channel counts to multiples of 8, in place; any
    configuration (colour or mono, joint or assembled motion, with or without flow guidance). Returns it."""
    cfg = model.config
    c, t, f, k = cfg.colour_features, cfg.time_points, cfg.features, cfg.colours
    cp = padded(c)
    # the colour features as the temporal pixels take them: with a spare padded channel for the warped mask (50 -> 56);
    # where there is none (lite's 24), 8 more channels, which the BSSR writes its output into (24 -> 32)
    width = padded(c + 1) if cfg.flow_guidance else cp
    for bssr in model.bssr:
        bssr.width = width
        window = bssr.window  # (C, 1, w, 3, 3): a Conv3d run as a 2D convolution over the w frames
        bssr.window = _conv(window, [0], 1, list(range(c)), cp)
        w = window.kernel_size[0]
        frames = torch.zeros(cp, padded(w), 3, 3, dtype=window.weight.dtype, device=window.weight.device)
        frames[:c, :w] = window.weight[:, 0].detach()
        bssr.register_buffer("window_padded", frames, persistent=False)  # (C', 16, 3, 3): frames past w weigh 0
        bssr.bias = nn.Parameter(torch.cat([bssr.bias.detach(), bssr.bias.new_zeros(cp - c)]))
        bssr.mix[0] = _prefix(bssr.mix[0], c, c)
        gate = bssr.attention.gate  # pool, (N'C -> N'C/4) conv, ReLU, (N'C/4 -> N'C) conv, sigmoid
        r = gate[1].out_channels
        gate[1] = _conv(gate[1], _per_time(t, c), t * cp, list(range(r)), padded(r))
        gate[3] = _conv(gate[3], list(range(r)), padded(r), _per_time(t, c), t * cp)
    for temporal in model.temporal:
        refine = temporal.refine[0][0]  # [warped x (C'), middle (C'), warped mask (1)] -> C
        joined = list(range(c)) + list(range(cp, cp + c)) + [2 * cp]
        temporal.refine[0][0] = _conv(refine, joined, padded(2 * cp + 1), list(range(c)), cp)
        if cfg.flow_guidance:  # a spare channel in x for the mask: the first conv split in two, no concatenation
            temporal.refine_x = _conv(_part(refine, list(range(c)) + [2 * c], bias=False), list(range(c + 1)), width,
                                      list(range(c)), cp)  # (x, mask in x's channel C) -> C  (the GPU path)
            temporal.refine_c = _conv(_part(refine, list(range(c, 2 * c)), bias=True), list(range(c)), width,
                                      list(range(c)), cp)  # middle -> C, with the bias: once a clip, broadcast
            temporal.mask_slot = c
        temporal.refine[1] = _prefix(temporal.refine[1], c, c)
        temporal.fuse[0][0] = _conv(temporal.fuse[0][0], _per_time(t, c), t * cp, list(range(c)), cp)
        temporal.fuse[1][0] = _prefix(temporal.fuse[1][0], c, c)
    _pad_integration(model.integration, c, f, k)
    if not cfg.mono:  # the base image's demosaicking: its two 3-channel grouped convolutions as one of 8 channels
        model.register_buffer("demosaic_kernel", aligned_kernel(MULTIPLE).to(model.integration.fuse.weight),
                              persistent=False)
    if model.motion is not None:
        _pad_flow(model.motion.flow)
    return model


def _pad_integration(integration, c: int, f: int, k: int) -> None:
    cp, fp = padded(c), padded(f)
    fuse = integration.fuse  # [k colours' C', reset (1), LR images] -> F
    images = fuse.in_channels - k * c - 1
    joined = [j * cp + i for j in range(k) for i in range(c)] + [k * cp + i for i in range(1 + images)]
    integration.fuse = _conv(fuse, joined, padded(k * cp + 1 + images), list(range(f)), fp)
    for block in integration.trunk[:-1]:
        block.body[0] = _prefix(block.body[0], f, f)
        block.body[2] = _prefix(block.body[2], f, f)
    integration.trunk[-1] = _prefix(integration.trunk[-1], f, f)
    for up in integration.up:  # conv to 4F, pixel shuffle: output channel 4i + j becomes feature i
        up[0] = _conv(up[0], list(range(f)), fp, [4 * i + j for i in range(f) for j in range(4)], 4 * fp)
    # the GPU path's heads read the upsampling conv's output before its pixel shuffle (no 4x-size shuffle of F channels)
    integration.shuffled_heads = nn.ModuleList([_shuffled_head(head, 4 * fp) for head in integration.heads])
    for step, head in enumerate(integration.heads):
        integration.heads[step] = Narrow(_prefix(head, f, head.out_channels), head.out_channels)


def _shuffled_head(head, into: int):
    """A 3x3 head (F -> K) of pixel-shuffled features (B, F, 2H, 2W) as a 3x3 convolution of the (B, ``into``, H, W)
    features before the shuffle (channel 4i + 2p + q: feature i at sub-pixel (p, q), as ``pixel_shuffle`` reads
    them): output channel 4k + 2p + q is colour k at sub-pixel (p, q), so ``pixel_shuffle`` of the first 4K gives the
    head's output. The same sums: each of the head's 3x3 taps of an output sub-pixel lands on one tap of one
    sub-pixel channel. Outputs padded to a multiple of 8 (zeros)."""
    k, f = head.out_channels, head.in_channels
    new = nn.Conv2d(into, padded(4 * k), 3, 1, 1).to(head.weight.device, head.weight.dtype)
    colours = torch.arange(k, device=head.weight.device)
    features = torch.arange(f, device=head.weight.device)
    with torch.no_grad():
        new.weight.zero_()
        new.bias.zero_()
        for p in (0, 1):
            for q in (0, 1):
                rows = 4 * colours + 2 * p + q
                new.bias[rows] = head.bias
                for dy in (-1, 0, 1):
                    for dx in (-1, 0, 1):
                        ey, sp = divmod(p + dy, 2)  # the shuffled row 2y + p + dy is sub-pixel row sp of row y + ey
                        ex, sq = divmod(q + dx, 2)
                        cols = 4 * features + 2 * sp + sq
                        new.weight[rows[:, None], cols[None, :], ey + 1, ex + 1] = head.weight[:, :, dy + 1, dx + 1]
    return new


def _pad_flow(net) -> None:
    stages = [net.encoder[level] for level in range(3)]
    widths = [stage[1][0].out_channels for stage in stages]  # f0, f1, f2
    previous = stages[0][0][0].in_channels  # the stacked clip's frames
    for stage, width in zip(stages, widths):
        stage[0][0] = _prefix(stage[0][0], previous, width)
        stage[1][0] = _prefix(stage[1][0], width, width)
        previous = width
    for level, decoder in enumerate(net.decoders):  # [cost, own features (f'), flow (2, not at 1/4)] -> 2f
        first = decoder.body[0][0]
        costs = (2 * net.RADII[level] + 1) ** 2
        flow = first.in_channels - costs - widths[level]
        joined = list(range(costs + widths[level])) + [costs + padded(widths[level]) + i for i in range(flow)]
        hidden = first.out_channels
        decoder.body[0][0] = _conv(first, joined, padded(costs + padded(widths[level]) + flow), list(range(hidden)),
                                   padded(hidden))
        decoder.body[1][0] = _prefix(decoder.body[1][0], hidden, decoder.body[1][0].out_channels)
        last = decoder.body[2]
        decoder.body[2] = Narrow(_prefix(last, last.in_channels, last.out_channels), last.out_channels)
    net.real_widths = tuple(widths)
