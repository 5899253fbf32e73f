"""Stages: camera paths with exact flow (camera_path) and frame interpolation (interpolate)."""

import pickle

import cv2
import numpy as np
import pytest

from stages.errors import InputError
from stages.reconstruction.cfa import BAYER_PATTERNS, colour_index
from stages.simulation.interpolate import estimate_flows, flow_interpolate, interpolate, interpolate_mosaic, linear, pair_motion
from stages.simulation.sensor import cfa_sample
from stages.simulation.camera_path import CameraPath, backward_warp, render

HEIGHT, WIDTH = 96, 128


def texture(height: int = HEIGHT, width: int = WIDTH, seed: int = 0, cell: int = 8) -> np.ndarray:
    """(H, W, 3) float32 smooth random colour texture in [0, 1] (bicubic-enlarged noise)."""
    noise = np.random.default_rng(seed).random((height // cell, width // cell, 3)).astype(np.float32)
    return np.clip(cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC), 0, 1)


def interior(image: np.ndarray, margin: int) -> np.ndarray:
    return image[margin:-margin, margin:-margin]


def test_a_pure_translation_has_constant_flow_equal_to_the_shift():
    path = CameraPath(HEIGHT, WIDTH, drift=(-1.5, 0.5))  # the source moves by (+1.5, -0.5) px per frame
    flow = path.flow(2, 6)
    assert flow.shape == (HEIGHT, WIDTH, 2) and flow.dtype == np.float32
    np.testing.assert_allclose(flow.reshape(-1, 2), np.tile([6.0, -2.0], (HEIGHT * WIDTH, 1)), atol=1e-5)
    image = texture()
    shifted = np.roll(image, (-1, 3), axis=(0, 1))  # content moved by (3, -1) px
    np.testing.assert_array_equal(interior(render(image, path, 2), 8), interior(shifted, 8))


def test_random_path_without_deformation_moves_rigidly():
    path = CameraPath.random(100, HEIGHT, WIDTH, seed=4, speed=0.5)
    flow = path.flow(10, 30).reshape(-1, 2).astype(np.float64)
    # A similarity transform: flow is affine in (x, y), so a least-squares affine fit is exact.
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].reshape(2, -1)
    design = np.stack([x, y, np.ones_like(x)], 1).astype(np.float64)
    fit = np.linalg.lstsq(design, flow, rcond=None)[0]
    assert np.abs(design @ fit - flow).max() < 1e-4
    assert np.abs(flow).max() > 1  # it did move


@pytest.mark.parametrize("deform", [0.0, 2.0])
@pytest.mark.parametrize("k", [5, 20])
def test_warping_a_later_frame_by_the_true_flow_gives_the_earlier_frame(deform, k):
    image = texture()
    path = CameraPath.random(200, HEIGHT, WIDTH, seed=7, speed=0.5, deform=deform)
    t = 31.5
    earlier, later, flow = render(image, path, t), render(image, path, t + k), path.flow(t, t + k)
    margin = int(np.ceil(np.abs(flow).max())) + 4  # beyond it the later frame shows reflected border
    assert margin < 20
    error = np.abs(interior(backward_warp(later, flow), margin) - interior(earlier, margin)).mean()
    error_without_motion = np.abs(interior(later, margin) - interior(earlier, margin)).mean()
    assert error < 0.01
    assert error_without_motion > 10 * error


def test_flow_composes_and_reverses():
    path = CameraPath.random(100, HEIGHT, WIDTH, seed=2, speed=1.0, deform=2.0)
    forward, backward = path.flow(3, 17), path.flow(17, 3)
    round_trip = forward + backward_warp(backward, forward)  # there and back again: zero
    margin = int(np.ceil(np.abs(forward).max())) + 2  # points that leave the frame do not come back
    assert np.abs(interior(round_trip, margin)).max() < 0.01


@pytest.mark.parametrize("phase", [(0, 0), (0, 1), (1, 0), (1, 1)])
def test_a_warp_at_one_bayer_phase_is_the_whole_warp_sampled_byte_for_byte(phase):
    flow = CameraPath.random(100, HEIGHT, WIDTH, seed=3, speed=2.0, deform=2.0).flow(4, 40)  # reaches the borders
    dy, dx = phase
    for image in (texture(), texture()[:, :, 1]):  # colour and one plane
        alone = backward_warp(image, flow, phase=phase)
        assert alone.shape == image[dy::2, dx::2].shape and alone.dtype == np.float32
        np.testing.assert_array_equal(alone, backward_warp(image, flow)[dy::2, dx::2])


