"""TFP (texture from playback): the firing rate of each pixel over a window of frames.

Spike rate is proportional to light, so the mean of the spikes in a window is the simplest
intensity estimate: unbiased for a static scene, blurred by motion inside the window.

A sensor that resets its accumulator to zero (``reset="zero"``, the paper's simulator)
throws away the remainder above the threshold at every spike: on average half a frame's
worth, rho/2 in units of the threshold for true rate rho. Each spike then costs 1 + rho/2,
so the measured rate is r = rho / (1 + rho/2); :func:`undo_zero_reset` inverts that
(rho = r / (1 - r/2)), which removes the brightness bias (up to -17 % at rho = 0.4).
"""

import numpy as np

from stages.capture.bits import unpack_rows


def undo_zero_reset(rate: np.ndarray) -> np.ndarray:
    """Measured rate of a zero-reset sensor -> the rate alpha*I/theta that produced it."""
    return (rate / (1 - rate / 2)).astype(np.float32)


def tfp_rate(packed_window: np.ndarray, width: int, reset: str = "subtract") -> np.ndarray:
    """(N, H, ceil(W/8)) packed frames -> (H, W) float32 rate alpha*I/theta."""
    counts = unpack_rows(packed_window, width).sum(axis=0, dtype=np.uint32)
    rate = (counts / np.float32(packed_window.shape[0])).astype(np.float32)
    return undo_zero_reset(rate) if reset == "zero" else rate


def tfp_image(packed_window: np.ndarray, *, width: int, cfa: str, gain: float | None = None, scale: int = 1,
              reset: str = "subtract"):
    """One window -> (HR uint8 RGB image, gain used): TFP, exposure, demosaic, upsample.

    ``gain`` None means automatic exposure (:func:`stages.reconstruction.colour.auto_gain`).
    """
    from stages.reconstruction.colour import auto_gain, rate_to_rgb

    rate = tfp_rate(packed_window, width, reset)
    gain = auto_gain(rate) if gain is None else gain
    return rate_to_rgb(rate, cfa, gain, scale), gain
