"""Training, validation and test clips simulated on the fly, with their exact truth.

A clip is what the network sees and what it should give: 41 LR Bayer spike frames of a
picture moving along a smooth random camera path (``stages.simulation.camera_path``), the HR picture at
the middle frame in rate units α·I/θ, and the exact LR flows from the middle frame to
frames 11 and 29 (motion supervision). The sensor is the project's simulator
(``stages.simulation.sensor``, Algorithm 2): brightness α in [0.6, 1.0], random initial integrator
state, either reset, light realistic noise on half the clips (shot noise and dark current; no threshold
mismatch), any of the four CFA phases.

Pictures come from what is installed, nothing downloaded: scikit-image's bundled pictures
(or any folders of picture files, ``picture_files``) and procedurally generated "dead leaves" images (occluding discs of random colours and
textures, the classic synthetic set for restoration). Test pictures are kept apart from
training ones (``TEST_PICTURES``); validation uses dead leaves from their own seeds.
Everything is a function of the seed, so a clip is reproducible bit for bit.
"""

from dataclasses import dataclass, replace

import numpy as np

from cscsr.training.frame_motion import FrameMotion, choices, source_names
from stages.reconstruction.cfa import BAYER_PATTERNS, flip_horizontally, flip_vertically, transpose
from stages.simulation.intensities import luma_rgb, to_unit_rgb
from stages.simulation.camera_path import CameraPath, render
from stages.capture.bits import unpack_rows
from stages.errors import InputError, describe
from stages.reconstruction.methods import WINDOW
from stages.simulation.sensor import SensorModel, area_downsample, cfa_sample, fire, increments, initial_state

TRAIN_PICTURES = ("rocket", "motorcycle_left", "motorcycle_right", "hubble_deep_field", "immunohistochemistry",
                  "retina", "colorwheel", "logo", "brick", "grass", "gravel", "camera", "coins", "moon", "page", "text")
TEST_PICTURES = ("astronaut", "coffee", "chelsea")  # never seen in training
_STEREO_VIEWS = {"motorcycle_left": 0, "motorcycle_right": 1}  # index in skimage.data.stereo_motorcycle()
FRAMES, MIDDLE, SPAN = WINDOW, WINDOW // 2, 9
DEAD_LEAVES_SHARE = 0.4  # clips of dead leaves rather than a picture
PICTURE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
MAX_SPEED = 0.15  # LR px per frame (RMS), the fastest training motion (the test set moves at 0.125)


@dataclass(frozen=True)
class Clip:
    spikes: np.ndarray  # (41, h, w) uint8 0/1
    truth: np.ndarray  # (3, s*h, s*w) float32 rate alpha*I/theta at frame 20
    flows: np.ndarray  # (2, 2, h, w) float32 LR flow frame 20 -> 11 and 20 -> 29 (x, y)
    cfa: str
    zero_reset: bool
    alpha: float
    scale: int


