"""Colour spike camera sensor model: HR RGB frames -> LR Bayer spike frames (CSCSR, Algorithm 2).

The simulator area-downsamples each latent frame by ``s``, samples it through the colour
filter array and integrates and fires: a pixel of intensity ``I`` in [0, 1] gains
``α·I`` per frame (α = brightness) and spikes when its accumulator reaches ``θ``
(threshold). Reset ``subtract`` keeps the remainder (real sensors: rate ``α·I/θ``);
reset ``zero`` empties it (the paper: rate ``1/ceil(θ/(α·I))``). No pixel fires more
than once per frame, so ``α·I/θ`` is clipped to [0, 1].

Why integers: the pipeline simulates time chunks on different workers and needs
bit-identical spikes however the frames are chunked. The accumulator therefore counts
``UNITS`` (2^24) units per threshold θ in int64, and each frame adds an integer
increment ``q = round(clip(α·I/θ, 0, 1) · UNITS)``; every random draw is keyed by the
seed and the absolute frame number, never by the chunk.

Realistic noise (``noise="realistic"``, all from ``seed``):

* shot noise: ``electrons_per_threshold`` photo-electrons fill one θ, so an increment of
  mean ``m`` units has variance ``m · UNITS / electrons_per_threshold`` (Gaussian
  approximation of Poisson, drawn per frame; it overestimates the mean slightly below a
  few electrons per frame, where negative draws clip to 0);
* threshold mismatch (fixed pattern): per-pixel ``θ · (1 + threshold_mismatch · z)``;
* dark current (fixed pattern): ``dark_rate`` θ per frame on average, lognormal across
  pixels (log-std ``DARK_SPREAD``), added to the signal before shot noise.

A pixel holds at most one spike's worth of charge: after a subtract reset the remainder is
capped below the threshold (this only matters where mismatch makes a threshold < UNITS).
"""

import sys
import threading
from dataclasses import dataclass

import numba
import numpy as np

from stages.capture.bits import count_spikes, packed_width
from stages.capture.resets import RESETS, check_reset  # noqa: F401 - the sensor's resets, named here too
from stages.reconstruction.cfa import check_cfa, colour_index
from stages.errors import InputError
from stages.simulation.intensities import LUMA

UNITS: int = 1 << 24
NOISES = ("none", "realistic")
_MAX_UNITS = 1 << 30  # state and thresholds below this keep acc + q inside int32
DARK_SPREAD = 0.5  # log-std of the per-pixel dark current (lognormal, mean dark_rate)

# Random streams, keyed default_rng([seed, stream(, frame)]) so chunking never changes a draw.
_STATE_STREAM, _THRESHOLD_STREAM, _SHOT_STREAM, _DARK_STREAM = 0, 1, 2, 3


