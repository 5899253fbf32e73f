"""Latent intensity frames, one per spike frame (Algorithm 2, step 1), and their LR mosaics.

Two kinds of scene: a *video*, whose source frames are spread evenly over the spike frames
and interpolated (linear or flow-based), and a *still* image moved along a camera path, whose
latent frames are exact warps (so the true flow is known).

Spike input is built at low resolution. For a video, source frames are area-downsampled
first and interpolated at LR: exact for linear interpolation (both are linear), and for
flow interpolation it estimates flow at LR, 1/s^2 of the work. For a still, every latent
frame is rendered at HR and then area-downsampled, exactly as Algorithm 2 orders it.
Ground truth is always rendered at HR.
"""

import numpy as np

from stages.simulation.intensities import luma_rgb, to_uint8
from stages.reconstruction.cfa import colour_index
from stages.simulation.interpolate import PairMotion, interpolate, interpolate_mosaic, linear, pair_motion
from stages.simulation.camera_path import CameraPath, render
from stages.simulation.sensor import area_downsample, cfa_sample


def source_position(frame: int, n_spike_frames: int, n_source_frames: int) -> float:
    """Where spike frame ``frame`` falls between source frames (0 .. n_source_frames - 1)."""
    return frame * (n_source_frames - 1) / max(n_spike_frames - 1, 1)


def bracket(position: float, n_source_frames: int) -> tuple[int, float]:
    """(i, w): the position lies a fraction w of the way from source frame i to i + 1."""
    i = min(int(np.floor(position)), n_source_frames - 2)
    return i, float(position - i)


def between(frame0: np.ndarray, frame1: np.ndarray, w: float, motion: PairMotion | None) -> np.ndarray:
    """The frame a fraction ``w`` from frame0 to frame1; flow-based when the pair's motion is given."""
    if w == 0:
        return frame0
    if w == 1:
        return frame1
    return linear(frame0, frame1, w) if motion is None else interpolate(frame0, frame1, motion, w)


def upscale_flow(flow: np.ndarray, scale: int) -> np.ndarray:
    """(H, W, 2) flow at LR -> (s*H, s*W, 2) at HR, in HR pixels."""
    import cv2

    height, width = flow.shape[:2]
    return cv2.resize(flow, (width * scale, height * scale), interpolation=cv2.INTER_LINEAR) * np.float32(scale)


def upscale_motion(motion: PairMotion, scale: int) -> PairMotion:
    """A pair's motion estimated at LR, for its HR frames: the flows upscaled, the checks made at HR."""
    return pair_motion(upscale_flow(motion.flow01, scale), upscale_flow(motion.flow10, scale))


def video_mosaics(pairs: dict[int, tuple], positions: list[float], n_source_frames: int, cfa: str) -> np.ndarray:
    """LR mosaics (n, H, W) float32 at source ``positions``.

    ``pairs[i]`` is ``(lr_frame_i, lr_frame_i+1, motion_or_None)`` for every bracket needed.
    Behind a Bayer filter, flow interpolation computes only the channel each pixel keeps
    (:func:`stages.simulation.interpolate.interpolate_mosaic`: the same bytes, half the work).
    """
    planes = {}  # pair i -> both frames as (3, H, W) planes, made once per pair
    cell = colour_index(cfa, 2, 2) if cfa != "mono" else None  # (2, 2) channel kept at each Bayer phase

    def mosaic(position: float) -> np.ndarray:
        i, w = bracket(position, n_source_frames)
        frame0, frame1, motion = pairs[i]
        if motion is None or cfa == "mono":
            return cfa_sample(between(frame0, frame1, w, motion), cfa)
        if i not in planes:
            planes[i] = tuple(np.ascontiguousarray(np.moveaxis(frame, 2, 0), np.float32) for frame in (frame0, frame1))
        return interpolate_mosaic(*planes[i], motion, w, cell)

    return np.stack([mosaic(position) for position in positions])


def still_mosaics(image: np.ndarray, path: CameraPath, times: list[int], scale: int, cfa: str) -> np.ndarray:
    """LR mosaics (n, H, W) float32 of an HR still moved along ``path``."""
    return np.stack([cfa_sample(area_downsample(render(image, path, t), scale), cfa) for t in times])


def truth_image(rgb: np.ndarray, cfa: str) -> np.ndarray:
    """HR float RGB -> uint8 ground truth; a mono sensor's truth is the luma it sees."""
    return to_uint8(luma_rgb(rgb) if cfa == "mono" else rgb)
