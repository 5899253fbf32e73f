"""What a simulation job will do, as frozen data: its options (:class:`SimulateOptions`), their checks against
the source (:func:`check_options`), what the spike store records (:func:`simulated_meta`), and the scene it reads
(:func:`open_scene`): a picture under camera motion (:class:`CameraFrames`), a video spread over the spike frames
(:class:`VideoFrames`), or a source's frames as they are (:class:`SourceFrames`), each read a block of frames at a
time, and the first two making their LR mosaics and truth pictures as the simulator always has
(``stages.simulation.latent``). Nothing here touches a cluster or a store: ``pipeline.jobs.simulate`` makes the
graph, which ``pipeline.lazy`` offers as ``open_frames`` -> ``simulate`` -> ``to_spikes``.
"""

import functools
from dataclasses import dataclass

import numpy as np

from pipeline.stores.frame_sources import FrameSource
from pipeline.stores.spike_store import SpikeMeta, check_fps
from pipeline.stores.storage import resolve
from stages.errors import InputError
from stages.numbers import check_flag, check_number, check_text
from stages.reconstruction.cfa import check_cfa
from stages.reconstruction.colour import check_gain
from stages.reconstruction.methods import WINDOW
from stages.simulation import sensor
from stages.simulation.camera_path import CameraPath, render
from stages.simulation.intensities import to_unit_rgb
from stages.simulation.interpolate import INTERPOLATIONS, PairMotion, estimate_motion
from stages.simulation.latent import (between, bracket, source_position, still_mosaics, upscale_motion,
                                      video_mosaics)

TRUTH_SCALES = (1, 2, 4)  # the HR truth the simulator can draw beside the LR spikes
MOTIONS = ("static", "random")
# The longest simulation: 10^9 spike frames are 13.9 hours at 20,000 fps, beyond any recording a reconstruction
# is tested on; 10^12 would run for years (it ended in a bare MemoryError, listing its truth frames).
MAX_FRAMES = 10**9
MAX_FRAMES_WHY = "13.9 hours at 20,000 fps"
MAX_TRUTH_FRAMES = 2**25  # their indices: a Python list of ~1.2 GB and one int64 chunk of 256 MiB


@dataclass(frozen=True)
class SimulateOptions:
    scale: int = 4
    cfa: str = "rggb"
    brightness: float = 0.6
    threshold: float = 1.0
    frames: int = WINDOW
    motion: str | None = None  # for a still image: "static" or "random"
    seed: int = 0
    noise: str = "none"
    reset: str = "zero"
    interp: str = "flow"
    truth_every: int = WINDOW
    speed: float | None = None  # random motion: typical HR pixels per spike frame (None: CameraPath.random's)
    deform: float | None = None  # random motion: local deformation amplitude, HR pixels (None: CameraPath.random's)
    fps: float = 20000.0
    chunk_frames: int | None = None
    overwrite: bool = False

    def check(self) -> None:
        """The type of every option (only the Python API can get them wrong: ``scale=4.0``, ``frames="82"``,
        ``overwrite="no"``), before :func:`check_options` checks their values against the source."""
        for name in ("cfa", "noise", "reset", "interp"):
            check_text(f"--{name}", getattr(self, name))
        check_text("--motion", self.motion, optional=True)
        for name in ("scale", "frames", "seed", "truth_every"):
            check_number(f"--{name.replace('_', '-')}", getattr(self, name), integer=True)
        if self.chunk_frames is not None:
            check_number("--chunk-frames", self.chunk_frames, integer=True)
        for name in ("brightness", "threshold", "speed", "deform", "fps"):
            if getattr(self, name) is not None or name not in ("speed", "deform"):
                check_number(f"--{name}", getattr(self, name))
        check_flag("--overwrite", self.overwrite)

    def sensor_model(self) -> sensor.SensorModel:
        return sensor.SensorModel(self.brightness, self.threshold, self.reset, self.noise, self.seed)


