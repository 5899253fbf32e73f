"""Source frames -> intensities: whatever a file holds (uint8/uint16/float, grey/RGB/RGBA) to
float32 RGB in [0, 1], and back to uint8 for ground truth.

Intensities are the stored pixel values taken as linear light (no gamma decoding), as the
spike-camera simulators of the literature do.
"""

import numpy as np

from stages.errors import InputError

LUMA = (0.299, 0.587, 0.114)  # Rec.601 weights of R, G, B: what a mono sensor sees


def to_unit_rgb(frame: np.ndarray) -> np.ndarray:
    """(H, W), (H, W, 1|3|4) -> (H, W, 3) float32 in [0, 1]."""
    frame = np.asarray(frame)
    if frame.ndim == 2:
        frame = frame[:, :, None]
    if frame.ndim != 3 or frame.shape[2] not in (1, 3, 4):
        raise InputError(f"a frame must be grey, RGB or RGBA, got shape {frame.shape}")
    frame = np.repeat(frame, 3, axis=2) if frame.shape[2] == 1 else frame[:, :, :3]
    if np.issubdtype(frame.dtype, np.integer):
        return frame.astype(np.float32) / np.float32(np.iinfo(frame.dtype).max)
    return np.clip(frame, 0, 1).astype(np.float32)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8, rounded."""
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)


def luma_rgb(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) RGB -> the Rec.601 luma repeated in three channels (what a mono sensor sees)."""
    luma = rgb @ np.array(LUMA, np.float32)
    return np.repeat(luma[..., None], 3, axis=-1)
