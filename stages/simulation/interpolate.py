"""Frames between two video frames: linear blending, or optical flow with occlusion-aware blending.

A video gives far fewer frames than the 20,000 per second a spike camera sees, so latent frames
in between are interpolated. ``linear`` cross-fades (ghosts on motion); ``flow`` estimates
bidirectional flow with OpenCV DIS, approximates the flows from the in-between time to both
frames as Super SloMo does, sharpens them at motion boundaries with two fixed-point steps of
linear motion (F_w0(x) = -w F01(x + F_w0(x))), backward-warps both frames there and blends
them, down-weighting pixels that a forward-backward check marks as occluded in the other frame. Flow vectors follow
:func:`stages.simulation.camera_path.CameraPath.flow`: frame0(x) ~ frame1(x + flow01(x)).

What does not depend on the in-between time (both flows and both forward-backward checks) is a
:class:`PairMotion`, made once per pair of frames and shared by every frame between them: a
video's pair lies under hundreds of spike frames, and the check is most of one interpolation.
"""

from dataclasses import dataclass

import numpy as np

from stages.errors import InputError
from stages.simulation.camera_path import backward_warp, check_image

INTERPOLATIONS = ("flow", "linear")

_PROJECTION_STEPS = 2
_VISIBILITY_FLOOR = 0.05  # where both frames look occluded, fall back to time-weighted blending


