"""A mono network's starting weights from a colour (Bayer) one of the same size.

On a grey scene a Bayer sensor sees what a mono one sees, so the colour network's green branch (the
colour sampled at 2 pixels in 4, the closest to a mono sensor's every pixel: the partial convolution
keeps its features on the same scale) is the natural start of the mono branch:

    bssr.1, temporal.1 (green)          -> bssr.0, temporal.0
    motion (R, G1, G2, B cells)          -> motion (the 2x2 cell's four phases: the same split)
    integration.fuse  (F, 3C + 1 + 6)    -> (F, C + 1 + 2): the green features' slice, the reset's, and
                                            each TFP image's R, G and B slices summed (grey: R = G = B)
    integration.heads (3, F)             -> (1, F): the mean of the R, G and B heads
    trunk, upsamplers                    -> as they are
"""

from dataclasses import replace

import torch

from cscsr.network.config import CSCSRConfig
from stages.errors import InputError

GREEN = 1  # the colour branch a mono network starts from


def mono_config_of(colour: CSCSRConfig, name: str | None = None) -> CSCSRConfig:
    """The mono configuration of a colour network's size."""
    return replace(colour, name=name or f"{colour.name}-mono", colours=1).check()


def mono_state(state: dict[str, torch.Tensor], colour: CSCSRConfig) -> dict[str, torch.Tensor]:
    """A colour network's state dict -> a mono network's of the same size (the module docstring's map)."""
    if colour.colours != 3:
        raise InputError(f"a mono network starts from a colour (Bayer) network's weights, not from {colour.name!r}")
    c = colour.colour_features
    out = {}
    for key, value in state.items():
        parts = key.split(".")
        if parts[0] in ("bssr", "temporal"):
            if int(parts[1]) == GREEN:
                out[".".join([parts[0], "0", *parts[2:]])] = value.clone()
        elif key == "integration.fuse.weight":  # (F, 3C + 1 + 6, 3, 3) -> (F, C + 1 + 2, 3, 3)
            features = value[:, GREEN * c : (GREEN + 1) * c]
            reset = value[:, 3 * c : 3 * c + 1]
            whole, middle = value[:, 3 * c + 1 : 3 * c + 4], value[:, 3 * c + 4 : 3 * c + 7]
            out[key] = torch.cat([features, reset, whole.sum(1, keepdim=True), middle.sum(1, keepdim=True)], 1)
        elif key.startswith("integration.heads."):  # (3, F, 3, 3) -> (1, F, 3, 3); bias (3,) -> (1,)
            out[key] = value.mean(0, keepdim=True)
        else:
            out[key] = value.clone()
    return out
