"""``cscsr simulate``: an LR Bayer spike recording with HR ground truth (Algorithm 2), on Dask.

The graph, per time chunk of the output:

    mosaics + increments (parallel over chunks: the costly part, interpolation/warping)
      -> fire (a chain: the integer accumulator passes from chunk to chunk, exactly)
      -> write (one task per chunk region of ``spikes``: no two writers share a chunk)

plus one task per ground-truth frame (and per flow field for synthetic motion). The steps are
planned as frozen data (``pipeline.jobs.simulate_plan``) and submitted in a bounded window
(``pipeline.compute.executor``), so memory and graph size stay bounded however long the recording is. The accumulator is an integer (``stages.simulation.sensor.UNITS`` per threshold) and all
noise is keyed by frame index, so the bytes written do not depend on the chunking or on the
number of workers.
"""

import functools
import logging
from dataclasses import dataclass

import numpy as np
from distributed import Client

from pipeline.compute.cluster import check_in_memory, check_scheduler, check_workers, dask_client
from pipeline.compute.executor import submitted
from pipeline.stores.frame_sources import FrameSource, open_frame_source
from pipeline.compute.hold import hold_point
from pipeline.stores.lease import claimed, held
from pipeline.compute.progress import progress_bar
from pipeline.jobs.simulate_plan import SpikeChunk, Step, TruthFrame, simulation_steps
from pipeline.stores.ground_truth import declare_truth, write_flow, write_truth
from pipeline.stores.spike_store import SPIKES, SpikeMeta, SpikeStoreWriter, chunk_frames_for, write_region
from pipeline.stores.outputs import SPIKE_STORE, new_output
from pipeline.stores.storage import check_apart, recorded
from stages.simulation import sensor
from stages.reconstruction.cfa import check_cfa
from stages.reconstruction.colour import check_gain
from stages.errors import InputError
from stages.simulation.intensities import to_unit_rgb
from stages.simulation.interpolate import INTERPOLATIONS, PairMotion, estimate_motion
from stages.numbers import check_flag, check_number, check_text
from stages.simulation.latent import bracket, between, source_position, still_mosaics, truth_image, upscale_motion, video_mosaics
from stages.simulation.camera_path import CameraPath, render
from stages.reconstruction.methods import WINDOW, output_centres

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
    speed: float = 0.5  # random motion: typical HR pixels per spike frame
    deform: float = 0.0  # random motion: local deformation amplitude, HR pixels
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
            check_number(f"--{name}", getattr(self, name))
        check_flag("--overwrite", self.overwrite)

    def sensor_model(self) -> sensor.SensorModel:
        return sensor.SensorModel(self.brightness, self.threshold, self.reset, self.noise, self.seed)


@dataclass(frozen=True)
class Scene:
    """What the latent frames come from: a video-like source, or a still and its camera path."""

    source: FrameSource
    path: CameraPath | None  # None for a video, or a static still

    @property
    def is_still(self) -> bool:
        return self.source.n_frames == 1


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
    check_number("--speed", options.speed, at_least=0)
    check_number("--deform", options.deform, at_least=0)
    if options.chunk_frames is not None:  # 0 must not mean "the default"
        check_number("--chunk-frames", options.chunk_frames, at_least=1, integer=True)
    multiple = 2 * options.scale
    if source.height % multiple or source.width % multiple:
        raise InputError(f"frame size {source.height}x{source.width} is not divisible by 2*scale = {multiple} "
                         f"({cfa} Bayer cells of {options.scale}x{options.scale} HR pixels)")
    return source.height // options.scale, source.width // options.scale


def simulated_meta(options: SimulateOptions, height: int, width: int, source: str) -> SpikeMeta:
    """What a simulated spike store records (its attributes): the LR size, the sensor's settings, how the scene
    was made (``motion`` "video" for a video-like source) and ``source``."""
    return SpikeMeta(height=height, width=width, cfa=options.cfa, fps=options.fps, source=source,
                     reset=options.reset, gain=options.sensor_model().gain, threshold=options.threshold,
                     extra={"brightness": options.brightness, "scale": options.scale, "seed": options.seed,
                            "noise": options.noise, "interp": options.interp, "motion": options.motion or "video",
                            "truth_every": options.truth_every, "simulated": True})


# ---- tasks (run on workers; module-level so they pickle by reference) ----

