"""Rate image -> HR RGB image: exposure, demosaicking (OpenCV edge-aware) and upsampling.

The contract's brightness rule: the written value is ``clip(rate * gain, 0, 1) * 255``.
Bayer rates are demosaicked with OpenCV's VNG (variable number of gradients) Bayer
conversion on an 8-bit copy: on the bundled pictures it beats OpenCV's edge-aware and
bilinear conversions by 4.3 dB (e.g. 32.0 vs 27.7 dB on a 96 px crop of ``coffee``), and
the output is 8-bit anyway. Every colour is then upsampled by bicubic interpolation;
``mono`` repeats the grey plane in R, G and B.
"""

import numpy as np

from stages.reconstruction.cfa import opencv_bayer_code
from stages.errors import InputError
from stages.numbers import FLOAT32_MAX, check_number

CLASSIC_SCALES = (1, 2, 3, 4, 8)  # what the classic methods and previews upsample by
_MID_GREY = 0.45
_CLIP_QUANTILE = 0.99
# The largest gain a user may give: a firing rate is spikes per frame, so at gain G a pixel that fires once in
# G frames is already full white. At 10^6 that is one spike in 50 s at 20,000 fps, dimmer than any window a
# picture is made from; a larger gain only turns every pixel that fired at all white (1e30: white frames).
MAX_GAIN = 1e6
MAX_GAIN_WHY = "at that gain one spike in a million frames is already full white"


def check_gain(name: str, gain) -> None:
    """Refuse a gain that is not a finite number in (0, MAX_GAIN] (``name``: the flag or what it comes from)."""
    check_number(name, gain, above=0, at_most=MAX_GAIN, why=MAX_GAIN_WHY)


def auto_gain(rate: np.ndarray) -> float:
    """A gain that puts the mean at mid grey, reduced so at most 1 % of pixels clip."""
    mean = float(rate.mean())
    if mean <= 0:
        return 1.0
    high = float(np.quantile(rate, _CLIP_QUANTILE))
    return min(_MID_GREY / mean, 1.0 / high) if high > 0 else _MID_GREY / mean


# Columns of mirrored mosaic VNG is given beyond an image's right edge (even: the Bayer phase is kept). OpenCV's
# VNG computes most of a row with vector instructions and its last few pixels (fewer than one vector) with
# scalar code that can round a level apart, so a pixel's value depended on where its row ended: a tile's right
# columns differed from the whole frame's by a level (2026-11-29, TFP at tile 8 against 16). Given these columns,
# every pixel of the image is computed by the vector code, wherever its tile ends.
VNG_TAIL = 64


def demosaic(intensity: np.ndarray, cfa: str) -> np.ndarray:
    """(H, W) float in [0, 1] sampled through ``cfa`` -> (H, W, 3) float32 RGB in [0, 1]; a pixel's value depends
    only on its 5x5 neighbourhood (and the image's edges within it), not on the image's width."""
    if cfa == "mono":
        return np.repeat(intensity[:, :, None], 3, axis=2).astype(np.float32)
    import cv2

    mosaic = np.round(np.clip(intensity, 0, 1) * 255).astype(np.uint8)  # VNG takes 8-bit only
    width = mosaic.shape[1]
    mosaic = np.pad(mosaic, ((0, 0), (0, VNG_TAIL)), mode="reflect")  # mirrored about the last column: same phase
    return cv2.cvtColor(mosaic, opencv_bayer_code(cfa))[:, :width].astype(np.float32) / np.float32(255)


def upsample(rgb: np.ndarray, scale: int) -> np.ndarray:
    """Bicubic x``scale`` enlargement of an (H, W, 3) float image, clipped to [0, 1]."""
    if scale == 1:
        return rgb
    import cv2

    height, width = rgb.shape[:2]
    big = cv2.resize(rgb, (width * scale, height * scale), interpolation=cv2.INTER_CUBIC)
    return np.clip(big, 0, 1)


def check_scale(name: str, scale) -> None:
    """Refuse an upsampling factor the classic methods cannot make (``name``: the flag or attribute)."""
    if scale not in CLASSIC_SCALES or isinstance(scale, bool):
        raise InputError(f"{name} must be one of {', '.join(map(str, CLASSIC_SCALES))}, got {scale}")


def rate_to_rgb(rate: np.ndarray, cfa: str, gain: float, scale: int = 1) -> np.ndarray:
    """(H, W) firing rate -> (s*H, s*W, 3) uint8 RGB: exposure, demosaic, upsample."""
    check_scale("scale", scale)
    rgb = upsample(demosaic(np.clip(exposed(rate, gain), 0, 1), cfa), scale)
    return np.round(rgb * 255).astype(np.uint8)


def expose(rgb_rate: np.ndarray, gain: float) -> np.ndarray:
    """(..., 3) RGB firing rates -> uint8 by the contract's rule ``clip(rate * gain, 0, 1) * 255``."""
    return np.round(np.clip(exposed(rgb_rate, gain), 0, 1) * 255).astype(np.uint8)


def exposed(rate: np.ndarray, gain: float) -> np.ndarray:
    """``rate * gain`` in float32, refused unless every value is finite: NaN or infinity would become
    black or noise in uint8, and a picture made of them must never be written as a good one."""
    check_number("gain", gain, above=0, at_most=FLOAT32_MAX)
    values = rate * np.float32(gain)
    if not np.isfinite(values).all():
        bad = int(values.size - np.isfinite(values).sum())
        raise ValueError(f"{bad} of {values.size} values of the exposed image are not finite (NaN or infinity): "
                         f"the image is not written")
    return values