def dead_leaves(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size, 3) float32: occluding discs of random colour, radius ~ 1/r^3, some striped.

    Sized for x2 to x4 super-resolution: the smallest discs and stripes span a few LR pixels.
    """
    import cv2

    image = np.empty((size, size, 3), np.float32)
    image[:] = rng.random(3)
    for _ in range(int(size * size / 150)):
        radius = int(np.clip(size * 0.025 / np.sqrt(rng.uniform(0.002, 1)), 2, size // 3))
        cx, cy = (int(v) for v in rng.integers(0, size, 2))
        colour = rng.random(3)
        if rng.random() < 0.2:  # a striped disc: fine texture the network must not blur away
            period, angle = rng.uniform(6, 24), rng.uniform(0, np.pi)
            y0, y1, x0, x1 = max(cy - radius, 0), min(cy + radius + 1, size), max(cx - radius, 0), min(cx + radius + 1, size)
            y, x = np.mgrid[y0:y1, x0:x1]
            stripes = 0.5 + 0.5 * np.sin(2 * np.pi * (x * np.cos(angle) + y * np.sin(angle)) / period)
            inside = (x - cx) ** 2 + (y - cy) ** 2 <= radius**2
            image[y0:y1, x0:x1][inside] = (colour * (0.4 + 0.6 * stripes[..., None]))[inside]
        else:
            cv2.circle(image, (cx, cy), radius, tuple(float(c) for c in colour), -1)
    return image


def bundled_picture(name: str) -> np.ndarray:
    """A scikit-image picture as (H, W, 3) float32; grey ones are tinted later (``tint``).

    The two views of the stereo motorcycle (natural colour, like the test pictures) are
    pictures of their own: the same scene from two viewpoints.
    """
    from skimage import data

    if name in _STEREO_VIEWS:
        return to_unit_rgb(data.stereo_motorcycle()[_STEREO_VIEWS[name]])
    return to_unit_rgb(getattr(data, name)())


def picture(name: str) -> np.ndarray:
    """A training picture by name: a bundled scikit-image picture, or the path of an image file (a file that
    is not a picture we can use is refused in one line naming it)."""
    if name in TRAIN_PICTURES or name in TEST_PICTURES:
        return bundled_picture(name)
    import imageio.v3 as iio

    try:
        return to_unit_rgb(iio.imread(name))
    except (OSError, ValueError, RuntimeError, SyntaxError, IndexError) as error:  # what imageio's plugins raise
        raise InputError(f"training picture {name} cannot be used: {describe(error)}") from None


def picture_files(folders) -> tuple[str, ...]:
    """Every image file under the given folders (recursively, sorted): the names ``--pictures`` trains on.

    Refused: a folder that does not exist or holds no pictures, and any file whose pixels are one of
    the held-out test pictures (the test set must stay unseen, whatever a folder holds).
    """
    from pathlib import Path

    files = []
    for folder in folders:
        root = Path(folder)
        if not root.is_dir():
            raise InputError(f"picture folder {folder} " + ("is a file: give the folder that holds it" if root.exists()
                                                              else "does not exist"))
        found = sorted(str(f) for f in root.rglob("*") if f.suffix.lower() in PICTURE_SUFFIXES and f.is_file())
        if not found:
            raise InputError(f"picture folder {folder} holds no pictures ({', '.join(PICTURE_SUFFIXES)})")
        files += found
    return tuple(files)


def check_not_test_pictures(names: tuple) -> None:
    """InputError if any named picture file (a still, or a frame of a sequence) holds the pixels of a test
    picture (any size, same picture)."""
    import cv2

    def signature(image: np.ndarray) -> np.ndarray:
        return cv2.resize(np.ascontiguousarray(image, np.float32), (16, 16), interpolation=cv2.INTER_AREA)

    tests = {name: signature(bundled_picture(name)) for name in TEST_PICTURES}
    for name in source_names(names):
        if name in TEST_PICTURES:
            raise InputError(f"{name} is a test picture: it must stay out of training")
        if name in TRAIN_PICTURES:
            continue
        image = signature(picture(name))
        for test, reference in tests.items():
            if np.abs(image - reference).mean() < 0.02:
                raise InputError(f"{name} looks like the test picture {test!r}: it must stay out of training")


def tint(rng: np.random.Generator, image: np.ndarray) -> np.ndarray:
    """Give a grey picture colour: a random mix of two colours by its intensity."""
    if not np.allclose(image[..., 0], image[..., 1]):
        return image
    grey = image[..., :1]
    low, high = rng.random(3) * 0.5, 0.5 + rng.random(3) * 0.5
    return (low + (high - low) * grey).astype(np.float32)


def source_scene(rng: np.random.Generator, pictures: tuple, hr_side: int, cache: dict,
                 dead_leaves_share: float = DEAD_LEAVES_SHARE) -> tuple[np.ndarray, FrameMotion | None]:
    """A random HR crop (side ``hr_side``) of a random picture, rescaled, flipped, rotated, or dead leaves;
    with the real motion around it when the source is a sequence of frames (``pictures`` holds names of
    stills and tuples of frames, ``cscsr.training.frame_motion.group_sequences``), else None.
    A sequence offers one clip per frame with a neighbour on each side; the three frames are cropped alike."""
    import cv2

    if not pictures or rng.random() < dead_leaves_share:
        return dead_leaves(rng, hr_side), None
    choice = int(rng.integers(sum(choices(p) for p in pictures)))
    for source in pictures:  # a still is one choice, a sequence of n frames n - 2
        if choice < choices(source):
            break
        choice -= choices(source)
    names = (source,) if isinstance(source, str) else source[choice : choice + 3]
    for name in names:
        if name not in cache:
            cache[name] = picture(name)
    frames = [cache[name] for name in names]
    if len({f.shape for f in frames}) != 1:
        raise InputError(f"the frames {', '.join(names)} of one sequence differ in size")
    image = tint(rng, np.concatenate(frames, 1))  # side by side: one tint for all
    factor = rng.uniform(0.35, 1.0)
    factor = max(factor, hr_side / min(image.shape[0], frames[0].shape[1]))
    top = rng.integers(0, max(hr_side, round(image.shape[0] * factor)) - hr_side + 1)
    left = rng.integers(0, max(hr_side, round(frames[0].shape[1] * factor)) - hr_side + 1)
    turns, flip = rng.integers(4), rng.random() < 0.5
    width = frames[0].shape[1]
    crops = []
    for k in range(len(frames)):
        frame = image[:, k * width : (k + 1) * width]
        if factor != 1:
            size = (max(hr_side, round(frame.shape[1] * factor)), max(hr_side, round(frame.shape[0] * factor)))
            frame = cv2.resize(frame, size, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_CUBIC)
        crop = np.rot90(frame[top : top + hr_side, left : left + hr_side], turns)
        crops.append(np.ascontiguousarray(crop[:, ::-1] if flip else crop))
    if len(crops) == 1:
        return crops[0], None
    return crops[1], FrameMotion.between(*crops)


@dataclass(frozen=True)
class ClipPlan:
    """Every random choice of one clip, drawn on the CPU; ``simulate_clip`` (numpy, the simulator of
    record) and ``cscsr.training.synthesis`` (torch, on the training device) both carry it out."""

    picture: np.ndarray  # (hr_side, hr_side, 3) float32: the padded scene, hr_side = scale * (lr_side + 2 * margin)
    path: CameraPath | FrameMotion  # the scene's motion on the HR grid: a camera path, or footage's own
    sensor: SensorModel
    cfa: str
    lr_side: int
    scale: int

    @property
    def margin(self) -> int:
        """LR pixels of scene around the clip on each side: the borders never show reflected content."""
        return (self.picture.shape[0] // self.scale - self.lr_side) // 2

    @property
    def zero_reset(self) -> bool:
        return self.sensor.reset == "zero"

    def flows(self) -> np.ndarray:
        """(2, 2, lr, lr) float32 exact LR flows from the middle frame to frames MIDDLE -/+ SPAN, (x, y)."""
        crop = slice(self.margin, self.margin + self.lr_side)
        if isinstance(self.path, FrameMotion):  # HR flows averaged over each LR pixel, in LR pixels
            return np.stack([area_downsample(self.path.flow(MIDDLE + d, FRAMES), self.scale)[crop, crop]
                             .transpose(2, 0, 1) / self.scale for d in (-SPAN, SPAN)]).astype(np.float32)
        lr_path = self.path.scaled(1 / self.scale)
        return np.stack([lr_path.flow(MIDDLE, MIDDLE + d)[crop, crop].transpose(2, 0, 1)
                         for d in (-SPAN, SPAN)]).astype(np.float32)

    def frame(self, t: float) -> np.ndarray:
        """(hr_side, hr_side, 3) float32 latent frame t of the whole padded scene (numpy, the simulator of record)."""
        if isinstance(self.path, FrameMotion):
            return self.path.render(self.picture, t, FRAMES)
        return render(self.picture, self.path, t)


def plan_clip(picture: np.ndarray, rng: np.random.Generator, *, lr_side: int, scale: int, alpha: float,
              cfa: str, zero_reset: bool, noise: str, speed: float, motion: FrameMotion | None = None) -> ClipPlan:
    """The camera path (or the footage's ``motion``) and sensor of a clip of ``picture``
    (HR side = scale * (lr_side + 2 * margin))."""
    hr_side = picture.shape[0]
    if motion is None:
        seed = int(rng.integers(2**31))
        path = CameraPath.random(FRAMES, hr_side, hr_side, seed=seed, speed=speed * scale,
                                 deform=float(rng.uniform(0, 0.5)) * scale if rng.random() < 0.3 else 0.0)
    else:
        path = motion
    sensor = SensorModel(brightness=alpha, threshold=1.0, reset="zero" if zero_reset else "subtract",
                         noise=noise, seed=int(rng.integers(2**31)))
    return ClipPlan(picture, path, sensor, cfa, lr_side, scale)


def simulate_clip(picture: np.ndarray, rng: np.random.Generator, *, lr_side: int, scale: int, alpha: float,
                  cfa: str, zero_reset: bool, noise: str, speed: float) -> Clip:
    """A picture (HR side = scale * (lr_side + 2 * margin)) moving on a random path -> one clip."""
    return run_plan(plan_clip(picture, rng, lr_side=lr_side, scale=scale, alpha=alpha, cfa=cfa,
                              zero_reset=zero_reset, noise=noise, speed=speed))


def run_plan(plan: ClipPlan) -> Clip:
    """A clip planned by ``plan_clip``, simulated with ``stages`` (numpy): the simulator of record.

    The path moves the whole padded picture; the clip is its centre, so the borders never show
    reflected content and the flows are exact everywhere in the crop.
    """
    scale, lr_side, margin = plan.scale, plan.lr_side, plan.margin
    crop = slice(margin, margin + lr_side)
    hr_crop = slice(margin * scale, (margin + lr_side) * scale)
    mosaics = np.stack([cfa_sample(area_downsample(plan.frame(t), scale), plan.cfa)[crop, crop]
                        for t in range(FRAMES)])  # (41, lr, lr)
    sensor = plan.sensor
    fired = fire(increments(sensor, mosaics, 0), initial_state(sensor, lr_side, lr_side), reset=sensor.reset)
    truth = sensor.brightness * plan.frame(MIDDLE)[hr_crop, hr_crop]
    return Clip(unpack_rows(fired.packed, lr_side), np.ascontiguousarray(truth.transpose(2, 0, 1), np.float32),
                plan.flows(), plan.cfa, plan.zero_reset, sensor.brightness, scale)


def random_plan(seed, *, lr_side: int, scale: int, pictures: tuple = TRAIN_PICTURES,
                cache: dict | None = None, alpha: float | None = None,
                dead_leaves_share: float = DEAD_LEAVES_SHARE, mono: bool = False) -> ClipPlan:
    """A training clip's plan: everything drawn from ``seed`` (an int or a sequence of ints). ``mono``: a mono
    sensor's clip (the scene turned to its Rec.601 luma, so the truth is the grey it sees; the same draws)."""
    rng = np.random.default_rng(seed)
    margin = max(4, lr_side // 4) // 2 * 2
    picture, motion = source_scene(rng, pictures, scale * (lr_side + 2 * margin), {} if cache is None else cache,
                                   dead_leaves_share)
    if mono:
        picture = luma_rgb(picture)
        if motion is not None:  # footage's neighbours grey too (their flows stay: they were measured on colour)
            motion = replace(motion, before=luma_rgb(motion.before), after=luma_rgb(motion.after))
    alpha = float(rng.uniform(0.6, 1.0)) if alpha is None else alpha
    cfa = BAYER_PATTERNS[rng.integers(4)]
    return plan_clip(picture, rng, lr_side=lr_side, scale=scale, alpha=alpha,
                     cfa="mono" if mono else cfa, zero_reset=bool(rng.random() < 0.5),
                     noise="realistic" if rng.random() < 0.5 else "none",
                     speed=float(rng.uniform(0, MAX_SPEED)), motion=motion)


def random_clip(seed, *, lr_side: int, scale: int, pictures: tuple = TRAIN_PICTURES,
                cache: dict | None = None, alpha: float | None = None,
                dead_leaves_share: float = DEAD_LEAVES_SHARE, mono: bool = False) -> Clip:
    """A training clip: everything drawn from ``seed`` (an int or a sequence of ints); ``mono`` as in ``random_plan``."""
    return run_plan(random_plan(seed, lr_side=lr_side, scale=scale, pictures=pictures, cache=cache, alpha=alpha,
                                dead_leaves_share=dead_leaves_share, mono=mono))


def reoriented(clip: Clip, orientation: int) -> Clip:
    """The clip seen under one of the 8 flips and quarter turns (0 leaves it as it is).

    Spikes, truth and flows turn together and the CFA name follows the turn, so the result is
    exactly the clip the simulator would give for the turned scene: eight clips for one
    simulation. Bits 0, 1, 2 of ``orientation``: transpose, then flip left-right, then upside down.
    """
    spikes, truth, flows, cfa = clip.spikes, clip.truth, clip.flows, clip.cfa
    if orientation & 1:
        spikes, truth = spikes.swapaxes(-1, -2), truth.swapaxes(-1, -2)
        flows, cfa = flows[:, ::-1].swapaxes(-1, -2), transpose(cfa)  # (x, y) -> (y, x)
    if orientation & 2:
        spikes, truth, flows = spikes[..., ::-1], truth[..., ::-1], flows[..., ::-1] * _SIGNS[0]
        cfa = flip_horizontally(cfa, spikes.shape[-1])
    if orientation & 4:
        spikes, truth, flows = spikes[..., ::-1, :], truth[..., ::-1, :], flows[..., ::-1, :] * _SIGNS[1]
        cfa = flip_vertically(cfa, spikes.shape[-2])
    return Clip(np.ascontiguousarray(spikes), np.ascontiguousarray(truth), np.ascontiguousarray(flows, np.float32),
                cfa, clip.zero_reset, clip.alpha, clip.scale)


_SIGNS = (np.array([-1, 1], np.float32)[:, None, None], np.array([1, -1], np.float32)[:, None, None])  # x or y negated


def batch_arrays(clips: list[Clip]) -> dict:
    """Clips of one scale and size -> stacked arrays for the trainer."""
    return {"spikes": np.stack([c.spikes for c in clips]), "truth": np.stack([c.truth for c in clips]),
            "flows": np.stack([c.flows for c in clips]), "cfa": [c.cfa for c in clips],
            "zero_reset": np.array([c.zero_reset for c in clips]), "alpha": np.array([c.alpha for c in clips]),
            "scale": clips[0].scale}
