"""Lazy simulation (``cscsr.lazy``, issue #45): HR scene frames -> lazy spikes (:func:`simulate`), and lazy spikes
-> a spike store (:func:`to_spikes`).

:func:`simulate` computes nothing: it returns the spikes of the ``simulate`` job as a dask graph, per time chunk of
the frames

    frames -> mosaics -> increments (parallel over chunks)
      -> fire (a chain: chunk k fires on from the integrator state chunk k - 1 left, exactly)
      -> unpacked spikes (one block of the output)

with the sensor's fixed draws (dark current, threshold mismatch, initial state) made once, one task each. The
accumulator is an integer and every noise draw is keyed by frame index (``stages.simulation.sensor``), so the spikes are the
job's bytes whatever the chunking. :func:`to_spikes` writes spikes (from :func:`simulate`,
``pipeline.lazy.spikes.open_spikes`` or any stage that keeps the convention) as the jobs write a store: claimed,
metadata first, then one task per run of whole chunks, each recorded in ``committed`` once stored, so a failed
run is resumed (``resume=True``) where it stopped; on the active scheduler (a ``distributed.Client`` if one is
active, else Dask's default).
"""

import dataclasses
import json
import operator
import uuid

import dask.array as da
import dask.threaded
import numpy as np
import xarray as xr
import zarr
from dask.base import get_scheduler, tokenize
from dask.callbacks import Callback
from dask.highlevelgraph import HighLevelGraph

from pipeline.stores.frame_sources import FrameSource
from pipeline.compute.executor import released
from pipeline.compute.hold import hold_point
from pipeline.compute.progress import progress_bar
from pipeline.jobs.ingest import (COMMITTED_UNITS, IngestPlan, check_same_capture, ingest_task, run_tasks,
                                  task_frames_for)
from pipeline.lazy.capture import capture_frames, check_unchanged
from pipeline.lazy.spikes import (as_spikes, check_here, check_spikes, distributed_client, python_words, selection,
                                  unpacked_bits, url_text)
from pipeline.stores.lease import check_free, claimed, held
from pipeline.stores.outputs import SPIKE_STORE, check_existing, new_output
from pipeline.jobs.simulate import MOTIONS, SimulateOptions, check_options, fire_chunk, simulated_meta, state_after
from pipeline.stores.spike_store import (COMMITTED, SPIKES, SpikeMeta, SpikeStore, SpikeStoreWriter,
                                  chunk_frames_for, open_spike_store, write_region)
from pipeline.stores.ground_truth import declare_truth, has_truth, write_truth
from pipeline.stores.storage import check_apart, exists, recorded
from stages.simulation import sensor
from stages.capture.bits import count_spikes, pack_rows, packed_width
from stages.errors import InputError, InputTypeError, describe
from stages.reconstruction.methods import WINDOW, output_centres
from stages.simulation.intensities import to_unit_rgb
from stages.simulation.latent import truth_image
from stages.numbers import check_flag, check_number

FRAME_DIMS = ("t", "y", "x", "rgb")  # HR scene frames: one per spike frame
CHANNELS = (1, 3, 4)  # grey, RGB, RGBA: what stages.simulation.intensities.to_unit_rgb takes
READ_FROM = "store"  # the attribute naming the store lazy spikes were read from (lazy_spikes.open_spikes): not recorded
RESUME_FLAG = "resume=True or overwrite=True"  # how a caller finishes or replaces an existing store (as ingest says it)


# ---- simulate ----

