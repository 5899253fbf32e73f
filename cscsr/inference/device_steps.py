"""The pipeline's steps around the network, in torch, so they run where the network runs.

On a GPU worker the packed spike bits go to the device (1/32 of the float32 spikes' bytes), are
unpacked there, and only the exposed uint8 HR image comes back (1/4 of the float32 image's bytes).
Each step is the twin of a numpy step in ``stages`` and gives the same bytes (tested):

- :func:`unpack_bits` is :func:`stages.capture.bits.unpack_rows` (bit k of byte b is pixel 8b + k);
- :func:`expose_uint8` is :func:`stages.reconstruction.colour.expose` (``round(clip(rate * gain, 0, 1) * 255)``, float32,
  halves to even), refusing non-finite values as :func:`stages.reconstruction.colour.exposed` does.
"""

import numpy as np
import torch

from stages.numbers import FLOAT32_MAX, check_number

_BITS = {}  # device -> (8,) uint8 [0..7]: the shifts that take bit k of a byte to bit 0


def unpack_bits(packed: torch.Tensor, width: int) -> torch.Tensor:
    """(..., ceil(W/8)) uint8 -> (..., W) uint8 of 0/1, little-endian bits, on ``packed``'s device."""
    shifts = _BITS.get(packed.device)
    if shifts is None:
        shifts = _BITS[packed.device] = torch.arange(8, dtype=torch.uint8, device=packed.device)
    bits = (packed.unsqueeze(-1) >> shifts) & 1  # (..., ceil(W/8), 8)
    return bits.flatten(-2)[..., :width]


def expose_uint8(rate: torch.Tensor, gain: float) -> torch.Tensor:
    """(..., 3) float32 RGB firing rates -> uint8 by the contract's rule, on ``rate``'s device.

    The gain is taken as float32 first (as numpy does for ``rate * np.float32(gain)``), so every
    product, and then every byte, is what :func:`stages.reconstruction.colour.expose` gives."""
    check_number("gain", gain, above=0, at_most=FLOAT32_MAX)
    values = rate * float(np.float32(gain))  # float32 x an exactly representable scalar: rounded as numpy rounds
    if not bool(torch.isfinite(torch.stack([values.amax(), values.amin()])).all()):  # NaN and infinities show in
        bad = int(values.numel() - torch.isfinite(values).sum())  # the extremes: two reductions, not a mask
        raise ValueError(f"{bad} of {values.numel()} values of the exposed image are not finite (NaN or infinity): "
                         f"the image is not written")
    return torch.round(values.clamp_(0, 1).mul_(255)).to(torch.uint8)
