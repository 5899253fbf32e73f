"""Real motion from folders of consecutive frames (cscsr.training.frame_motion): which folders are sequences, and clips
of footage whose frames follow the footage's motion, in numpy and in torch alike."""

import imageio.v3 as iio
import numpy as np
import pytest

from cscsr.training.frame_motion import FrameMotion, group_sequences, sequence_frames
from cscsr.training.synthesis import prepare, synthesise
from cscsr.training.training_data import dead_leaves, picture_files, random_plan, run_plan

SHIFT = 2  # HR pixels per frame of footage: the picture moves left by this much from frame to frame
SIDE = 96  # the padded scene of a clip of LR 16 at x4: frames of exactly this size are cropped, not rescaled


def test_a_folder_of_consecutive_numbered_frames_is_a_sequence():
    davis = [f"dog/{i:05d}.jpg" for i in (2, 0, 1, 3)]
    assert sequence_frames(davis) == ("dog/00000.jpg", "dog/00001.jpg", "dog/00002.jpg", "dog/00003.jpg")
    assert sequence_frames([f"walk/frame_{i:03d}.png" for i in range(1, 8)])[-1] == "walk/frame_007.png"
    assert sequence_frames(["b/100075.jpg", "b/100080.jpg", "b/100098.jpg"]) is None  # BSDS500: not consecutive
    assert sequence_frames([f"u/img_{i:03d}_SRF_2_HR.png" for i in (1, 3, 5)]) is None  # Urban100: steps of 2
    assert sequence_frames(["t/t37.png", "t/t38.png", "t/tt1.png"]) is None  # two prefixes
    assert sequence_frames(["s/00000.jpg", "s/00001.png", "s/00002.jpg"]) is None  # two extensions
    assert sequence_frames(["s/00000.jpg", "s/00001.jpg"]) is None  # too short for a centre with two neighbours
    assert sequence_frames(["s/a.jpg", "s/b.jpg", "s/c.jpg"]) is None
    names = ("p/a.png", *(f"p/seq/{i}.png" for i in range(3)), "p/z.png")
    assert group_sequences(names) == ("p/a.png", ("p/seq/0.png", "p/seq/1.png", "p/seq/2.png"), "p/z.png")


@pytest.fixture
def footage(tmp_path):
    """A folder of 5 frames of a picture moving left by SHIFT pixels per frame, as 8-bit PNG."""
    scene = dead_leaves(np.random.default_rng(3), SIDE + 5 * SHIFT)
    folder = tmp_path / "footage"
    folder.mkdir()
    for j in range(5):
        iio.imwrite(folder / f"frame_{j + 1:03d}.png", (scene[:SIDE, j * SHIFT : j * SHIFT + SIDE] * 255).round()
                    .astype(np.uint8))
    return group_sequences(picture_files([folder]))


def moved(image: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``image`` with its content moved by an integer (dx, dy)."""
    return np.roll(image, (int(shift[1]), int(shift[0])), axis=(0, 1))


def inner(image: np.ndarray) -> np.ndarray:
    return image[16:-16, 16:-16]


def test_a_clip_of_footage_follows_the_footages_motion(footage):
    assert len(footage) == 1 and len(footage[0]) == 5
    directions = set()
    for seed in range(6):
        plan = random_plan([seed, 1], lr_side=16, scale=4, pictures=footage, dead_leaves_share=0.0)
        assert isinstance(plan.path, FrameMotion)
        centre = plan.picture
        # the frame of footage after the centre is the centre moved by SHIFT along one axis (the crop turns and flips)
        candidates = [np.array(d) * SHIFT for d in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        errors = [np.abs(inner(plan.path.after - moved(centre, d))).mean() for d in candidates]
        motion = candidates[int(np.argmin(errors))]
        assert min(errors) < 0.01 < sorted(errors)[1]
        directions.add(tuple(motion))
        # spike frames 0, 20 and 40 are frames k-1, k, k+1; the frames between move by the same steps
        assert np.array_equal(plan.frame(20), centre) and np.abs(plan.frame(40) - plan.path.after).max() < 1e-6
        for t, part in ((30, 0.5), (10, -0.5), (0, -1.0)):
            expected = moved(centre, part * motion)
            error = np.abs(inner(plan.frame(t) - expected)).mean()
            assert error < 0.01, (seed, t, error)
            assert error < 0.2 * np.abs(inner(plan.frame(t) - centre)).mean()
        # the key flows, middle -> frames 11 and 29: 9/20 of a frame's motion, in LR pixels
        flows = plan.flows()  # (2, 2, 16, 16)
        for k, sign in ((0, -1), (1, 1)):
            median = np.median(flows[k, :, 4:-4, 4:-4].reshape(2, -1), axis=1)
            assert median == pytest.approx(sign * 9 / 20 * motion / 4, abs=0.03)
        clip = run_plan(plan)  # the truth is the centre frame
        crop = slice(16, 16 + 64)
        assert np.allclose(clip.truth, plan.sensor.brightness * centre[crop, crop].transpose(2, 0, 1), atol=1e-6)
    assert len(directions) > 1  # the crops turn, and their motion with them


def test_torch_clips_of_footage_are_the_simulators_clips(footage):
    plans = [random_plan([seed, 2], lr_side=16, scale=4, pictures=footage, dead_leaves_share=0.5) for seed in range(6)]
    assert 0 < sum(isinstance(p.path, FrameMotion) for p in plans) < len(plans)  # footage and camera paths mixed
    made = synthesise(prepare(plans), "cpu")
    for i, plan in enumerate(plans):
        clip = run_plan(plan)
        assert (made["spikes"][i].numpy().astype(np.uint8) == clip.spikes).mean() > 0.999
        assert np.abs(made["truth"][i].numpy() - clip.truth).max() < 1e-3
        assert np.array_equal(made["flows"][i].numpy(), clip.flows)


def test_a_test_picture_among_the_frames_of_a_sequence_is_refused(tmp_path, footage):
    from skimage import data

    from cscsr.training.train import TrainOptions
    from cscsr.training.training_batches import training_pictures
    from stages.errors import InputError

    folder = tmp_path / "footage"
    iio.imwrite(folder / "frame_006.png", data.chelsea())  # frame 6 of the sequence
    assert len(group_sequences(picture_files([folder]))[0]) == 6
    with pytest.raises(InputError, match="test picture 'chelsea'"):
        training_pictures(TrainOptions(pictures=str(folder)))