def simulate(frames: xr.DataArray, *, scale: int = 4, cfa: str = "rggb", brightness: float = 0.6,
             threshold: float = 1.0, seed: int = 0, noise: str = "none", reset: str = "zero",
             fps: float = 20000.0) -> xr.DataArray:
    """HR scene frames ``(t, s*H, s*W, rgb)`` (uint8, uint16 or float in [0, 1]; grey, RGB or RGBA) -> lazy spikes
    ``(t, H, W)`` bool, one spike frame per scene frame, chunked along ``t`` as ``frames`` is; nothing computed.

    The bytes of ``cscsr simulate --interp linear`` on a video of as many frames as it simulates (spike frame ``t``
    is then scene frame ``t``), or on a picture under ``--motion`` (``lazy.open_frames``), with the same options;
    the attributes it records (``source`` and ``motion``: the frames' own attributes, else "" and "video").
    Refuses, in one line and before any graph exists, what the job refuses (``pipeline.jobs.simulate.check_options``)
    and frames of other dims or dtype; float frames must hold intensities in [0, 1] (a scene of 0..255 as floats,
    NaN, inf or negatives are refused: before the graph for frames in memory, when their block is computed for
    lazy ones, never clipped).

    ``reset`` defaults to ``zero``, the ``simulate`` job's default (``cscsr simulate``), so that the same options
    give the job's bytes; ``ingest`` records ``subtract`` by default because that is how the real camera resets.
    Give ``reset="subtract"`` to simulate that camera.
    """
    n_frames, hr_height, hr_width, _ = _checked_frames(frames).shape
    options = SimulateOptions(scale=scale, cfa=cfa, brightness=brightness, threshold=threshold, frames=n_frames,
                              seed=seed, noise=noise, reset=reset, interp="linear", fps=fps)
    # the job's checks; of its source they read the frame count and size only
    with python_words():
        height, width = check_options(options, FrameSource("frames", "array", n_frames, hr_height, hr_width))
    source, motion = frames.attrs.get("source"), frames.attrs.get("motion")
    if motion == "random":  # lazy.open_frames of a picture along a camera path: the job's scene, as recorded
        _check_camera_path(frames.attrs, seed, n_frames)
    made = dataclasses.replace(options, motion=motion if motion in MOTIONS else None)
    meta = simulated_meta(made, height, width, source if isinstance(source, str) else "")
    scene = frames.data
    if not isinstance(scene, da.Array):  # in memory: checked now, then chunks of Dask's size, whole frames
        check_intensities(np.asarray(scene), 0)
        scene = da.from_array(scene, chunks=("auto", -1, -1, -1))
    scene = scene.rechunk({1: -1, 2: -1, 3: -1})  # whole frames per block
    return as_spikes(_fired_spikes(scene, options, height, width), {**meta.attrs(), "frames": n_frames})


def _check_camera_path(attrs: dict, seed: int, n_frames: int) -> None:
    """Refuse, in one line, to record as the ``simulate`` job's a scene along a camera path it would not make: one
    of another seed (the job's one ``--seed`` draws both path and noise) or a part of a longer path (the job's path
    spans its ``--frames``)."""
    if attrs.get("seed") != seed:
        raise InputError(f"frames follow the camera path of seed {attrs.get('seed')} (open_frames(seed=...)), but "
                         f"simulate(seed={seed}): give the same seed, as cscsr simulate's one --seed draws both")
    if attrs.get("frames") != n_frames:
        raise InputError(f"frames are {n_frames} of a camera path of {attrs.get('frames')} frames: the job's path of "
                         f"{n_frames} frames is open_frames(..., frames={n_frames})")


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


def _checked_frames(frames) -> xr.DataArray:
    """``frames`` if they are HR scene frames :func:`simulate` takes, else one line naming what is wrong."""
    if not isinstance(frames, xr.DataArray):
        raise InputTypeError(f"frames must be an xarray.DataArray of HR scene frames with dims {FRAME_DIMS}, got "
                             f"{type(frames).__name__}")
    if frames.dims != FRAME_DIMS:
        raise InputError(f"frames must have dims {FRAME_DIMS} (time, HR rows, HR columns, colour), got {frames.dims}")
    if not (np.issubdtype(frames.dtype, np.unsignedinteger) or np.issubdtype(frames.dtype, np.floating)):
        raise InputError(f"frames must be unsigned integers (uint8, uint16: 0 to their maximum) or floats in [0, 1], "
                         f"got {frames.dtype}")
    if frames.sizes["rgb"] not in CHANNELS:
        raise InputError(f"frames must be grey, RGB or RGBA: rgb of size 1, 3 or 4, got {frames.sizes['rgb']}")
    return frames