def test_scaled_path_moves_the_same_at_a_quarter_size():
    path = CameraPath.random(100, HEIGHT, WIDTH, seed=3, speed=1.0, deform=2.0)
    small = path.scaled(0.25)
    assert (small.height, small.width) == (HEIGHT // 4, WIDTH // 4)
    flow = cv2.resize(path.flow(5, 40), (WIDTH // 4, HEIGHT // 4), interpolation=cv2.INTER_AREA) / 4
    assert np.abs(flow - small.flow(5, 40)).max() < 0.01
    with pytest.raises(InputError, match="whole pixels"):
        path.scaled(1 / 5)


def test_paths_and_frames_are_deterministic():
    image = texture()
    path = CameraPath.random(50, HEIGHT, WIDTH, seed=11, deform=1.5)
    again = CameraPath.random(50, HEIGHT, WIDTH, seed=11, deform=1.5)
    assert path == again and pickle.loads(pickle.dumps(path)) == path
    np.testing.assert_array_equal(render(image, path, 12.25), render(image, again, 12.25))
    np.testing.assert_array_equal(path.flow(1, 9), again.flow(1, 9))
    other = CameraPath.random(50, HEIGHT, WIDTH, seed=12, deform=1.5)
    assert other != path
    assert np.abs(render(image, other, 12.25) - render(image, path, 12.25)).mean() > 0.01


def test_render_keeps_shape_and_range():
    grey = texture()[:, :, 0] * 1.2 - 0.1  # some values outside [0, 1]
    frame = render(grey, CameraPath.random(10, HEIGHT, WIDTH, seed=0, speed=2.0), 4)
    assert frame.shape == grey.shape and frame.dtype == np.float32
    assert frame.min() >= 0 and frame.max() <= 1


def test_bad_motion_input():
    with pytest.raises(InputError, match="would fold"):
        CameraPath.random(10, HEIGHT, WIDTH, seed=0, deform=50)
    with pytest.raises(InputError, match="must be finite and >= 0"):
        CameraPath.random(10, HEIGHT, WIDTH, seed=0, speed=-1)
    with pytest.raises(InputError, match="but the path is"):
        render(texture(), CameraPath(HEIGHT, WIDTH + 2), 0)
    with pytest.raises(InputError, match="must be float"):
        render((texture() * 255).astype(np.uint8), CameraPath(HEIGHT, WIDTH), 0)
    with pytest.raises(InputError, match="flow must be"):
        backward_warp(texture(), np.zeros((HEIGHT, WIDTH, 3), np.float32))


def test_linear_interpolation_known_values():
    zeros, ones = np.zeros((4, 5, 3), np.float32), np.ones((4, 5, 3), np.float32)
    np.testing.assert_array_equal(linear(zeros, ones, 0.25), np.full((4, 5, 3), 0.25, np.float32))
    np.testing.assert_array_equal(linear(zeros + 0.2, ones, 0), zeros + 0.2)
    assert linear(zeros, ones, 0.5).dtype == np.float32
    with pytest.raises(InputError, match="differ in shape"):
        linear(zeros, ones[:, :4], 0.5)
    with pytest.raises(InputError, match="w must be in"):
        linear(zeros, ones, 1.5)


@pytest.fixture(scope="module")
def translating_pair():
    """Frames 0 and 1 of a texture moving by (3, 2) px per frame, and the truth at t = 0.5."""
    image = texture(seed=5)
    path = CameraPath(HEIGHT, WIDTH, drift=(-3, -2))
    return render(image, path, 0), render(image, path, 1), render(image, path, 0.5)


def test_estimate_flows_recovers_a_translation(translating_pair):
    frame0, frame1, _ = translating_pair
    flow01, flow10 = estimate_flows(frame0, frame1)
    assert flow01.shape == (HEIGHT, WIDTH, 2) and flow01.dtype == np.float32
    assert np.abs(interior(flow01, 12) - [3, 2]).max() < 0.5
    assert np.abs(interior(flow10, 12) + [3, 2]).max() < 0.5
    again = estimate_flows(frame0, frame1)
    np.testing.assert_array_equal(again[0], flow01)
    np.testing.assert_array_equal(again[1], flow10)


def test_flow_interpolation_beats_linear_blending(translating_pair):
    frame0, frame1, truth = translating_pair
    flow01, flow10 = estimate_flows(frame0, frame1)
    middle = flow_interpolate(frame0, frame1, flow01, flow10, 0.5)
    assert middle.shape == truth.shape and middle.dtype == np.float32
    flow_error = np.abs(interior(middle - truth, 12)).mean()
    linear_error = np.abs(interior(linear(frame0, frame1, 0.5) - truth, 12)).mean()
    assert flow_error < 0.01 and linear_error > 4 * flow_error


def test_flow_interpolation_endpoints_are_exact(translating_pair):
    frame0, frame1, _ = translating_pair
    flow01, flow10 = estimate_flows(frame0, frame1)
    np.testing.assert_array_equal(flow_interpolate(frame0, frame1, flow01, flow10, 0), frame0)
    np.testing.assert_array_equal(flow_interpolate(frame0, frame1, flow01, flow10, 1), frame1)
    grey0, grey1 = frame0[:, :, 1], frame1[:, :, 1]
    assert flow_interpolate(grey0, grey1, flow01, flow10, 0.3).shape == grey0.shape


def test_flow_interpolation_prefers_the_frame_that_sees_an_occluded_background():
    # A square moving 8 px right over a still background; true flows given.
    background, square = texture(seed=1), texture(seed=2, cell=12)

    def frame(x):
        out = background.copy()
        out[30:70, 30 + x : 70 + x] = square[30:70, 30:70]
        return out

    flow01, flow10 = np.zeros((2, HEIGHT, WIDTH, 2), np.float32)
    flow01[30:70, 30:70, 0], flow10[30:70, 38:78, 0] = 8, -8
    middle = flow_interpolate(frame(0), frame(8), flow01, flow10, 0.5)
    flow_error = np.abs(middle - frame(4)).mean()
    assert flow_error < 0.5 * np.abs(linear(frame(0), frame(8), 0.5) - frame(4)).mean()
    # Uncovered background just behind the square (x 30..33 at t = 0.5) comes from frame 1 only.
    assert np.abs(middle - frame(4))[32:68, 30:34].mean() < 0.02


@pytest.mark.parametrize("cfa", BAYER_PATTERNS)
def test_a_mosaic_interpolated_alone_is_the_whole_frame_sampled_byte_for_byte(cfa):
    # Flows of up to ~25 px on a 48x64 frame: many samples fall outside and take the reflected border.
    frame0, frame1 = texture(48, 64, seed=3), texture(48, 64, seed=4)
    rng = np.random.default_rng(0)
    flow01 = cv2.resize(rng.normal(0, 10, (6, 8, 2)).astype(np.float32), (64, 48), interpolation=cv2.INTER_CUBIC)
    flow10 = cv2.resize(rng.normal(0, 10, (6, 8, 2)).astype(np.float32), (64, 48), interpolation=cv2.INTER_CUBIC)
    motion = pair_motion(flow01, flow10)
    planes0, planes1 = (np.ascontiguousarray(np.moveaxis(f, 2, 0)) for f in (frame0, frame1))
    for w in (0, 0.3, 0.77, 1):
        whole = cfa_sample(interpolate(frame0, frame1, motion, w), cfa)
        alone = interpolate_mosaic(planes0, planes1, motion, w, colour_index(cfa, 2, 2))
        assert alone.dtype == np.float32
        np.testing.assert_array_equal(alone, whole)
    # ...and a motion made once per pair gives what the flows give frame by frame.
    np.testing.assert_array_equal(interpolate(frame0, frame1, motion, 0.4),
                                  flow_interpolate(frame0, frame1, flow01, flow10, 0.4))
    assert not np.array_equal(interpolate(frame0, frame1, motion, 0.4), interpolate(frame0, frame1, motion, 0.5))
