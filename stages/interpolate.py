"""Frames between two video frames: linear blending, or optical flow with occlusion-aware blending.

A video gives far fewer frames than the 20,000 per second a spike camera sees, so latent frames
in between are interpolated. ``linear`` cross-fades (ghosts on motion); ``flow`` estimates
bidirectional flow with OpenCV DIS, approximates the flows from the in-between time to both
frames as Super SloMo does, sharpens them at motion boundaries with two fixed-point steps of
linear motion (F_w0(x) = -w F01(x + F_w0(x))), backward-warps both frames there and blends
them, down-weighting pixels that a forward-backward check marks as occluded in the other frame. Flow vectors follow
:func:`stages.camera_path.CameraPath.flow`: frame0(x) ~ frame1(x + flow01(x)).
"""

import numpy as np

from stages.errors import InputError
from stages.camera_path import backward_warp, check_image

INTERPOLATIONS = ("flow", "linear")

_PROJECTION_STEPS = 2
_VISIBILITY_FLOOR = 0.05  # where both frames look occluded, fall back to time-weighted blending


def _check_pair(frame0: np.ndarray, frame1: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
    frame0, frame1 = check_image(frame0, "frame0"), check_image(frame1, "frame1")
    if frame0.shape != frame1.shape:
        raise InputError(f"frames differ in shape: {frame0.shape} and {frame1.shape}")
    if not 0 <= w <= 1:
        raise InputError(f"w must be in [0, 1], got {w}")
    return frame0, frame1


def linear(frame0: np.ndarray, frame1: np.ndarray, w: float) -> np.ndarray:
    """(1 - w) frame0 + w frame1, float32 of the frames' shape."""
    frame0, frame1 = _check_pair(frame0, frame1, w)
    return np.float32(1 - w) * frame0 + np.float32(w) * frame1


def _grey_uint8(frame: np.ndarray) -> np.ndarray:
    """(H, W[, C]) float in [0, 1] -> (H, W) uint8 (RGB weighted as luma, other counts averaged)."""
    import cv2

    if frame.ndim == 3 and frame.shape[2] == 3:
        frame = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
    elif frame.ndim == 3:
        frame = frame.mean(axis=2)
    return np.round(np.clip(frame, 0, 1) * 255).astype(np.uint8)


def estimate_flows(frame0: np.ndarray, frame1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bidirectional optical flow (flow01, flow10), each (H, W, 2) float32, by OpenCV DIS
    (PRESET_MEDIUM) on 8-bit grey: frame0(x) ~ frame1(x + flow01(x)) and vice versa."""
    import cv2

    frame0, frame1 = _check_pair(frame0, frame1, 0)
    grey0, grey1 = _grey_uint8(frame0), _grey_uint8(frame1)  # (H, W) uint8
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(grey0, grey1, None), dis.calc(grey1, grey0, None)


def _consistency(flow_ab: np.ndarray, flow_ba: np.ndarray) -> np.ndarray:
    """(H, W) in (0, 1]: ~1 where following a->b and back returns home (the pixel of frame a is
    visible in frame b), ~0 where it does not (occluded). Soft version of Sundaram et al.'s test
    |F_ab + F_ba(x + F_ab)|^2 < 0.01 (|F_ab|^2 + |F_ba(x + F_ab)|^2) + 0.5."""
    back = backward_warp(flow_ba, flow_ab)  # (H, W, 2) F_ba at x + F_ab(x)
    error = np.sum((flow_ab + back) ** 2, axis=2)
    tolerance = 0.01 * (np.sum(flow_ab**2, axis=2) + np.sum(back**2, axis=2)) + 0.5
    return np.exp(-error / tolerance)


def flow_interpolate(frame0: np.ndarray, frame1: np.ndarray, flow01: np.ndarray, flow10: np.ndarray,
                     w: float) -> np.ndarray:
    """The frame at fraction ``w`` between frame0 and frame1, float32 in [0, 1].

    Both frames are backward-warped to time w with Super SloMo's intermediate flows
    F_w0 = -(1-w) w F01 + w^2 F10 and F_w1 = (1-w)^2 F01 - w (1-w) F10, refined by the
    fixed-point steps F_w0 <- -w F01(x + F_w0), F_w1 <- -(1-w) F10(x + F_w1) (the pixel of
    each frame that linear motion brings to x; Super SloMo's guess mixes foreground and
    background flow near motion boundaries, these steps pick one), then blended with
    weights (1-w) V0 and w V1, V being each frame's visibility at time w from the
    forward-backward check. w = 0 or 1 returns frame0 / frame1 exactly.
    """
    frame0, frame1 = _check_pair(frame0, frame1, w)
    flow01, flow10 = np.asarray(flow01, np.float32), np.asarray(flow10, np.float32)
    if flow01.shape != (*frame0.shape[:2], 2) or flow10.shape != flow01.shape:
        raise InputError(f"flows must be (H, W, 2) for {frame0.shape} frames, got {flow01.shape} and {flow10.shape}")
    if w == 0 or w == 1:
        return (frame1 if w == 1 else frame0).copy()
    flow_w0 = np.float32(-(1 - w) * w) * flow01 + np.float32(w * w) * flow10  # (H, W, 2)
    flow_w1 = np.float32((1 - w) ** 2) * flow01 - np.float32(w * (1 - w)) * flow10
    for _ in range(_PROJECTION_STEPS):
        flow_w0 = np.float32(-w) * backward_warp(flow01, flow_w0)
        flow_w1 = np.float32(w - 1) * backward_warp(flow10, flow_w1)
    warped0, warped1 = backward_warp(frame0, flow_w0), backward_warp(frame1, flow_w1)  # frames' shape
    # Frame 0 can show what is at x at time w if that content is visible in frame 1 too, and vice versa.
    visible0 = backward_warp(_consistency(flow10, flow01), flow_w1)  # (H, W)
    visible1 = backward_warp(_consistency(flow01, flow10), flow_w0)
    weight0 = np.float32(1 - w) * (_VISIBILITY_FLOOR + (1 - _VISIBILITY_FLOOR) * visible0)
    weight1 = np.float32(w) * (_VISIBILITY_FLOOR + (1 - _VISIBILITY_FLOOR) * visible1)
    if frame0.ndim == 3:
        weight0, weight1 = weight0[:, :, None], weight1[:, :, None]
    blend = (weight0 * warped0 + weight1 * warped1) / (weight0 + weight1)
    return np.clip(blend, 0, 1).astype(np.float32)