def _lr_frame(source: FrameSource, index: int, scale: int) -> np.ndarray:
    return sensor.area_downsample(_hr_frame(source, index), scale)


@functools.lru_cache(maxsize=2)
def _hr_frame(source: FrameSource, index: int) -> np.ndarray:
    """Source frame ``index`` as intensities, decoded once per worker process: a still is read by
    every chunk and truth task, a video frame by its LR task and the truth frames beside it."""
    frame = to_unit_rgb(source.read(index))
    frame.flags.writeable = False  # shared between tasks
    return frame


def _increments(scene: Scene, pairs: dict | None, frames: range, options: SimulateOptions, dark) -> np.ndarray:
    if scene.is_still:
        image = _hr_frame(scene.source, 0)
        if scene.path is None:  # static: one mosaic, repeated
            mosaic = sensor.cfa_sample(sensor.area_downsample(image, options.scale), options.cfa)
            mosaics = np.broadcast_to(mosaic, (len(frames), *mosaic.shape))
        else:
            mosaics = still_mosaics(image, scene.path, list(frames), options.scale, options.cfa)
    else:
        positions = [source_position(t, options.frames, scene.source.n_frames) for t in frames]
        mosaics = video_mosaics(pairs, positions, scene.source.n_frames, options.cfa)
    return sensor.increments(options.sensor_model(), np.ascontiguousarray(mosaics), frames.start, dark=dark)


def fire_chunk(increments: np.ndarray, state: np.ndarray, reset: str, thresholds) -> sensor.Fired:
    """Task (the job's and ``pipeline.lazy.simulate``'s): a chunk's increments fired on from ``state``."""
    return sensor.fire(increments, state, reset=reset, thresholds=thresholds)


def state_after(fired: sensor.Fired) -> np.ndarray:
    """Task: the integrator's state a chunk leaves, which the next chunk fires on."""
    return fired.state


def _write_spikes(url: str, start: int, fired: sensor.Fired) -> tuple[int, int]:
    hold_point()  # inert unless a fault test asks (pipeline.compute.hold)
    write_region(url, SPIKES, start, fired.packed)
    return fired.packed.shape[0], fired.spikes


def _write_truth(url: str, index: int, scene: Scene, frame: int, options: SimulateOptions,
                 hr_motion: PairMotion | None) -> None:
    if scene.is_still:
        image = _hr_frame(scene.source, 0)
        rgb = image if scene.path is None else render(image, scene.path, frame)
    else:
        i, w = bracket(source_position(frame, options.frames, scene.source.n_frames), scene.source.n_frames)
        frame0 = _hr_frame(scene.source, i)
        frame1 = frame0 if w == 0 else _hr_frame(scene.source, i + 1)
        rgb = between(frame0, frame1, w, hr_motion)
    write_truth(url, index, truth_image(rgb, options.cfa))


def _write_flow(url: str, index: int, path: CameraPath, frame0: int, frame1: int) -> None:
    write_flow(url, index, path.flow(frame0, frame1))


# ---- the graph ----

class _SourcePairs:
    """Futures of LR source frames and their pairs' motion (at LR for the spikes, at HR for the truth),
    made once each and dropped when passed. A pair's HR motion (384 MB at 4000x4000) stays on the
    worker that made it, and Dask runs the pair's truth frames there rather than move it."""

    def __init__(self, client: Client, source: FrameSource, options: SimulateOptions):
        self.client, self.source, self.options = client, source, options
        self.frames, self.motions, self.hr_motions = {}, {}, {}

    def frame(self, i: int):
        if i not in self.frames:
            self.frames[i] = self.client.submit(_lr_frame, self.source, i, self.options.scale)
        return self.frames[i]

    def motion(self, i: int):
        if self.options.interp != "flow":
            return None
        if i not in self.motions:
            self.motions[i] = self.client.submit(estimate_motion, self.frame(i), self.frame(i + 1))
        return self.motions[i]

    def hr_motion(self, i: int):
        if self.options.interp != "flow":
            return None
        if i not in self.hr_motions:
            self.hr_motions[i] = self.client.submit(upscale_motion, self.motion(i), self.options.scale)
        return self.hr_motions[i]

    def for_pairs(self, needed: tuple[int, ...]) -> dict:
        for old in [i for i in self.frames if i < needed[0]]:
            del self.frames[old]
            self.motions.pop(old, None)
            self.hr_motions.pop(old, None)
        return {i: (self.frame(i), self.frame(i + 1), self.motion(i)) for i in needed}


