"""TFP (texture from playback): the firing rate of each pixel over a window of frames.

Spike rate is proportional to light, so the mean of the spikes in a window is the simplest
intensity estimate: unbiased for a static scene, blurred by motion inside the window.
"""

import numpy as np

from stages.bits import unpack_rows


def tfp_rate(packed_window: np.ndarray, width: int) -> np.ndarray:
    """(N, H, ceil(W/8)) packed frames -> (H, W) float32 firing rate in [0, 1]."""
    counts = unpack_rows(packed_window, width).sum(axis=0, dtype=np.uint32)
    return (counts / np.float32(packed_window.shape[0])).astype(np.float32)


def tfp_image(packed_window: np.ndarray, *, width: int, cfa: str, gain: float | None = None, scale: int = 1):
    """One window -> (HR uint8 RGB image, gain used): TFP, exposure, demosaic, upsample.

    ``gain`` None means automatic exposure (:func:`stages.colour.auto_gain`).
    """
    from stages.colour import auto_gain, rate_to_rgb

    rate = tfp_rate(packed_window, width)
    gain = auto_gain(rate) if gain is None else gain
    return rate_to_rgb(rate, cfa, gain, scale), gain