def check_options(options: SimulateOptions, source: FrameSource) -> tuple[int, int]:
    """Validate everything before any output exists; return the LR (height, width)."""
    options.check()  # types first
    options.sensor_model()  # alpha, theta, reset, noise
    cfa = check_cfa(options.cfa)
    if options.interp not in INTERPOLATIONS:
        raise InputError(f"unknown interpolation {options.interp!r}: expected one of {', '.join(INTERPOLATIONS)}")
    if options.scale not in TRUTH_SCALES:
        raise InputError(f"scale must be one of {', '.join(map(str, TRUTH_SCALES))}, got {options.scale}")
    check_number("--frames", options.frames, integer=True)
    if options.frames < WINDOW:
        raise InputError(f"--frames {options.frames} is too few: a reconstruction window needs {WINDOW}")
    check_number("--frames", options.frames, at_most=MAX_FRAMES, why=MAX_FRAMES_WHY)
    check_number("--truth-every", options.truth_every, at_least=1, integer=True)
    truth_frames = len(range(WINDOW // 2, options.frames - WINDOW // 2, options.truth_every))
    if truth_frames > MAX_TRUTH_FRAMES:  # output_centres is one list, truth_frames one chunk: both in memory
        raise InputError(f"--frames {options.frames} with --truth-every {options.truth_every} gives {truth_frames:,} "
                         f"truth frames, more than {MAX_TRUTH_FRAMES:,} (their frame indices are held in memory "
                         f"and written as one chunk): raise --truth-every")
    check_gain("the recorded gain θ/α (--threshold / --brightness)", options.threshold / options.brightness)
    if options.motion is not None and options.motion not in MOTIONS:
        raise InputError(f"unknown motion {options.motion!r}: expected one of {', '.join(MOTIONS)}")
    if source.n_frames < 2 and options.motion is None:
        raise InputError(f"{source.url} has {source.n_frames} frame: give --motion static|random to move a still image")
    if options.motion is not None and source.n_frames != 1:
        raise InputError("--motion applies to a single image; a video or folder brings its own motion")
    check_path_options(options.motion, options.speed, options.deform)
    check_fps("--fps", options.fps)
    if options.chunk_frames is not None:  # 0 must not mean "the default"
        check_number("--chunk-frames", options.chunk_frames, at_least=1, integer=True)
    if cfa == "mono" and (source.height % options.scale or source.width % options.scale):  # any LR size
        raise InputError(f"frame size {source.height}x{source.width} is not divisible by --scale {options.scale} "
                         f"(an LR pixel is {options.scale}x{options.scale} HR pixels)")
    multiple = 2 * options.scale
    if cfa != "mono" and (source.height % multiple or source.width % multiple):
        raise InputError(f"frame size {source.height}x{source.width} is not divisible by 2*scale = {multiple} (a "
                         f"{cfa} cell of 2x2 LR pixels is {multiple}x{multiple} HR pixels)")
    return source.height // options.scale, source.width // options.scale


def simulated_meta(options: SimulateOptions, height: int, width: int, source: str) -> SpikeMeta:
    """What a simulated spike store records (its attributes): the LR size, the sensor's settings, how the scene
    was made (``motion`` "video" for a video-like source) and ``source``."""
    return SpikeMeta(height=height, width=width, cfa=options.cfa, fps=options.fps, source=source,
                     reset=options.reset, gain=options.sensor_model().gain, threshold=options.threshold,
                     extra={"brightness": options.brightness, "scale": options.scale, "seed": options.seed,
                            "noise": options.noise, "interp": options.interp, "motion": options.motion or "video",
                            "truth_every": options.truth_every, "simulated": True})


def check_path_options(motion: str | None, speed: float | None, deform: float | None) -> None:
    """Refuse ``--speed`` and ``--deform`` (None where not given) where there is no random camera path for them to
    shape: they would be ignored without a word. Each given one must be a number >= 0."""
    given = {name: value for name, value in (("--speed", speed), ("--deform", deform)) if value is not None}
    if given and motion != "random":
        scene = f"--motion {motion}" if motion else "a video's own motion"
        raise InputError(f"{' and '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to the random camera path "
                         f"(--motion random) only, not to {scene}")
    for name, value in given.items():
        check_number(name, value, at_least=0)


# ---- the scene ----

def open_scene(source: FrameSource, *, frames: int | None, motion: str | None, seed: int, speed: float | None,
               deform: float | None, interp: str, scale: int) -> "CameraFrames | VideoFrames | SourceFrames":
    """The scene of ``source`` (as ``open_frame_source`` opened it; ``lazy.open_frames`` says what each option means):
    a picture under ``motion`` over ``frames`` frames, a video spread over ``frames`` spike frames, or (no
    ``frames``) a source's own frames; its first frame read now (its dtype and colours are every frame's). One line, in Python words, for a
    source or options that make no scene."""
    url = source.url
    first = as_4d(source.read(0), source, 0, None)
    version = source_version(url)
    if source.n_frames == 1 and (source.kind == "image" or motion is not None):
        if frames is None or motion not in MOTIONS:
            raise InputError(f"{url} is one picture: give frames= and motion= ({' or '.join(MOTIONS)}), the "
                             f"scene's length and how the camera moves, got frames={frames}, motion={motion!r}")
        shape = {name: value for name, value in (("speed", speed), ("deform", deform)) if value is not None}
        path = CameraPath.random(frames, source.height, source.width, seed=seed, **shape) \
            if motion == "random" else None
        return CameraFrames(source, frames, first.dtype.str, first.shape[-1], path, seed, version)
    if motion is not None:
        raise InputError(f"motion= is for a picture; {url} is a {source.kind} with motion of its own")
    if frames is None:
        return SourceFrames(source, first.dtype.str, first.shape[-1], version)
    if source.n_frames < 2:
        raise InputError(f"{url} has {source.n_frames} frame: give motion= ({' or '.join(MOTIONS)}) to move a still "
                         f"picture")
    return VideoFrames(source, frames, first.dtype.str, first.shape[-1], interp, scale, version)


def source_version(url: str):
    """What tells this version of the source from a later one at the same place (in the graph's token): a file's
    key, a folder's (pictures, a Zarr video) every file's name, size and time (a file rewritten inside a folder
    leaves the folder's own as it was)."""
    fs, path = resolve(url)
    if fs.isdir(path):
        return tuple(sorted((entry["name"], entry.get("size"), str(entry.get("mtime") or entry.get("LastModified")
                                                                    or entry.get("ETag")))
                            for entry in fs.find(path, detail=True).values()))
    return fs.ukey(path)


def as_4d(frame: np.ndarray, source: FrameSource, index: int, like: tuple[str, int] | None) -> np.ndarray:
    """Frame ``index`` as (1, H, W, colours); refused unless it is the size of the source and, given ``like``
    (dtype, colours), of that dtype and those colours."""
    frame = np.asarray(frame)
    frame = frame[:, :, None] if frame.ndim == 2 else frame
    if frame.ndim != 3 or frame.shape[:2] != (source.height, source.width) or frame.shape[2] not in (1, 3, 4):
        raise InputError(f"{source.url}: frame {index} has shape {frame.shape}, not ({source.height}, "
                         f"{source.width}) grey, RGB or RGBA as frame 0")
    if not np.issubdtype(frame.dtype, np.unsignedinteger):
        raise InputError(f"{source.url}: frame {index} holds {frame.dtype}, not unsigned integers")
    if like is not None and (frame.dtype.str, frame.shape[2]) != like:
        raise InputError(f"{source.url}: frame {index} is {frame.dtype} with {frame.shape[2]} colours, frame 0 "
                         f"{np.dtype(like[0])} with {like[1]}: convert the frames alike")
    return frame[None]


@dataclass(frozen=True)
class CameraFrames:
    """A picture as ``n_frames`` scene frames under a camera ``path`` (None: static), as dask reads them, a block
    at a time; the picture decoded once a block. Pickled as its fields."""

    source: FrameSource
    n_frames: int
    dtype_str: str  # the picture's (static), float32 (rendered)
    colours: int
    path: CameraPath | None
    seed: int  # what drew the path (CameraPath.random)
    version: object  # :func:`source_version`: only in the token

    ndim = 4

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.dtype_str if self.path is None else np.float32)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return self.n_frames, self.source.height, self.source.width, self.colours if self.path is None else 3

    def __getitem__(self, key) -> np.ndarray:
        frames, *rest = key
        start, stop, _ = frames.indices(self.n_frames)
        picture = _picture(self.source, self.version, (self.dtype_str, self.colours))
        if self.path is None:
            block = np.broadcast_to(picture, (stop - start, *picture.shape[1:]))
        else:
            image = to_unit_rgb(picture[0])
            block = np.stack([render(image, self.path, t) for t in range(start, stop)])
        return np.ascontiguousarray(block[(slice(None), *rest)])

    def mosaics(self, frames: range, scale: int, cfa: str, pairs: dict) -> np.ndarray:
        """The LR mosaics (n, H, W) float32 of spike frames ``frames``, as the ``simulate`` job makes them: one
        mosaic repeated (static), or each frame rendered at HR and area-downsampled, one at a time."""
        image = intensities(self.source, self.version, 0)
        if self.path is None:
            mosaic = sensor.cfa_sample(sensor.area_downsample(image, scale), cfa)
            return np.broadcast_to(mosaic, (len(frames), *mosaic.shape))
        return still_mosaics(image, self.path, list(frames), scale, cfa)

    def intensities(self, frame: int, hr_motion: PairMotion | None = None) -> np.ndarray:
        """Scene frame ``frame`` as float32 RGB intensities (the ``simulate`` job's truth is drawn from it)."""
        image = intensities(self.source, self.version, 0)
        return image if self.path is None else render(image, self.path, frame)

    def pairs(self, frames: range) -> list[int]:
        return []  # a picture: no pair of source frames to interpolate between


@functools.lru_cache(maxsize=2)
def _picture(source: FrameSource, version, like: tuple[str, int]) -> np.ndarray:
    """The picture of a scene, (1, H, W, colours), decoded once a process (every block of its frames reads it)."""
    picture = as_4d(source.read(0), source, 0, like)
    picture.flags.writeable = False  # shared between blocks
    return picture


@dataclass(frozen=True)
class VideoFrames:
    """A video's frames spread evenly over ``n_frames`` spike frames and interpolated between (the ``simulate``
    job's latent frames, ``stages.simulation.latent``), as float32 RGB intensities: spike frame ``t`` lies a
    fraction ``w`` of the way from source frame ``i`` to ``i + 1`` (:meth:`pair`). Pickled as its fields."""

    source: FrameSource
    n_frames: int
    dtype_str: str  # the source's (checked as frame 0's)
    colours: int
    interp: str  # "flow" or "linear"
    scale: int  # flow: each pair's motion estimated on its frames area-downsampled by this
    version: object  # :func:`source_version`: only in the token

    ndim = 4
    dtype = np.dtype(np.float32)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return self.n_frames, self.source.height, self.source.width, 3

    def pair(self, frame: int) -> tuple[int, float]:
        """(i, w): spike frame ``frame`` lies a fraction ``w`` from source frame ``i`` to ``i + 1``."""
        return bracket(source_position(frame, self.n_frames, self.source.n_frames), self.source.n_frames)

    def pairs(self, frames: range) -> list[int]:
        """The pairs (i, i + 1) spike frames ``frames`` lie between, by ``i``."""
        return sorted({self.pair(t)[0] for t in frames})

    def lr_frame(self, index: int) -> np.ndarray:
        """Task: source frame ``index`` as intensities, area-downsampled by :attr:`scale` (the job's LR frame)."""
        frame = intensities(self.source, self.version, index, (self.dtype_str, self.colours))
        return sensor.area_downsample(frame, self.scale)

    def motion(self, lr_frame0: np.ndarray, lr_frame1: np.ndarray) -> PairMotion | None:
        """Task: a pair's motion at LR (None: linear interpolation)."""
        return estimate_motion(lr_frame0, lr_frame1) if self.interp == "flow" else None

    def mosaics(self, frames: range, scale: int, cfa: str, pairs: dict) -> np.ndarray:
        """The LR mosaics (n, H, W) float32 of spike frames ``frames``, as the ``simulate`` job makes them: LR frames
        interpolated at LR; ``pairs[i]``: (LR frame i, LR frame i + 1, their motion) of each pair they lie in."""
        positions = [source_position(t, self.n_frames, self.source.n_frames) for t in frames]
        return video_mosaics(pairs, positions, self.source.n_frames, cfa)

    def intensities(self, frame: int, hr_motion: PairMotion | None = None) -> np.ndarray:
        """Scene frame ``frame`` at HR: its pair's frames interpolated, by their motion estimated at LR and upscaled
        (``hr_motion``, else made here, once a process)."""
        i, w = self.pair(frame)
        like = (self.dtype_str, self.colours)
        frame0 = intensities(self.source, self.version, i, like)
        frame1 = frame0 if w == 0 else intensities(self.source, self.version, i + 1, like)
        if hr_motion is None and self.interp == "flow" and 0 < w < 1:
            hr_motion = _hr_motion(self, i)
        return between(frame0, frame1, w, hr_motion if self.interp == "flow" else None)

    def __getitem__(self, key) -> np.ndarray:
        frames, *rest = key
        start, stop, _ = frames.indices(self.n_frames)
        return np.stack([self.intensities(t) for t in range(start, stop)])[(slice(None), *rest)]


def hr_pair_motion(scene: VideoFrames, motion: PairMotion | None) -> PairMotion | None:
    """Task: a pair's motion at LR, for its HR frames."""
    return None if motion is None else upscale_motion(motion, scene.scale)


@functools.lru_cache(maxsize=1)
def _hr_motion(scene: VideoFrames, index: int) -> PairMotion | None:
    """Pair ``index``'s motion for its HR frames, made once a process (384 MB at 4000x4000: one kept)."""
    return hr_pair_motion(scene, scene.motion(scene.lr_frame(index), scene.lr_frame(index + 1)))


@functools.lru_cache(maxsize=2)
def intensities(source: FrameSource, version, index: int, like: tuple[str, int] | None = None) -> np.ndarray:
    """Source frame ``index`` as float32 RGB intensities, decoded once a process (a picture is read by every block
    and truth task, a video's frame by its LR task and the truth frames beside it); ``like``: the dtype and colours
    it must have (frame 0's)."""
    frame = np.asarray(source.read(index))
    if like is not None:
        as_4d(frame, source, index, like)
    frame = to_unit_rgb(frame)
    frame.flags.writeable = False  # shared between tasks
    return frame


@dataclass(frozen=True)
class SourceFrames:
    """A source's frames as dask reads them (``da.from_array``), a block of frames at a time. Pickled as its
    fields."""

    source: FrameSource
    dtype_str: str
    colours: int
    version: object  # :func:`source_version`: only in the token

    ndim = 4

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.dtype_str)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return self.source.n_frames, self.source.height, self.source.width, self.colours

    def __getitem__(self, key) -> np.ndarray:
        frames, *rest = key
        start, stop, _ = frames.indices(self.source.n_frames)
        like = (self.dtype_str, self.colours)
        block = np.concatenate([as_4d(frame, self.source, i, like)
                                for i, frame in enumerate(self.source.read_run(start, stop), start)])
        return block[(slice(None), *rest)]
