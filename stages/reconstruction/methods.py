"""The reconstructor interface: a window of packed spikes (a tile with its halo) -> HR RGB.

Every method, classic or learned, is a :class:`Reconstructor`: it declares how many LR
pixels of context (``halo``) it needs around a tile for the tile's interior to come out
exactly as in a whole-frame reconstruction, and maps a window to an HR tile. The pipeline
cuts tiles, adds halos, crops them off and never needs to know which method ran.
"""

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from stages.reconstruction.colour import check_scale, rate_to_rgb
from stages.errors import InputError
from stages.reconstruction.tfi import tfi_rate
from stages.reconstruction.tfp import tfp_rate

WINDOW = 41  # spike frames per output frame (CSCSR's input, N = 41); also the default step between outputs


def output_centres(n_frames: int, window: int, every: int) -> list[int]:
    """Centre spike frames of the output (and of the simulator's ground truth): W//2, W//2 + K, ...
    while the window fits."""
    half = window // 2
    return list(range(half, n_frames - half, every))


def middle_centre(n_frames: int, window: int) -> int:
    """The centre spike frame of the recording's middle window (of ``window`` frames, ``n_frames >= window``): where
    the automatic exposure is measured, whatever the output frames (``every``, a part)."""
    half = window // 2
    return min(max(n_frames // 2, half), n_frames - 1 - half)


@dataclass(frozen=True)
class Window:
    """One reconstruction input: packed spikes of a (tile of a) window, and how to read them."""

    packed: np.ndarray  # (N, h, ceil(w/8)) uint8, the centre frame is N // 2
    width: int  # w: real pixels per row of the tile
    cfa: str  # pattern as seen at the tile's top-left corner (tiles start on even rows/columns)
    reset: str
    gain: float
    scale: int


class Reconstructor(Protocol):
    name: str
    halo: int  # LR pixels of context needed on every side (even: keeps the Bayer phase)
    batch: int  # windows of one tile worth reconstructing together
    weights: str | None  # the weights file a network was loaded from (recorded in its output); None: classic
    weights_sha256: str | None  # that file's SHA-256 (recorded too, and checked by --resume); None: classic

    def __call__(self, window: Window) -> np.ndarray:
        """-> (s*h, s*w, 3) uint8 RGB."""

    def many(self, windows: list[Window]) -> list[np.ndarray]:
        """Windows of the same tile geometry -> one image each, as ``__call__`` would give."""

    def many_tiles(self, tiles: list[list[Window]], most: int | None = None) -> list[list[np.ndarray]]:
        """The windows of several tiles (each tile's as ``many`` takes them) -> each tile's images; a
        reconstructor may run tiles of the same shape together, at most ``most`` windows at a time."""

    def check(self, window: int, scale: int, cfa: str) -> None:
        """Refuse, before any work, a window length, scale or CFA the method cannot serve."""


@dataclass(frozen=True)
class RateReconstructor:
    """A classic method: a per-pixel rate estimate, then exposure, demosaicking (VNG), bicubic x s.

    The halo covers VNG's 5x5 neighbourhood and bicubic's 4x4 support with margin, so tiled
    output equals whole-frame output exactly.
    """

    name: str
    estimate: callable
    halo: int = 8
    batch: int = 1
    weights: None = None
    weights_sha256: None = None

    def __call__(self, window: Window) -> np.ndarray:
        rate = self.estimate(window.packed, window.width, window.reset)
        return rate_to_rgb(rate, window.cfa, window.gain, window.scale)

    def many(self, windows: list[Window]) -> list[np.ndarray]:
        return [self(window) for window in windows]

    def many_tiles(self, tiles: list[list[Window]], most: int | None = None) -> list[list[np.ndarray]]:
        return [self.many(windows) for windows in tiles]

    def check(self, window: int, scale: int, cfa: str) -> None:
        """Any window and CFA will do; the scale must be one the upsampling makes."""
        check_scale("scale", scale)


CLASSIC = {"tfp": RateReconstructor("tfp", tfp_rate), "tfi": RateReconstructor("tfi", tfi_rate)}
NETWORKS = ("cscsr", "cscsr-ensemble")  # the network; the same averaged over the 8 flips and quarter turns
METHODS = ("tfp", "tfi", *NETWORKS)


def classic(method: str) -> Reconstructor:
    """The classic reconstructor called ``method``; an error naming the known ones otherwise."""
    if method in NETWORKS:
        raise InputError(f"{method} is a network, not a classic method: load it with cscsr.inference.reconstructor")
    if method not in CLASSIC:
        raise InputError(f"unknown method {method!r}: expected one of {', '.join(METHODS)}")
    return CLASSIC[method]
