"""Reference pictures made from the ground truth, not from spikes: what a method could reach.

The quality table needs ceilings to read a gap against. Two, both from the HR truth:

- ``exact_lr_bicubic``: the exact LR picture (area mean of each s x s block), enlarged
  bicubically. What any method gets that recovers the LR scene perfectly, then enlarges it.
- ``exact_mosaic_demosaicked``: the exact LR mosaic through the CFA, demosaicked (VNG) and
  enlarged, the same steps as TFP and TFI (``stages.colour``) but with perfect intensities:
  the classic pipeline with no spike noise and no motion blur.
- ``steady_state_mosaic``: the same mosaic read the way a perfect per-pixel estimator reads
  a static scene through the noiseless sensor, from its long-run firing rate. With the
  paper's zero reset a pixel fires every ``ceil(θ/(α·I))`` frames, so every intensity of one
  period reads the same (at α = 1, all of I in [0.5, 1) reads 2/3): this is the ceiling of
  TFP and TFI on such data, and what only spatial and temporal context can beat.
"""

import numpy as np

from stages.colour import demosaic, upsample
from stages.errors import InputError
from stages.sensor import area_downsample, cfa_sample
from stages.tfp import RESETS, undo_zero_reset


def _unit(truth: np.ndarray) -> np.ndarray:
    return np.asarray(truth, np.float32) / np.float32(255)


def _uint8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def exact_lr_bicubic(truth: np.ndarray, scale: int) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (s*H, s*W, 3) uint8: its exact LR picture enlarged bicubically."""
    return _uint8(upsample(area_downsample(_unit(truth), scale), scale))


def exact_mosaic_demosaicked(truth: np.ndarray, cfa: str, scale: int) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (s*H, s*W, 3) uint8: its exact LR mosaic through ``cfa``, VNG, bicubic."""
    mosaic = cfa_sample(area_downsample(_unit(truth), scale), cfa)  # (H, W)
    return _uint8(upsample(demosaic(mosaic, cfa), scale))


def steady_state_mosaic(truth: np.ndarray, cfa: str, scale: int, brightness: float, reset: str) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (s*H, s*W, 3) uint8: its LR mosaic as a static scene's long-run rate reads it.

    ``brightness`` α (threshold fractions gained per frame at intensity 1, θ = 1); ``reset``
    ``zero`` quantises the rate to 1/ceil(1/(α·I)) and undoes the bias as TFP does;
    ``subtract`` reads α·I exactly (then this equals :func:`exact_mosaic_demosaicked`).
    """
    if reset not in RESETS:
        raise InputError(f"unknown reset {reset!r}: expected one of {', '.join(RESETS)}")
    if not 0 < brightness <= 1:
        raise InputError(f"brightness must be in (0, 1], got {brightness!r}")
    rate = np.float32(brightness) * cfa_sample(area_downsample(_unit(truth), scale), cfa)  # (H, W) spikes per frame
    if reset == "zero":
        period = np.ceil(1 / np.maximum(rate, np.float32(1e-12)))  # frames between spikes
        rate = undo_zero_reset(np.where(rate > 0, 1 / period, 0).astype(np.float32))
    return _uint8(upsample(demosaic(rate / np.float32(brightness), cfa), scale))