def _fired_spikes(scene: da.Array, options: SimulateOptions, height: int, width: int) -> da.Array:
    """The graph: ``scene`` (t, s*H, s*W, c), whole frames per block -> spikes (t, H, W) bool, block k fired on from
    the integrator state block k - 1 left (module docstring)."""
    token = tokenize(scene.name, options)
    name = f"simulated-spikes-{token}"
    model = options.sensor_model()
    dark, thresholds, state = (f"{name}-dark", f"{name}-thresholds", f"{name}-initial-state")
    layer = {dark: (sensor.dark_increments, model, height, width),
             thresholds: (sensor.pixel_thresholds, model, height, width),
             state: (sensor.initial_state, model, height, width)}
    first_frame = 0
    for k, n_frames in enumerate(scene.chunks[0]):
        increments, fired = (f"{name}-increments", k), (f"{name}-fired", k)
        layer[increments] = (_increments, (scene.name, k, 0, 0, 0), first_frame, options, dark)
        layer[fired] = (fire_chunk, increments, state, options.reset, thresholds)
        state = (f"{name}-state", k)  # what block k + 1 fires on
        layer[state] = (state_after, fired)
        layer[(name, k, 0, 0)] = (unpacked_bits, (operator.attrgetter("packed"), fired), width)
        first_frame += n_frames
    graph = HighLevelGraph.from_collections(name, layer, dependencies=[scene])
    return da.Array(graph, name, chunks=(scene.chunks[0], (height,), (width,)), meta=np.empty((0, 0, 0), bool))