def _check_pair(frame0: np.ndarray, frame1: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
    frame0, frame1 = check_image(frame0, "frame0"), check_image(frame1, "frame1")
    if frame0.shape != frame1.shape:
        raise InputError(f"frames differ in shape: {frame0.shape} and {frame1.shape}")
    _check_weight(w)
    return frame0, frame1


def _check_weight(w: float) -> None:
    if not 0 <= w <= 1:
        raise InputError(f"w must be in [0, 1], got {w}")


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


@dataclass(frozen=True)
class PairMotion:
    """The motion between two frames, shared by every frame interpolated between them."""

    flow01: np.ndarray  # (H, W, 2) float32: frame0(x) ~ frame1(x + flow01(x))
    flow10: np.ndarray  # (H, W, 2) float32: frame1(x) ~ frame0(x + flow10(x))
    kept01: np.ndarray  # (H, W) float32 in (0, 1]: frame0's pixel x is visible in frame1 (not occluded)
    kept10: np.ndarray  # (H, W) float32 in (0, 1]: frame1's pixel x is visible in frame0


def pair_motion(flow01: np.ndarray, flow10: np.ndarray) -> PairMotion:
    """The pair's motion from its two flows (each (H, W, 2)): the flows and both forward-backward checks."""
    flow01, flow10 = np.asarray(flow01, np.float32), np.asarray(flow10, np.float32)
    if flow01.ndim != 3 or flow01.shape[2] != 2 or flow10.shape != flow01.shape:
        raise InputError(f"flows must both be (H, W, 2), got {flow01.shape} and {flow10.shape}")
    return PairMotion(flow01, flow10, _consistency(flow01, flow10), _consistency(flow10, flow01))


def estimate_motion(frame0: np.ndarray, frame1: np.ndarray) -> PairMotion:
    """:func:`estimate_flows` and the forward-backward checks: all that :func:`interpolate` needs
    besides the frames and the time."""
    return pair_motion(*estimate_flows(frame0, frame1))


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
    """:func:`interpolate` for one frame between frame0 and frame1 given their two flows."""
    return interpolate(frame0, frame1, pair_motion(flow01, flow10), w)


def interpolate(frame0: np.ndarray, frame1: np.ndarray, motion: PairMotion, w: float) -> np.ndarray:
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
    _check_motion(motion, frame0.shape[:2])
    if w == 0 or w == 1:
        return (frame1 if w == 1 else frame0).copy()
    flow_w0, flow_w1 = _time_flows(motion, w)  # (H, W, 2) each
    warped0, warped1 = backward_warp(frame0, flow_w0), backward_warp(frame1, flow_w1)  # frames' shape
    weight0, weight1 = _blend_weights(motion, flow_w0, flow_w1, w)  # (H, W) each
    if frame0.ndim == 3:
        weight0, weight1 = weight0[:, :, None], weight1[:, :, None]
    return _blend(weight0, warped0, weight1, warped1)


def interpolate_mosaic(planes0: np.ndarray, planes1: np.ndarray, motion: PairMotion, w: float,
                       cell: np.ndarray) -> np.ndarray:
    """(H, W) float32: of :func:`interpolate`'s frame, only the channel each pixel keeps, as behind a
    Bayer filter: ``cell[y % 2, x % 2]``. Bit-identical to picking those channels from the whole
    frame (each output pixel is computed alone, by the same operations), at half the cost.

    ``planes0``, ``planes1``: the frames as (C, H, W) float32 planes (``np.moveaxis(frame, 2, 0)``,
    made once per pair by the caller); ``cell``: (2, 2) channel indices.
    """
    planes0, planes1 = np.asarray(planes0, np.float32), np.asarray(planes1, np.float32)
    if planes0.ndim != 3 or planes1.shape != planes0.shape or planes0.shape[1] % 2 or planes0.shape[2] % 2:
        raise InputError(f"expected two (C, H, W) planes of even H and W, got {planes0.shape} and {planes1.shape}")
    height, width = planes0.shape[1:]
    _check_motion(motion, (height, width))
    _check_weight(w)
    mosaic = np.empty((height, width), np.float32)
    if w == 0 or w == 1:
        for (dy, dx), channel in np.ndenumerate(cell):
            mosaic[dy::2, dx::2] = (planes1 if w == 1 else planes0)[channel, dy::2, dx::2]
        return mosaic
    flow_w0, flow_w1 = _time_flows(motion, w)
    weight0, weight1 = _blend_weights(motion, flow_w0, flow_w1, w)
    for (dy, dx), channel in np.ndenumerate(cell):  # backward_warp(frame, flow)[dy::2, dx::2, channel]
        warped0 = backward_warp(planes0[channel], flow_w0, phase=(dy, dx))
        warped1 = backward_warp(planes1[channel], flow_w1, phase=(dy, dx))
        mosaic[dy::2, dx::2] = _blend(weight0[dy::2, dx::2], warped0, weight1[dy::2, dx::2], warped1)
    return mosaic


def _check_motion(motion: PairMotion, size: tuple[int, int]) -> None:
    if motion.flow01.shape != (*size, 2):
        raise InputError(f"flows must be (H, W, 2) for frames of {size[0]}x{size[1]}, got {motion.flow01.shape}")


def _time_flows(motion: PairMotion, w: float) -> tuple[np.ndarray, np.ndarray]:
    """(F_w0, F_w1), each (H, W, 2): where each frame's pixel seen at x at time w comes from."""
    flow01, flow10 = motion.flow01, motion.flow10
    flow_w0 = np.float32(-(1 - w) * w) * flow01 + np.float32(w * w) * flow10
    flow_w1 = np.float32((1 - w) ** 2) * flow01 - np.float32(w * (1 - w)) * flow10
    for _ in range(_PROJECTION_STEPS):  # in place on fresh arrays: at HR each temporary is 128 MB of page faults
        flow_w0 = backward_warp(flow01, flow_w0)
        flow_w0 *= np.float32(-w)
        flow_w1 = backward_warp(flow10, flow_w1)
        flow_w1 *= np.float32(w - 1)
    return flow_w0, flow_w1


def _blend_weights(motion: PairMotion, flow_w0: np.ndarray, flow_w1: np.ndarray,
                   w: float) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's (H, W) weight at time w: its share of time, times its visibility."""
    # Frame 0 can show what is at x at time w if that content is visible in frame 1 too, and vice versa.
    visible0 = backward_warp(motion.kept10, flow_w1)  # (H, W)
    visible1 = backward_warp(motion.kept01, flow_w0)
    weight0 = np.float32(1 - w) * (_VISIBILITY_FLOOR + (1 - _VISIBILITY_FLOOR) * visible0)
    weight1 = np.float32(w) * (_VISIBILITY_FLOOR + (1 - _VISIBILITY_FLOOR) * visible1)
    return weight0, weight1


def _blend(weight0: np.ndarray, warped0: np.ndarray, weight1: np.ndarray, warped1: np.ndarray) -> np.ndarray:
    """clip((weight0 warped0 + weight1 warped1) / (weight0 + weight1), 0, 1) in float32, computed in
    place in the (fresh, float32) warped arrays: the same operations on each element, fewer temporaries."""
    np.multiply(warped0, weight0, out=warped0)
    np.multiply(warped1, weight1, out=warped1)
    warped0 += warped1
    warped0 /= weight0 + weight1
    return np.clip(warped0, 0, 1, out=warped0)
