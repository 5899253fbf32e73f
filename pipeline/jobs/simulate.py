"""``cscsr simulate``: an LR Bayer spike recording with HR ground truth (Algorithm 2), on Dask; and its graph, which
``pipeline.lazy`` offers as ``open_frames`` -> ``simulate`` -> ``to_spikes`` (the job's tasks, on one client).

The job checks its options against the source (``pipeline.jobs.simulate_plan``) before anything is made, then writes
the spikes of its scene (:func:`fired_spikes`) into a new store (:func:`write_store`), per time chunk of the output:

    LR mosaics -> increments (parallel over chunks: the costly part, interpolation or warping; a video's LR frames
                              and pair motion a task each, shared by the chunks between them)
      -> fire (a chain: chunk k fires on from the integrator state chunk k - 1 left, exactly)
      -> write (one task per chunk region of ``spikes``, recorded in ``committed``: no two writers share a chunk)

with the sensor's fixed draws (dark current, threshold mismatch, initial state) made once, a task each; then a task
per ground-truth picture (and per flow field for synthetic motion: :func:`made_truth`). The accumulator is an
integer (``stages.simulation.sensor.UNITS`` per threshold) and all noise is keyed by frame index, so the bytes
written do not depend on the chunking or on the number of workers. :func:`write_store` is also ``lazy.to_spikes``'s:
any spikes written as the jobs write a store (claimed, metadata first, a task per run of whole chunks committed as
it is stored, resumable), on the given client or Dask's own scheduler.
"""

import logging
import math
import operator
from typing import TYPE_CHECKING

import numpy as np
from dask.base import tokenize
from dask.highlevelgraph import HighLevelGraph

from pipeline.compute.cluster import check_in_memory, check_scheduler, check_workers, dask_client
from pipeline.jobs.simulate_plan import (SimulateOptions, check_options, hr_pair_motion, open_scene,
                                         simulated_meta)
from pipeline.stores.frame_sources import open_frame_source
from pipeline.stores.ground_truth import write_flow, write_truth
from pipeline.stores.outputs import SPIKE_STORE, check_existing
from pipeline.stores.spike_store import chunk_frames_for
from pipeline.stores.spike_writes import SpikesIncomplete, SpikeWrites, Truth, write_store
from pipeline.stores.storage import check_apart, recorded
from stages.capture.bits import unpacked_bits
from stages.errors import InputError, describe
from stages.reconstruction.methods import WINDOW, output_centres
from stages.simulation import sensor
from stages.simulation.intensities import to_unit_rgb
from stages.simulation.latent import truth_image

if TYPE_CHECKING:  # dask.array imports xarray, pandas and SciPy: never in the workers that run these tasks
    import dask.array as da

BLOCK_BYTES = 64 * 2**20  # scene frames a block unless chunk_frames says otherwise: about this many bytes, at least one


def simulate(src: str, dest: str, options: SimulateOptions = SimulateOptions(), *, workers: int | None = None,
             scheduler: str | None = None, progress: bool = True) -> dict:
    """Simulate ``options.frames`` spike frames from ``src`` into a new spike store at ``dest``; -> its attributes."""
    check_workers(workers, scheduler)
    check_apart(dest, src)
    check_in_memory((src, dest))  # read and written by the tasks, in worker processes
    source = open_frame_source(src)
    height, width = check_options(options, source)
    meta = simulated_meta(options, height, width, recorded(src))
    chunk = options.chunk_frames or chunk_frames_for(meta, options.frames)
    check_existing(dest, overwrite=options.overwrite, kind=SPIKE_STORE, flag="--overwrite")
    check_scheduler(scheduler)  # a named scheduler answers (within seconds) before DEST is claimed or replaced
    scene = open_scene(source, frames=options.frames, motion=options.motion, seed=options.seed, speed=options.speed,
                       deform=options.deform, interp=options.interp, scale=options.scale)
    bits = fired_spikes(frames_array(scene, chunk), options, height, width, scene)
    truth = made_truth(scene, output_centres(options.frames, WINDOW, options.truth_every), recorded(dest),
                       options.cfa)  # written by tasks, in workers of any working folder
    on = scheduler or f"a local cluster ({workers or 'a worker per core'} workers)"
    logging.getLogger("cscsr.simulate").debug(  # cscsr --verbose
        "%s -> %s: %d frames of %dx%d LR (x%d HR), cfa %s, chunks of %d frames; on %s", src, dest, options.frames,
        height, width, options.scale, options.cfa, chunk, on)
    try:
        written = write_store(SpikeWrites(dest, meta, options.frames, chunk, None), bits,
                              client=lambda: dask_client(workers=workers, scheduler=scheduler),
                              overwrite=options.overwrite, resume=False, truth=truth, progress=progress,
                              title=f"simulate {src}", keep_partial=False, flag="--overwrite")
    except SpikesIncomplete as error:  # the store is gone (a job is not resumed): the cause alone, if it is bad input
        if isinstance(error.__cause__, InputError):  # a frame of another size found as it is read, ...
            raise InputError(str(error.__cause__)) from None
        raise SpikesIncomplete(f"simulate {dest}: {describe(error.__cause__)}: the unfinished store was removed (a "
                               f"simulation is not resumed): fix the cause and run it again") from error.__cause__
    return written["attrs"]


