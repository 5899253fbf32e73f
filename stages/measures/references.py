"""Reference pictures made from the ground truth, not from spikes: what a method could reach.

The quality table needs ceilings to read a gap against, all from the HR truth:

- ``exact_lr_bicubic``: the exact LR picture (area mean of each s x s block), enlarged
  bicubically. What any method gets that recovers the LR scene perfectly, then enlarges it.
- ``exact_mosaic_demosaicked``: the exact LR mosaic through the CFA, demosaicked (VNG) and
  enlarged, the same steps as TFP and TFI (``stages.reconstruction.colour``) but with perfect intensities:
  the classic pipeline with no spike noise and no motion blur.
- ``steady_state_mosaic``: the same mosaic read the way a perfect per-pixel estimator reads
  a static scene through the noiseless sensor, from its long-run firing rate. With the
  paper's zero reset a pixel fires every ``ceil(θ/(α·I))`` frames, so every intensity of one
  period reads the same (at α = 1, all of I in [0.5, 1) reads 2/3 as TFP reads it): the
  ceiling of TFP and TFI on such data.
- ``read_periods`` with ``mean_level_per_period``: each period read as the mean intensity of
  the pixels that have it in the very pictures scored, the best any estimator of a still pixel
  from its own spikes can do; only spatial and temporal context can beat it.
"""

import numpy as np

from stages.reconstruction.colour import demosaic, upsample
from stages.errors import InputError
from stages.simulation.intensities import to_uint8
from stages.capture.resets import check_reset
from stages.simulation.sensor import area_downsample, cfa_sample
from stages.reconstruction.tfp import undo_zero_reset

NEVER = 1 << 40  # the period of a pixel that never fires


def _unit(truth: np.ndarray) -> np.ndarray:
    return np.asarray(truth, np.float32) / np.float32(255)


def _lr_mosaic(truth: np.ndarray, cfa: str, scale: int) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (H, W) float32 exact LR mosaic in [0, 1]."""
    return cfa_sample(area_downsample(_unit(truth), scale), cfa)


def _check_brightness(brightness: float) -> None:
    if not 0 < brightness <= 1:
        raise InputError(f"brightness must be in (0, 1], got {brightness!r}")


def exact_lr_bicubic(truth: np.ndarray, scale: int) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (s*H, s*W, 3) uint8: its exact LR picture enlarged bicubically."""
    return to_uint8(upsample(area_downsample(_unit(truth), scale), scale))


def exact_mosaic_demosaicked(truth: np.ndarray, cfa: str, scale: int) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (s*H, s*W, 3) uint8: its exact LR mosaic through ``cfa``, VNG, bicubic."""
    return to_uint8(upsample(demosaic(_lr_mosaic(truth, cfa, scale), cfa), scale))


def zero_reset_periods(truth: np.ndarray, cfa: str, scale: int, brightness: float) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (H, W) int64: frames between spikes of each LR pixel of the still scene.

    The noiseless zero-reset sensor at ``brightness`` α (θ = 1) fires every ceil(1/(α·I)) frames;
    a dark pixel never fires (``NEVER``).
    """
    return _periods(_lr_mosaic(truth, cfa, scale), brightness)


def _periods(mosaic: np.ndarray, brightness: float) -> np.ndarray:
    """(H, W) LR intensities -> (H, W) int64 frames between spikes (see :func:`zero_reset_periods`)."""
    _check_brightness(brightness)
    rate = np.float64(brightness) * mosaic  # (H, W) α·I
    return np.where(rate > 0, np.ceil(1 / np.maximum(rate, 1 / NEVER)), NEVER).astype(np.int64)


def steady_state_mosaic(truth: np.ndarray, cfa: str, scale: int, brightness: float, reset: str) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (s*H, s*W, 3) uint8: its LR mosaic as a static scene's long-run rate reads it.

    ``brightness`` α (threshold fractions gained per frame at intensity 1, θ = 1); ``reset``
    ``zero`` quantises the rate to 1/ceil(1/(α·I)) and undoes the bias as TFP does;
    ``subtract`` reads α·I exactly (then this equals :func:`exact_mosaic_demosaicked`).
    """
    check_reset(reset)
    if reset == "subtract":
        _check_brightness(brightness)
        return exact_mosaic_demosaicked(truth, cfa, scale)
    period = zero_reset_periods(truth, cfa, scale, brightness)  # (H, W)
    intensity = undo_zero_reset((1 / period).astype(np.float32)) / np.float32(brightness)
    return to_uint8(upsample(demosaic(intensity, cfa), scale))


def mean_level_per_period(truths: list[np.ndarray], cfa: str, scale: int, brightness: float) -> dict[int, float]:
    """Period -> mean LR intensity of the pixels with that period over ``truths``.

    The least-squares reading of each period for exactly these pictures: an oracle, fitted to
    the truth, about the best any estimator reading a still pixel's period alone can do.
    """
    levels = np.concatenate([_lr_mosaic(t, cfa, scale).ravel() for t in truths])
    periods = _periods(levels, brightness)
    found, index = np.unique(periods, return_inverse=True)
    means = np.bincount(index, weights=levels) / np.bincount(index)
    return dict(zip(found.tolist(), means.tolist()))


def read_periods(truth: np.ndarray, cfa: str, scale: int, brightness: float, levels: dict[int, float]) -> np.ndarray:
    """(s*H, s*W, 3) uint8 HR truth -> (s*H, s*W, 3) uint8: each LR pixel's period read as ``levels[period]``."""
    period = zero_reset_periods(truth, cfa, scale, brightness)  # (H, W)
    missing = set(np.unique(period).tolist()) - set(levels)
    if missing:
        raise InputError(f"no level for period(s) {sorted(missing)[:5]}: fit the levels on this picture too")
    intensity = np.vectorize(levels.__getitem__, otypes=[np.float32])(period)
    return to_uint8(upsample(demosaic(intensity, cfa), scale))