class _Tasks:
    """A simulation's steps as Dask tasks: the sensor's fixed draws made once, the integrator's state
    passed from chunk to chunk (a chain: the bytes do not depend on chunking or workers), a video's
    frames and flows made once each."""

    def __init__(self, client: Client, scene: Scene, options: SimulateOptions, dest: str, height: int, width: int):
        model = options.sensor_model()
        self.client, self.scene, self.options, self.dest = client, scene, options, dest
        self.dark = client.submit(sensor.dark_increments, model, height, width)
        self.thresholds = client.submit(sensor.pixel_thresholds, model, height, width)
        self.state = client.submit(sensor.initial_state, model, height, width)
        self.pairs = None if scene.is_still else _SourcePairs(client, scene.source, options)

    def submit(self, step: Step):
        """The future of the step's write: (frames, spikes) for a spikes chunk, None for truth or flow."""
        submit, scene, options = self.client.submit, self.scene, self.options
        if isinstance(step, SpikeChunk):
            pairs = self.pairs and self.pairs.for_pairs(step.source_frames)
            increments = submit(_increments, scene, pairs, step.frames, options, self.dark)
            fired = submit(fire_chunk, increments, self.state, options.reset, self.thresholds)
            self.state = submit(state_after, fired)
            return submit(_write_spikes, self.dest, step.frames.start, fired)
        if isinstance(step, TruthFrame):
            motion = None
            if self.pairs:  # a video: the HR motion of the pair the frame lies in, unless it is a source frame
                _, w = bracket(source_position(step.frame, options.frames, scene.source.n_frames), scene.source.n_frames)
                motion = self.pairs.hr_motion(step.source_frame) if w else None
            return submit(_write_truth, self.dest, step.index, scene, step.frame, options, motion)
        return submit(_write_flow, self.dest, step.index, scene.path, step.frame0, step.frame1)


def simulate(src: str, dest: str, options: SimulateOptions = SimulateOptions(), *, workers: int | None = None,
             scheduler: str | None = None, progress: bool = True) -> dict:
    """Simulate ``options.frames`` spike frames from ``src`` into a new spike store at ``dest``."""
    check_workers(workers, scheduler)
    check_apart(dest, src)
    check_in_memory((src, dest))  # read and written by the tasks, in worker processes
    source = open_frame_source(src)
    height, width = check_options(options, source)
    path = None
    if options.motion == "random":
        path = CameraPath.random(options.frames, source.height, source.width, seed=options.seed,
                                 speed=options.speed, deform=options.deform)
    scene = Scene(source, path)
    truth_at = output_centres(options.frames, WINDOW, options.truth_every)  # window centres with a full window
    meta = simulated_meta(options, height, width, recorded(src))
    chunk = options.chunk_frames or chunk_frames_for(meta, options.frames)
    check_scheduler(scheduler)  # a named scheduler answers (within seconds) before DEST is claimed or replaced

    with claimed(dest), new_output(dest, overwrite=options.overwrite, kind=SPIKE_STORE), \
            dask_client(workers=workers, scheduler=scheduler) as client:
        writer = SpikeStoreWriter(dest, meta, options.frames, chunk_frames=chunk)
        hr = (options.scale * height, options.scale * width)
        declare_truth(writer, truth_at, hr, options.fps, with_flow=path is not None)
        steps = simulation_steps(options.frames, chunk, truth_at, None if scene.is_still else source.n_frames,
                                 camera_moves=path is not None)
        tasks = _Tasks(client, scene, options, dest, height, width)
        logging.getLogger("cscsr.simulate").debug(  # cscsr --verbose
            "%s -> %s: %d frames of %dx%d LR (x%d HR), cfa %s, chunks of %d frames, truth at %d frames; on the "
            "cluster at %s", src, dest, options.frames, height, width, options.scale, options.cfa, chunk,
            len(truth_at), client.scheduler.address)
        spikes = 0
        with held(dest), progress_bar(f"simulate {src}", options.frames, enabled=progress) as advance:
            for _, future in submitted(client, steps, tasks.submit):
                if (written := future.result()) is not None:  # a spikes chunk: (frames, spikes)
                    advance(written[0])
                    spikes += written[1]
        writer.finish(spike_count=spikes)
        return dict(writer.group.attrs)
