"""Unpacked 0/1 spike arrays (the ``.npy``/``.npz`` exchange form) -> packed frames."""

import numpy as np

from stages.capture.bits import pack_rows
from stages.capture.sps100 import CaptureDamaged
from stages.errors import InputError


def check_spike_array_header(shape: tuple, dtype: np.dtype) -> None:
    """Reject arrays that cannot be spike frames, before any data is read."""
    if len(shape) != 3:
        raise InputError(f"spike array has rank {len(shape)} (shape {tuple(shape)}); expected (T, H, W)")
    if any(isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0 for n in shape):
        raise InputError(f"spike array header has a nonsense shape {tuple(shape)}")
    if not (np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.bool_) or np.issubdtype(dtype, np.floating)):
        raise InputError(f"spike array has dtype {dtype}; expected 0/1 integers, booleans or floats")
    if min(shape) == 0:
        raise InputError(f"spike array is empty (shape {tuple(shape)})")


def binary_to_packed(frames: np.ndarray, first_frame: int = 0) -> np.ndarray:
    """(n, H, W) array of 0/1 -> (n, H, ceil(W/8)) packed; :class:`CaptureDamaged` if any value is not 0 or 1 (the
    capture's own content, found as it is read: a resume would find it again, so the new store is removed)."""
    if frames.dtype != np.bool_:
        bad = (frames != 0) & (frames != 1)
        if bad.any():
            t, y, x = np.argwhere(bad)[0]
            raise CaptureDamaged(
                f"spike values must be 0 or 1: found {frames[t, y, x].item()!r} at frame {first_frame + t}, "
                f"row {y}, column {x}"
            )
    return pack_rows(frames.astype(np.uint8, copy=False))
