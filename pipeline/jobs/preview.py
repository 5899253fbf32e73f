"""One reconstructed picture from one window of a spike store (TFP), for a quick look."""

from dataclasses import dataclass

import numpy as np

from pipeline.stores.spike_store import open_spike_store
from stages.reconstruction.colour import check_gain, check_scale
from stages.errors import InputError
from stages.reconstruction.methods import WINDOW
from stages.reconstruction.tfp import tfp_image


@dataclass(frozen=True)
class Preview:
    image: np.ndarray
    centre: int
    window: int
    gain: float


def preview(url: str, *, centre: int | None = None, window: int = WINDOW, gain: float | None = None, scale: int = 1) -> Preview:
    """TFP image of frames ``[centre - window//2, centre + window//2]``; gain: given, store's, or auto."""
    if gain is not None:  # inf passes "> 0" and would write a picture of NaN
        check_gain("--gain", gain)
    check_scale("--scale", scale)
    store = open_spike_store(url)
    n = store.n_frames
    if window <= 0 or window % 2 == 0:
        raise InputError(f"window must be a positive odd number of frames, got {window}")
    if window > n:
        raise InputError(f"window of {window} frames is longer than the recording ({n} frames)")
    half = window // 2
    centre = n // 2 if centre is None else centre
    if not half <= centre < n - half:
        raise InputError(f"centre frame {centre} needs frames {centre - half}..{centre + half}; the recording has 0..{n - 1}")
    gain = gain if gain is not None else store.meta.gain
    image, used = tfp_image(store.read(centre - half, centre + half + 1), width=store.meta.width,
                            cfa=store.meta.cfa, gain=gain, scale=scale, reset=store.meta.reset)
    return Preview(image, centre, window, used)