def area_downsample(image: np.ndarray, scale: int) -> np.ndarray:
    """(s*H, s*W[, C]) float -> (H, W[, C]) float32: the exact mean of each s x s block."""
    image = np.asarray(image)
    if int(scale) != scale or scale < 1:
        raise InputError(f"scale must be a positive integer, got {scale!r}")
    scale = int(scale)
    if image.ndim not in (2, 3):
        raise InputError(f"expected an (H, W) or (H, W, C) image, got shape {image.shape}")
    height, width = image.shape[:2]
    if height % scale or width % scale:
        raise InputError(f"image of {height}x{width} pixels is not divisible by scale {scale}")
    blocks = image.reshape(height // scale, scale, width // scale, scale, *image.shape[2:])  # (H, s, W, s[, C])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def cfa_sample(rgb: np.ndarray, cfa: str) -> np.ndarray:
    """([n,] H, W, 3) float in [0, 1] -> ([n,] H, W) float32 mosaic through ``cfa``.

    Each pixel keeps the colour its filter passes (:func:`stages.reconstruction.cfa.colour_index`);
    ``mono`` gives Rec.601 luma ``0.299 R + 0.587 G + 0.114 B``.
    """
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim not in (3, 4) or rgb.shape[-1] != 3:
        raise InputError(f"expected an (H, W, 3) or (n, H, W, 3) RGB array, got shape {rgb.shape}")
    height, width = rgb.shape[-3:-1]
    cfa = check_cfa(cfa, height, width)
    if cfa == "mono":
        red, green, blue = (np.float32(weight) * rgb[..., c] for c, weight in enumerate(LUMA))
        return red + green + blue
    index = np.broadcast_to(colour_index(cfa, height, width)[..., None], (*rgb.shape[:-1], 1))  # ([n,] H, W, 1)
    return np.take_along_axis(rgb, index.astype(np.intp), axis=-1)[..., 0]


@dataclass(frozen=True)
class SensorModel:
    """Parameters of the simulated sensor (see the module docstring for the noise model)."""

    brightness: float = 0.6  # α: threshold fractions gained per frame at intensity 1 (times θ)
    threshold: float = 1.0  # θ
    reset: str = "zero"
    noise: str = "none"
    seed: int = 0
    electrons_per_threshold: float = 1000.0  # shot noise: photo-electrons that fill one θ
    threshold_mismatch: float = 0.02  # relative std of θ across pixels (fixed pattern)
    dark_rate: float = 2e-4  # mean dark increment per frame, in θ (lognormal across pixels)

    def __post_init__(self):
        checks = (("brightness α", self.brightness, False), ("threshold θ", self.threshold, False),
                  ("electrons_per_threshold", self.electrons_per_threshold, False),
                  ("threshold_mismatch", self.threshold_mismatch, True), ("dark_rate", self.dark_rate, True))
        for label, value, zero_ok in checks:
            if not (value >= 0 if zero_ok else value > 0) or not np.isfinite(value):
                raise InputError(f"{label} must be {'>= 0' if zero_ok else '> 0'}, got {value!r}")
        check_reset(self.reset)
        if self.noise not in NOISES:
            raise InputError(f"unknown noise {self.noise!r}: expected one of {', '.join(NOISES)}")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise InputError(f"seed must be an integer >= 0, got {self.seed!r}")

    @property
    def gain(self) -> float:
        """θ/α: multiplies a firing rate back into an intensity (what the store records)."""
        return self.threshold / self.brightness


def initial_state(model: SensorModel, height: int, width: int) -> np.ndarray:
    """(H, W) int64 accumulator at frame 0, uniform in [0, UNITS) (random phases)."""
    rng = np.random.default_rng([model.seed, _STATE_STREAM])
    return rng.integers(0, UNITS, (height, width), dtype=np.int64)


def pixel_thresholds(model: SensorModel, height: int, width: int) -> np.ndarray | None:
    """(H, W) int64 per-pixel thresholds in units for realistic noise; None means UNITS everywhere."""
    if model.noise == "none":
        return None
    z = np.random.default_rng([model.seed, _THRESHOLD_STREAM]).standard_normal((height, width))
    return np.maximum(np.rint(UNITS * (1 + model.threshold_mismatch * z)), UNITS // 2).astype(np.int64)


def dark_increments(model: SensorModel, height: int, width: int) -> np.ndarray | None:
    """(H, W) float32 dark increment per frame in θ (lognormal, mean dark_rate); None without noise."""
    if model.noise == "none":
        return None
    z = np.random.default_rng([model.seed, _DARK_STREAM]).standard_normal((height, width))
    return (model.dark_rate * np.exp(DARK_SPREAD * z - DARK_SPREAD**2 / 2)).astype(np.float32)


def shot_normals(model: SensorModel, frame: int, out: np.ndarray) -> np.ndarray:
    """Fill ``out`` (H, W) float32 with frame ``frame``'s standard normals of the shot noise (keyed by frame)."""
    return np.random.default_rng([model.seed, _SHOT_STREAM, frame]).standard_normal(dtype=np.float32, out=out)


def increments(model: SensorModel, mosaic: np.ndarray, first_frame: int, *,
               dark: np.ndarray | None = None) -> np.ndarray:
    """(n, H, W) intensities in [0, 1] of frames first_frame.. -> (n, H, W) int32 increments in units.

    ``round(clip(α·I/θ, 0, 1) · UNITS)``; realistic noise adds dark current (``dark``, or
    :func:`dark_increments` when None) and shot noise drawn from
    ``default_rng([seed, 2, frame])`` over the full frame, then clips to [0, UNITS].
    """
    if int(first_frame) != first_frame or first_frame < 0:
        raise InputError(f"first_frame must be an integer >= 0, got {first_frame!r}")
    mosaic = np.asarray(mosaic, dtype=np.float32)
    if mosaic.ndim != 3:
        raise InputError(f"expected (n, H, W) intensities, got shape {mosaic.shape}")
    n, height, width = mosaic.shape
    scale = model.brightness / model.threshold * UNITS  # clip(α·I/θ, 0, 1)·UNITS = clip(I·scale, 0, UNITS)
    out = np.empty(mosaic.shape, np.int32)
    if model.noise == "none":
        _parallel(_signal_kernel, mosaic, scale, out)
        return out
    dark = dark_increments(model, height, width) if dark is None else np.asarray(dark, np.float32)
    if dark.shape != (height, width):
        raise InputError(f"dark increments of shape {dark.shape} do not match frames of {height}x{width}")
    dark_units = dark.astype(np.float64) * UNITS  # (H, W)
    z = np.empty((height, width), np.float32)
    for t in range(n):
        shot_normals(model, int(first_frame) + t, out=z)
        _parallel(_noisy_kernel, mosaic[t], z, dark_units, scale, UNITS / model.electrons_per_threshold, out[t])
    return out


@dataclass(frozen=True)
class Fired:
    """What one call of :func:`fire` produced."""

    packed: np.ndarray  # (n, H, ceil(W/8)) uint8, packed along x LSB first (stages.capture.bits.pack_rows)
    state: np.ndarray  # (H, W) int64 accumulator after the last frame
    spikes: int  # spikes in this call


def fire(increments: np.ndarray, state: np.ndarray, *, reset: str,
         thresholds: np.ndarray | None = None) -> Fired:
    """Integrate and fire n frames: ``acc += q``; at ``acc >= thr`` a spike, then reset.

    ``increments`` (n, H, W) in [0, UNITS] as :func:`increments` makes them (not checked:
    a full pass would cost ~20 %); ``state`` (H, W) in [0, 2^30), not modified: the new one
    is returned; ``thresholds`` (H, W) in [1, 2^30), None means UNITS everywhere.
    ``subtract`` keeps ``acc - thr`` (capped below thr), ``zero`` sets 0.
    """
    check_reset(reset)
    q = np.ascontiguousarray(increments, dtype=np.int32)
    if q.ndim != 3:
        raise InputError(f"expected (n, H, W) increments, got shape {q.shape}")
    n, height, width = q.shape
    new_state = np.array(state, dtype=np.int64, order="C")  # a copy: the kernel updates it
    if new_state.shape != (height, width):
        raise InputError(f"state of shape {new_state.shape} does not match frames of {height}x{width}")
    if thresholds is None:
        thresholds = np.full((1, width), UNITS, np.int64)  # one row shared by every row
    else:
        thresholds = np.ascontiguousarray(thresholds, dtype=np.int64)
        if thresholds.shape != (height, width):
            raise InputError(f"thresholds of shape {thresholds.shape} do not match frames of {height}x{width}")
    for label, values, low in (("state", new_state, 0), ("thresholds", thresholds, 1)):
        if values.size and not (values.min() >= low and values.max() < _MAX_UNITS):
            raise InputError(f"{label} must lie in [{low}, 2^30) units, got [{values.min()}, {values.max()}]")
    packed = np.empty((n, height, packed_width(width)), np.uint8)
    _parallel(_fire_kernel, q, new_state, thresholds, reset == "subtract", packed)
    return Fired(packed=packed, state=new_state, spikes=count_spikes(packed))


# --- kernels ------------------------------------------------------------------------------
# Every pixel is computed on its own, so results do not depend on the number of threads.

_ROW_BLOCK = 16  # rows per parallel task in _fire_kernel
_GATHER_BITS = np.uint64(0x0102040810204080)  # (word * this) >> 56: bit 0 of bytes 0..7 -> bits 0..7
if sys.byteorder != "little":  # the word tricks above read byte 0 as the least significant
    raise ImportError("stages.simulation.sensor's fire kernel needs a little-endian machine")
_lock = threading.Lock()
_threadsafe = False  # the workqueue layer aborts on concurrent calls (e.g. Dask threads): serialise it


def _parallel(kernel, *args):
    global _threadsafe
    if _threadsafe:
        return kernel(*args)
    with _lock:
        result = kernel(*args)
        _threadsafe = numba.threading_layer() != "workqueue"
    return result


@numba.njit(inline="always")
def _signal_units(intensity, scale):
    """clip(I·scale, 0, UNITS) as float64 (NaN -> 0)."""
    value = np.float64(intensity) * scale
    value = value if value > 0 else 0.0
    return value if value < UNITS else float(UNITS)


@numba.njit(parallel=True, cache=True)
def _signal_kernel(mosaic, scale, out):  # (n, H, W) float32 -> (n, H, W) int32
    n, height, width = mosaic.shape
    for row in numba.prange(n * height):
        src, dst = mosaic[row // height, row % height], out[row // height, row % height]  # (W,) each
        for x in range(width):
            dst[x] = np.int32(np.rint(_signal_units(src[x], scale)))


@numba.njit(parallel=True, cache=True)
def _noisy_kernel(frame, z, dark_units, scale, units_per_electron, out):  # (H, W) each
    for y in numba.prange(frame.shape[0]):
        src, noise, dark, dst = frame[y], z[y], dark_units[y], out[y]  # (W,) each
        for x in range(src.size):
            mean = _signal_units(src[x], scale) + dark[x]
            value = np.rint(mean + np.sqrt(mean * units_per_electron) * np.float64(noise[x]))
            value = value if value > 0 else 0.0
            dst[x] = np.int32(value if value < UNITS else float(UNITS))


@numba.njit(parallel=True, cache=True)
def _fire_kernel(q, state, thresholds, subtract, packed):
    """q (n, H, W) int32; state (H, W) int64 updated in place; thresholds (H or 1, W) int64.

    Each task takes a block of rows through all frames: its accumulators stay in L2 while q
    streams by in contiguous runs of _ROW_BLOCK rows. Arithmetic is int32 (8 lanes per AVX2
    op instead of 4; fire() checks state, thr < 2^30), and each frame's row of 0/1 bytes
    becomes packed bytes with one multiply per 8 pixels.
    """
    n, height, width = q.shape
    threshold_row_step = 0 if thresholds.shape[0] == 1 else 1  # 0: one row shared by every row
    for block in numba.prange((height + _ROW_BLOCK - 1) // _ROW_BLOCK):
        first = block * _ROW_BLOCK
        rows = min(_ROW_BLOCK, height - first)
        acc = state[first:first + rows].astype(np.int32)  # (rows, W)
        thr = np.empty((rows, width), np.int32)
        for r in range(rows):
            thr[r] = thresholds[np.int64(first + r) * threshold_row_step]
        cap = thr - np.int32(1)  # a remainder stays below the threshold
        fired = np.zeros(packed.shape[2] * 8, np.uint8)  # one row of one frame, 0/1, zero padded
        fired_words = fired.view(np.uint64)  # 8 pixels per word, pixel x in byte x % 8
        for t in range(n):
            for r in range(rows):
                q_row, acc_row, thr_row, cap_row = q[t, first + r], acc[r], thr[r], cap[r]
                if subtract:
                    for x in range(width):
                        a = np.int32(acc_row[x] + q_row[x])  # np.int32(): keep numba from widening to int64
                        s = a >= thr_row[x]
                        acc_row[x] = min(np.int32(a - thr_row[x]), cap_row[x]) if s else a
                        fired[x] = s
                else:
                    for x in range(width):
                        a = np.int32(acc_row[x] + q_row[x])
                        s = a >= thr_row[x]
                        acc_row[x] = a if a < thr_row[x] else np.int32(0)
                        fired[x] = s
                out = packed[t, first + r]
                for b in range(out.size):
                    out[b] = np.uint8((fired_words[b] * _GATHER_BITS) >> np.uint64(56))  # byte i's bit 0 -> bit i
        for r in range(rows):
            state[first + r] = acc[r]