# ---- the graph: a scene's spikes and truth ----

def frames_array(scene, chunk_frames: int | None) -> "da.Array":
    """A scene (``pipeline.jobs.simulate_plan``) as a dask array of its HR frames (t, y, x, rgb), ``chunk_frames``
    frames a block (default: about :data:`BLOCK_BYTES`)."""
    import dask.array as da

    frame_bytes = scene.dtype.itemsize * math.prod(scene.shape[1:])
    chunk = min(chunk_frames or max(1, BLOCK_BYTES // frame_bytes), scene.shape[0])
    return da.from_array(scene, chunks=(chunk, -1, -1, -1), asarray=False, fancy=False,
                         meta=np.empty((0, 0, 0, 0), scene.dtype), name=f"frames-{tokenize(scene, chunk)}")


def fired_spikes(scene: "da.Array", options: SimulateOptions, height: int, width: int, made) -> "da.Array":
    """The graph: ``scene`` (t, s*H, s*W, c), whole frames per block -> spikes (t, H, W) bool, block k fired on from
    the integrator state block k - 1 left (module docstring). ``made``: the job's scene ``scene`` reads
    (``simulate_plan.open_scene``: a picture under camera motion, a video over the spike frames; else None), whose
    blocks make their LR mosaics themselves, as the simulator always has: a video's from its pairs' LR frames and
    motion, each made once (a task each, shared by the blocks between them)."""
    import dask.array as da

    token = tokenize(scene.name, scene.chunks[0], options)  # blocks of other lengths are other keys
    name = f"simulated-spikes-{token}"
    model = options.sensor_model()
    dark, thresholds, state = (f"{name}-dark", f"{name}-thresholds", f"{name}-initial-state")
    layer = {dark: (sensor.dark_increments, model, height, width),
             thresholds: (sensor.pixel_thresholds, model, height, width),
             state: (sensor.initial_state, model, height, width)}
    first_frame = 0
    for k, n_frames in enumerate(scene.chunks[0]):
        increments, fired, packed = (f"{name}-increments", k), (f"{name}-fired", k), (f"{name}-packed", k)
        if made is None:
            layer[increments] = (_increments, (scene.name, k, 0, 0, 0), first_frame, options, dark)
        else:
            frames = range(first_frame, first_frame + n_frames)
            pairs = [[i, *_pair_keys(layer, made, i, f"{name}-source")] for i in made.pairs(frames)]
            layer[increments] = (_made_increments, made, pairs, frames, options, dark)
        layer[fired] = (fire_chunk, increments, state, options.reset, thresholds)
        state = (f"{name}-state", k)  # what block k + 1 fires on
        layer[state] = (state_after, fired)
        layer[packed] = (operator.attrgetter("packed"), fired)  # spike_writes.packed_key: written as it is
        layer[(name, k, 0, 0)] = (unpacked_bits, packed, width)
        first_frame += n_frames
    graph = HighLevelGraph.from_collections(name, layer, dependencies=[] if made else [scene])
    return da.Array(graph, name, chunks=(scene.chunks[0], (height,), (width,)), meta=np.empty((0, 0, 0), bool))


def _pair_keys(layer: dict, made, i: int, prefix: str) -> tuple:
    """The keys of pair ``i``'s LR frames and motion at LR (a task each, added to ``layer`` once)."""
    lr0, lr1, motion = (f"{prefix}-lr", i), (f"{prefix}-lr", i + 1), (f"{prefix}-motion", i)
    for key, index in ((lr0, i), (lr1, i + 1)):
        layer.setdefault(key, (made.lr_frame, index))
    layer.setdefault(motion, (made.motion, lr0, lr1))
    return lr0, lr1, motion


def _made_increments(made, pairs: list, frames: range, options: SimulateOptions, dark: np.ndarray | None) -> np.ndarray:
    """Task: the increments (n, H, W) int32 of spike frames ``frames`` of the job's scene ``made``, from its
    LR mosaics as the ``simulate`` job makes them; ``pairs``: [i, LR frame i, LR frame i + 1, their motion]."""
    mosaics = made.mosaics(frames, options.scale, options.cfa, {i: tuple(pair) for i, *pair in pairs})
    return sensor.increments(options.sensor_model(), np.ascontiguousarray(mosaics), frames.start, dark=dark)


def fire_chunk(increments: np.ndarray, state: np.ndarray, reset: str, thresholds) -> sensor.Fired:
    """Task: a chunk's increments fired on from ``state``."""
    return sensor.fire(increments, state, reset=reset, thresholds=thresholds)


def state_after(fired: sensor.Fired) -> np.ndarray:
    """Task: the integrator's state a chunk leaves, which the next chunk fires on."""
    return fired.state


def _increments(frames: np.ndarray, first_frame: int, options: SimulateOptions, dark: np.ndarray | None) -> np.ndarray:
    """Task: scene frames (n, s*H, s*W, c) of spike frames ``first_frame``.. -> their increments (n, H, W) int32,
    through the job's stages: intensities, area downsampling, the colour filter, the sensor's gain and noise."""
    check_intensities(frames, first_frame)
    n_frames, hr_height, hr_width = frames.shape[:3]
    mosaics = np.empty((n_frames, hr_height // options.scale, hr_width // options.scale), np.float32)
    for i, frame in enumerate(frames):
        mosaics[i] = sensor.cfa_sample(sensor.area_downsample(to_unit_rgb(frame), options.scale), options.cfa)
    return sensor.increments(options.sensor_model(), mosaics, first_frame, dark=dark)


def check_intensities(frames: np.ndarray, first_frame: int) -> None:
    """Refuse, in one line, float scene frames (spike frames ``first_frame``..) that are not intensities in [0, 1]:
    NaN, inf, negatives, or a scene of 0..255 given as floats (clipping would make it white)."""
    if not np.issubdtype(frames.dtype, np.floating) or frames.size == 0:
        return
    ok = np.isfinite(frames) & (frames >= 0) & (frames <= 1)  # one pass: NaN compares false
    if not ok.all():
        bad = int(np.argmin(ok.reshape(len(frames), -1).all(1)))  # the first frame holding a value out of [0, 1]
        values = frames[bad][~ok[bad]]
        raise InputError(f"frames: scene frame {first_frame + bad} holds {values.flat[0]!r} (float frames are "
                         f"intensities in [0, 1], never clipped: divide a 0..255 scene by 255, or give it as uint8)")


def made_truth(made, centres: list[int], url: str, cfa: str) -> Truth:
    """The truth of a scene (``pipeline.jobs.simulate_plan``: a picture under camera motion, a video over the spike
    frames) at ``centres``, written into the store at ``url`` as the job writes it: a task a picture (a video's pair
    motion made once, upscaled), and the camera path's exact flow from each to the next."""
    name = f"truth-{tokenize(made, url, centres, cfa)}"
    graph, keys = {}, []
    path = getattr(made, "path", None)
    for k, frame in enumerate(centres):
        motion = None
        if getattr(made, "interp", None) == "flow":  # a video's: the HR motion of its pair, made once
            i, w = made.pair(frame)
            if 0 < w < 1:
                motion = (f"{name}-hr-motion", i)
                graph.setdefault(motion, (hr_pair_motion, made, _pair_keys(graph, made, i, name)[2]))
        keys.append((name, k))
        graph[keys[-1]] = (_write_made_truth, url, k, made, frame, cfa, motion)
        if path is not None and k + 1 < len(centres):
            keys.append((f"{name}-flow", k))
            graph[keys[-1]] = (_write_flow, url, k, path, frame, centres[k + 1])
    return Truth(centres, made.shape[1:3], path is not None, graph, keys)


def _write_made_truth(url: str, k: int, made, frame: int, cfa: str, hr_motion) -> None:
    """Task: truth picture ``k``, drawn from spike frame ``frame`` of the job's scene ``made``."""
    write_truth(url, k, truth_image(made.intensities(frame, hr_motion), cfa))


def _write_flow(url: str, k: int, path, frame0: int, frame1: int) -> None:
    """Task: the camera path's exact flow from truth picture ``k`` (spike frame ``frame0``) to the next."""
    write_flow(url, k, path.flow(frame0, frame1))