def _increments(frames: np.ndarray, first_frame: int, options: SimulateOptions, dark: np.ndarray | None) -> np.ndarray:
    """Task: scene frames (n, s*H, s*W, c) of spike frames ``first_frame``.. -> their increments (n, H, W) int32,
    through the job's stages: intensities, area downsampling, the colour filter, the sensor's gain and noise."""
    check_intensities(frames, first_frame)
    n_frames, hr_height, hr_width = frames.shape[:3]
    mosaics = np.empty((n_frames, hr_height // options.scale, hr_width // options.scale), np.float32)
    for i, frame in enumerate(frames):
        mosaics[i] = sensor.cfa_sample(sensor.area_downsample(to_unit_rgb(frame), options.scale), options.cfa)
    return sensor.increments(options.sensor_model(), mosaics, first_frame, dark=dark)


# ---- to_spikes ----

class SpikesIncomplete(RuntimeError):
    """Some :func:`to_spikes` tasks failed: the others are committed in the store, for ``resume=True``."""


def to_spikes(spikes: xr.DataArray, url: str, *, chunk_frames: int | None = None, task_frames: int | None = None,
              overwrite: bool = False, resume: bool = False, truth: xr.DataArray | None = None,
              progress: bool = False) -> dict:
    """Write lazy ``spikes`` (t, y, x) bool (the convention of ``pipeline.lazy.spikes``) into a new spike store at
    ``url``, computed on the active scheduler; -> ``attrs`` (the store's final attributes), ``frames``, ``spikes``
    (their count), ``tasks``, ``tasks_run``, ``tasks_skipped``.

    The store records ``spikes.attrs`` (the recording's settings: ``pipeline.stores.spike_store.SpikeMeta``) and is chunked
    by ``chunk_frames`` frames (default: about 4 MiB packed). Each task packs and writes ``task_frames`` frames (whole
    chunks; default: one chunk) and records them in ``committed``. Spikes of ``lazy.open_capture``, as it made them,
    are written by ``cscsr ingest``'s own tasks (each reads its frames packed by one byte range: no unpacked bits
    made or moved), on a client through the job's executor, and the store records the capture as ingest records
    it (its size and a SHA-256 of its ends, how it was read), so either finishes the other's store. A failed run
    raises :class:`SpikesIncomplete` and keeps what it committed; ``resume=True`` runs only the tasks not
    committed, cut as the store was (it refuses a store of other attributes, frame count or chunking, and a
    capture's store resumed from another capture; that other spikes are the same data is the caller's word).
    Everything is checked, in one line, before anything is written. ``progress=True``: a bar of the frames written
    on standard error (on a client or on dask's own scheduler).

    ``truth``: the HR scene frames the spikes were simulated from (:func:`simulate`'s ``frames``), written as the
    ``simulate`` job writes its ground truth (``pipeline.stores.ground_truth``: the picture at each 41-frame window
    centre, every ``truth_every`` frames), after the spikes and before the store is complete, so that ``cscsr
    evaluate`` scores reconstructions of it. A resume of a store written with truth needs it again.
    """
    url = url_text(url)
    check_flag("progress", progress)
    plan = _ToSpikes.checked(spikes, url, chunk_frames, task_frames, overwrite, resume)
    centres = _checked_truth(truth, spikes, url, plan.resumed)
    with claimed(url):  # one job per store, taken atomically before the store is touched
        if resume:
            check_free(url)  # and no live lease (a job on a machine that shares no claim file with us)
        with new_output(url, overwrite=overwrite, kind=SPIKE_STORE, flag=RESUME_FLAG, resume=resume,
                        keep_partial=True):
            if resume:
                counts = plan.resumable()  # again, under the claim
                writer = SpikeStoreWriter.reopened(url)
            else:
                writer = SpikeStoreWriter(url, plan.meta, plan.n_frames, chunk_frames=plan.chunk)
                writer.add_array(COMMITTED, (plan.n_tasks,), (1,), np.int64, ("task",),
                                 {"units": COMMITTED_UNITS, "task_frames": plan.task_frames, **plan.record},
                                 fill_value=-1)
                counts = np.full(plan.n_tasks, -1, np.int64)
                if truth is not None:
                    meta = plan.meta
                    declare_truth(writer, centres, truth.shape[1:3], float(meta.fps), with_flow=False)
            todo = [index for index in range(plan.n_tasks) if counts[index] < 0]
            if todo:
                to_write = sum(plan.frames_of(index) for index in todo)
                with held(url), progress_bar(f"to_spikes {url}", to_write, enabled=progress) as advance:
                    counts[todo] = (plan.run(spikes.data, todo, advance) if plan.capture is None
                                    else plan.run_ingest(todo, distributed_client(spikes.data), advance))
            if truth is not None and writer.group.attrs.get("state") != "complete":
                with held(url):
                    _write_truths(truth, centres, url, spikes.attrs["cfa"])
            if writer.group.attrs.get("state") != "complete":
                writer.finish(spike_count=int(counts.sum()))
    return {"attrs": dict(writer.group.attrs), "frames": plan.n_frames, "spikes": int(counts.sum()),
            "tasks": plan.n_tasks, "tasks_run": len(todo), "tasks_skipped": plan.n_tasks - len(todo)}


def _checked_truth(truth, spikes: xr.DataArray, url: str, resumed: SpikeStore | None) -> list[int]:
    """The truth's centres (the ``simulate`` job's: ``output_centres(frames, WINDOW, truth_every)``) if ``truth`` is
    the HR scene of ``spikes`` (one frame per spike frame, ``scale`` times its pixels), else one line; and a resume
    (``resumed``: the store to finish, as the checks opened it; None for a new store) must give truth exactly where
    the store was begun with it."""
    if resumed is not None:
        has = has_truth(resumed.group)
        if has != (truth is not None):
            raise InputError(f"cannot resume {url}: it was begun {'with' if has else 'without'} truth=: "
                             f"{'give the same scene frames' if has else 'leave truth out'}")
    if truth is None:
        return []
    frames = _checked_frames(truth).shape
    scale = spikes.attrs.get("scale")
    if not isinstance(scale, int) or "truth_every" not in spikes.attrs:
        raise InputError("truth= is for simulated spikes (lazy.simulate: their scale and truth_every say where the "
                         "truth goes); these spikes record none")
    n, height, width = spikes.shape
    if frames[:3] != (n, scale * height, scale * width):
        raise InputError(f"truth= must be the scene the spikes were simulated from, ({n}, {scale * height}, "
                         f"{scale * width}, rgb) at scale {scale}, got {frames}")
    centres = output_centres(n, WINDOW, int(spikes.attrs["truth_every"]))
    if not centres:
        raise InputError(f"truth=: {n} frames hold no {WINDOW}-frame window centre to draw the truth at")
    return centres


def _write_truths(truth: xr.DataArray, centres: list[int], url: str, cfa: str) -> None:
    """Write the truth at each centre (one task per picture, on the active scheduler): the simulate job's
    ``truth_image`` of the scene frame there."""
    scene = truth.data if isinstance(truth.data, da.Array) else da.from_array(truth.data, chunks=(1, -1, -1, -1))
    picked = scene[np.asarray(centres)].rechunk((1, -1, -1, -1))
    written = picked.map_blocks(_write_truth_block, url, cfa, tuple(centres), drop_axis=(1, 2, 3), chunks=((1,) * len(centres),),
                                dtype=np.int64, meta=np.empty((0,), np.int64), name=f"truth-{tokenize(picked.name, url)}")
    written.compute()


def _write_truth_block(frame: np.ndarray, url: str, cfa: str, centres: tuple[int, ...], block_info=None) -> np.ndarray:
    """Task: truth picture ``k`` (the block's place) from its scene frame (1, s*H, s*W, c), spike frame centres[k]."""
    k = block_info[0]["chunk-location"][0]
    check_intensities(frame, centres[k])
    write_truth(url, k, truth_image(to_unit_rgb(frame[0]), cfa))
    return np.ones(1, np.int64)


class _ToSpikes:
    """A :func:`to_spikes` checked and cut into tasks, before anything is written: the store's chunks of ``chunk``
    frames, task ``i`` its frames ``[i * task_frames, (i + 1) * task_frames)``; ``resumed``: the store to finish
    (``resume``) as these checks opened it, before the claim, else None."""

    def __init__(self, url: str, meta: SpikeMeta, n_frames: int, chunk_frames: int | None, task_frames: int | None):
        self.url, self.meta, self.n_frames = url, meta, n_frames
        # as the caller gave them (None: the default, or the store's cut), at most the whole recording
        chunk_frames, task_frames = (None if n is None else min(n, n_frames) for n in (chunk_frames, task_frames))
        self.asked = (chunk_frames, task_frames)
        self.resumed: SpikeStore | None = None
        self.capture = None  # lazy.open_capture's reader, when the spikes are all a capture's frames as it made them
        self.record: dict = {}  # then what the store records of the capture (ingest.capture_record)
        self.cut(chunk_frames or chunk_frames_for(meta, n_frames), task_frames)

    def cut(self, chunk: int, task_frames: int | None) -> None:
        """Chunks of ``chunk`` frames, tasks of ``task_frames`` rounded up to whole chunks (None: one chunk)."""
        self.chunk = chunk
        frame_bytes = self.meta.height * packed_width(self.meta.width)
        self.task_frames = task_frames_for(chunk, frame_bytes, task_frames or chunk)
        self.n_tasks = -(-self.n_frames // self.task_frames)

    def frames_of(self, index: int) -> int:
        """How many frames task ``index`` writes (the last may hold fewer)."""
        return min(self.task_frames, self.n_frames - index * self.task_frames)

    @classmethod
    def checked(cls, spikes, url, chunk_frames, task_frames, overwrite, resume) -> "_ToSpikes":
        """Every check of the arguments, the output and (``resume``) the store to finish; reads, never writes."""
        check_spikes(spikes)
        chosen = selection(spikes)  # a run of frames (one rate, one time base), steps and repeats refused
        if chosen.box != (0, chosen.shape[1], 0, chosen.shape[2]):
            y0, y1, x0, x1 = chosen.box
            raise InputError(f"spikes are a selection of pixels (y {y0}:{y1}, x {x0}:{x1} of the recording's "
                             f"{chosen.shape[1]}x{chosen.shape[2]}): to_spikes writes whole frames (a crop's colour "
                             f"phase and place would be lost); a crop is reconstructed as it is, by lazy.windows")
        check_flag("overwrite", overwrite)
        check_flag("resume", resume)
        for label, value in (("chunk_frames", chunk_frames), ("task_frames", task_frames)):
            if value is not None:
                check_number(label, value, at_least=1, integer=True)
        if resume and overwrite:
            raise InputError("resume=True and overwrite=True contradict each other: choose one")
        n_frames, height, width = spikes.shape
        if n_frames == 0:
            raise InputError("spikes hold no frames: a spike store records at least one")
        try:  # a store's count, state and identity are dropped as that store's own
            meta = SpikeMeta.from_attrs({k: v for k, v in spikes.attrs.items() if k != READ_FROM})
        except InputError as error:
            raise InputError(f"spikes: {error}") from None
        if (meta.height, meta.width) != (height, width):
            raise InputError(f"spikes are {height}x{width} pixels, but their attributes record "
                             f"{meta.height}x{meta.width}: keep the attrs of the spikes they were computed from")
        # never over the store they are read from, nor what that was made from
        check_apart(url, *(place for name in (READ_FROM, "source") if isinstance(place := spikes.attrs.get(name), str)))
        check_here([url], spikes.data)  # a memory:// store is this process's alone
        if resume and not exists(url):
            raise InputError(f"cannot resume: {url} does not exist")
        if not resume:
            check_existing(url, overwrite=overwrite, kind=SPIKE_STORE, flag=RESUME_FLAG)
        plan = cls(url, meta, n_frames, chunk_frames, task_frames)
        if (frames := capture_frames(spikes.data)) is not None:  # written by ingest's tasks, recorded as it records
            check_unchanged(frames)  # the capture as it is now is the one its record describes
            plan.capture, plan.record = frames, json.loads(frames.record)
        if resume:  # opened once for the checks before the claim: its cut here, its truth by _checked_truth
            plan.resumed = open_spike_store(url, allow_incomplete=True)
            plan.resumable(plan.resumed)
        return plan

    def resumable(self, store: SpikeStore | None = None) -> np.ndarray:
        """Cut as the unfinished store at ``url`` was (a cut the caller gives must be that one); refuse a store of
        other attributes or frames; -> the spike counts of its tasks (-1: not committed). ``store``: the store at
        ``url`` as the caller opened it, else opened now (under the claim: as it is then). Reads, never writes."""
        if store is None:
            store = open_spike_store(self.url, allow_incomplete=True)  # a video store, a folder, ...: refused by name
        committed = store.group[COMMITTED] if COMMITTED in store.group else None
        if not isinstance(committed, zarr.Array):
            raise InputError(f"cannot resume {self.url}: it holds no record of its tasks (a store written by a job "
                             f"that records none): write it again with overwrite=True")
        was, now = store.meta.attrs(), self.meta.attrs()
        if changed := [f"{k} {was.get(k)!r} -> {now.get(k)!r}" for k in sorted(was | now) if was.get(k) != now.get(k)]:
            raise InputError(f"cannot resume {self.url}: it records other attributes ({', '.join(changed)}): give "
                             f"the spikes it was written from, or write it again with overwrite=True")
        if self.record:  # the capture it was written from, read as it was (what ingest --resume checks)
            check_same_capture(self.url, self.capture.url, dict(committed.attrs), self.record, again="overwrite=True")
        asked_chunk, asked_task = self.asked
        recorded_task = committed.attrs.get("task_frames")
        recorded_ok = isinstance(recorded_task, int) and not isinstance(recorded_task, bool) and recorded_task > 0
        self.cut(store.spikes.chunks[0], asked_task or (recorded_task if recorded_ok else None))
        if (store.n_frames != self.n_frames or asked_chunk not in (None, self.chunk) or not recorded_ok
                or self.task_frames != recorded_task or committed.shape != (self.n_tasks,)):
            raise InputError(f"cannot resume {self.url}: it holds {store.n_frames} frames in chunks of {self.chunk}, "
                             f"{committed.shape[0]} tasks of {recorded_task} frames; these spikes: {self.n_frames} "
                             f"frames{'' if asked_chunk is None else f', chunk_frames={asked_chunk}'}"
                             f"{'' if asked_task is None else f', task_frames={asked_task}'}: give those, or write "
                             f"it again with overwrite=True")
        return committed[:].astype(np.int64)

    def run(self, bits: da.Array, todo: list[int], advance) -> np.ndarray:
        """Tasks ``todo`` of ``bits`` (t, y, x) bool on the active scheduler, ``advance(frames)`` as each is written;
        -> their spike counts. Raises :class:`SpikesIncomplete` if any fails (what the others committed stays)."""
        blocks = bits.rechunk((self.task_frames, -1, -1))
        name = f"to-spikes-{tokenize(blocks.name, self.url, todo)}"
        layer = {(name, j): (_write_task, (blocks.name, index, 0, 0), self.url, index * self.task_frames, index)
                 for j, index in enumerate(todo)}
        graph = HighLevelGraph.from_collections(name, layer, dependencies=[blocks])
        frames = {(name, j): self.frames_of(index) for j, index in enumerate(todo)}
        try:
            return np.concatenate(_computed(graph, frames, advance, distributed_client(bits)))
        except Exception as error:
            store = open_spike_store(self.url, allow_incomplete=True)
            done = int((store.group[COMMITTED][:] >= 0).sum())
            raise SpikesIncomplete(f"to_spikes {self.url}: {done} of {self.n_tasks} tasks committed, the others not "
                                   f"({describe(error)}): fix the cause and call to_spikes again with "
                                   f"resume=True") from error

    def run_ingest(self, todo: list[int], client, advance) -> np.ndarray:
        """Tasks ``todo`` of the capture (:attr:`capture`, ``lazy.open_capture``'s reader) as ``cscsr ingest`` runs
        them (``pipeline.jobs.ingest``: each reads its frames by one byte range and writes them packed, so no unpacked
        bits are made or moved), on ``client`` through its executor, else on dask's own scheduler; -> their spike
        counts. Raises :class:`SpikesIncomplete` if any fails or finds the capture damaged."""
        frames = self.capture
        plan = IngestPlan(frames.url, recorded(self.url), frames.height, frames.width, frames.flip,
                          frames.head_columns, None, frames.n_frames, self.task_frames, uuid.uuid4().hex, frames.layout)
        if client is not None:
            outcomes = {}
            for outcome in run_tasks(client, todo, plan=plan):
                outcomes[outcome.index] = outcome.spikes if outcome.error is None else outcome.error
                if outcome.error is None:
                    advance(self.frames_of(outcome.index))
        else:
            tasks = dict(ingest_task(plan, index) for index in todo)
            try:
                done = _computed(tasks, {key: self.frames_of(index) for key, index in zip(tasks, todo)}, advance, None)
            except Exception as error:  # noqa: BLE001 - every failure is said, as plan.run says it
                done = [describe(error)] * len(todo)
            outcomes = dict(zip(todo, done))
        if failed := [why for why in outcomes.values() if isinstance(why, str)]:
            committed = int((open_spike_store(self.url, allow_incomplete=True).group[COMMITTED][:] >= 0).sum())
            raise SpikesIncomplete(f"to_spikes {self.url}: {committed} of {self.n_tasks} tasks committed, the others "
                                   f"not ({failed[0]}): fix the cause and call to_spikes again with resume=True")
        return np.array([outcomes[index] for index in todo], np.int64)


def _computed(graph, frames: dict, advance, client) -> list:
    """The results of the tasks ``frames`` names (key -> frames it writes) of ``graph``, in that order, computed on
    ``client`` (else dask's own scheduler), ``advance(frames)`` as each finishes; the first error raised. The graph
    is handed over once, culled to what they need (a resume's tasks), its tasks' names kept (nothing fused)."""
    keys = list(frames)
    if isinstance(graph, HighLevelGraph):
        graph = dict(graph.cull(set(keys)))
    if client is not None:
        from distributed import as_completed

        futures = client.get(graph, keys, sync=False)
        with released(futures):  # forgotten by the cluster even while an error holds them: a resume computes afresh
            for future in as_completed(futures):
                if future.status == "finished":
                    advance(frames[future.key])
            return client.gather(futures)

    class Advance(Callback):  # dask's local schedulers call it as each task finishes, from their main loop
        def _posttask(self, key, result, dsk, state, worker_id):
            if key in frames:
                advance(frames[key])

    with Advance():  # dask's configured scheduler, else its default for arrays and delayed: threads
        return list((get_scheduler() or dask.threaded.get)(graph, keys))


def _write_task(bits: np.ndarray, url: str, start: int, index: int) -> np.ndarray:
    """Task ``index``: pack frames ``[start, start + n)`` (n, y, x) bool, write their chunks of ``spikes``, then record
    the task committed (its spike count); -> that count, shape (1,). Run again, it writes the same bytes."""
    hold_point()  # inert unless a fault test asks (pipeline.compute.hold)
    packed = pack_rows(bits)
    write_region(url, SPIKES, start, packed)
    count = np.array([count_spikes(packed)], np.int64)
    write_region(url, COMMITTED, index, count)
    return count
