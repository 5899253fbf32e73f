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

import contextlib
import dataclasses
import logging
import math
import operator
import uuid
from typing import TYPE_CHECKING

import dask.threaded
import numpy as np
import zarr
from dask.base import get_scheduler, tokenize
from dask.callbacks import Callback
from dask.core import get_deps
from dask.highlevelgraph import HighLevelGraph

from pipeline.compute.cluster import check_in_memory, check_scheduler, check_workers, dask_client
from pipeline.compute.executor import released
from pipeline.compute.hold import hold_point
from pipeline.compute.progress import progress_bar
from pipeline.jobs.ingest import (COMMITTED_UNITS, IngestPlan, check_same_capture, ingest_task, run_tasks,
                                  task_frames_for)
from pipeline.jobs.simulate_plan import (SimulateOptions, check_options, hr_pair_motion, open_scene,
                                         simulated_meta)
from pipeline.stores.frame_sources import open_frame_source
from pipeline.stores.ground_truth import declare_truth, write_flow, write_truth
from pipeline.stores.lease import check_free, claimed, held
from pipeline.stores.outputs import SPIKE_STORE, check_existing, new_output
from pipeline.stores.spike_store import (COMMITTED, SPIKES, SpikeMeta, SpikeStore, SpikeStoreWriter, chunk_frames_for,
                                         open_spike_store, write_region)
from pipeline.stores.storage import check_apart, recorded
from stages.capture.bits import count_spikes, pack_rows, packed_width, unpacked_bits
from stages.errors import InputError, describe
from stages.reconstruction.methods import WINDOW, output_centres
from stages.simulation import sensor
from stages.simulation.intensities import to_unit_rgb
from stages.simulation.latent import truth_image

if TYPE_CHECKING:  # dask.array imports xarray, pandas and SciPy: never in the workers that run these tasks
    import dask.array as da

BLOCK_BYTES = 64 * 2**20  # scene frames a block unless chunk_frames says otherwise: about this many bytes, at least one
WRITES_AT_ONCE = 32  # write tasks a round (computed): what a long recording keeps in flight, and in the scheduler


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
    truth = made_truth(scene, output_centres(options.frames, WINDOW, options.truth_every), dest, options.cfa)
    on = scheduler or f"a local cluster ({workers or 'a worker per core'} workers)"
    logging.getLogger("cscsr.simulate").debug(  # cscsr --verbose
        "%s -> %s: %d frames of %dx%d LR (x%d HR), cfa %s, chunks of %d frames; on %s", src, dest, options.frames,
        height, width, options.scale, options.cfa, chunk, on)
    written = write_store(SpikeWrites(dest, meta, options.frames, chunk, None), bits,
                          client=lambda: dask_client(workers=workers, scheduler=scheduler), overwrite=options.overwrite,
                          resume=False, truth=truth, progress=progress, title=f"simulate {src}", keep_partial=False,
                          flag="--overwrite")
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
        increments, fired = (f"{name}-increments", k), (f"{name}-fired", k)  # fired: fired_key
        if made is None:
            layer[increments] = (_increments, (scene.name, k, 0, 0, 0), first_frame, options, dark)
        else:
            frames = range(first_frame, first_frame + n_frames)
            pairs = [[i, *_pair_keys(layer, made, i, f"{name}-source")] for i in made.pairs(frames)]
            layer[increments] = (_made_increments, made, pairs, frames, options, dark)
        layer[fired] = (fire_chunk, increments, state, options.reset, thresholds)
        state = (f"{name}-state", k)  # what block k + 1 fires on
        layer[state] = (state_after, fired)
        layer[(name, k, 0, 0)] = (unpacked_bits, (operator.attrgetter("packed"), fired), width)
        first_frame += n_frames
    graph = HighLevelGraph.from_collections(name, layer, dependencies=[] if made else [scene])
    return da.Array(graph, name, chunks=(scene.chunks[0], (height,), (width,)), meta=np.empty((0, 0, 0), bool))


def fired_key(spikes: "da.Array", k: int) -> tuple[str, int]:
    """The key of what block ``k`` of simulated ``spikes`` fired (``sensor.Fired``: its bits packed, the state)."""
    return f"{spikes.name}-fired", k


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


@dataclasses.dataclass(frozen=True)
class Truth:
    """The ground truth a store of simulated spikes records beside them: pictures (HR ``size``) at spike frames
    ``centres``, and a camera path's flow between them (``with_flow``), written by the tasks ``keys`` of ``graph``."""

    centres: list[int]
    size: tuple[int, int]
    with_flow: bool
    graph: dict
    keys: list


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


# ---- the store written ----

class SpikesIncomplete(RuntimeError):
    """Some :func:`to_spikes` tasks failed: the others are committed in the store, for ``resume=True``."""


class SpikeWrites:
    """Spikes of ``meta`` and ``n_frames`` frames cut into the tasks that write them into a store at ``url``: its
    chunks of ``chunk`` frames, task ``i`` its frames ``[i * task_frames, (i + 1) * task_frames)``; ``resumed``: the
    store to finish as the caller's checks opened it, before the claim, else None; ``capture``: the reader of a raw
    capture the spikes are all the frames of (``lazy.open_capture``), whose tasks are ingest's."""

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

    def run(self, bits: "da.Array", todo: list[int], advance, client) -> np.ndarray:
        """Tasks ``todo`` of ``bits`` (t, y, x) bool on ``client`` (else Dask's own scheduler), ``advance(frames)`` as
        each is written; -> their spike counts. Raises :class:`SpikesIncomplete` if any fails (what the others
        committed stays)."""
        name = f"to-spikes-{tokenize(bits.name, self.url, self.task_frames, todo)}"
        if bits.chunks[0] == tuple(map(self.frames_of, range(self.n_tasks))) and fired_key(bits, 0) in bits.dask:
            blocks = bits  # simulated, a block a task: each task writes the bits its block fired, packed as they are
            layer = {(name, j): (_write_packed, (operator.attrgetter("packed"), fired_key(bits, index)), self.url,
                                 index * self.task_frames, index) for j, index in enumerate(todo)}
        else:
            blocks = bits.rechunk((self.task_frames, -1, -1))
            layer = {(name, j): (_write_task, (blocks.name, index, 0, 0), self.url, index * self.task_frames, index)
                     for j, index in enumerate(todo)}
        graph = HighLevelGraph.from_collections(name, layer, dependencies=[blocks])
        frames = {(name, j): self.frames_of(index) for j, index in enumerate(todo)}
        try:
            return np.concatenate(computed(graph, frames, advance, client, at_once=WRITES_AT_ONCE))
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
                done = computed(tasks, {key: self.frames_of(index) for key, index in zip(tasks, todo)}, advance, None)
            except Exception as error:  # noqa: BLE001 - every failure is said, as plan.run says it
                done = [describe(error)] * len(todo)
            outcomes = dict(zip(todo, done))
        if failed := [why for why in outcomes.values() if isinstance(why, str)]:
            committed = int((open_spike_store(self.url, allow_incomplete=True).group[COMMITTED][:] >= 0).sum())
            raise SpikesIncomplete(f"to_spikes {self.url}: {committed} of {self.n_tasks} tasks committed, the others "
                                   f"not ({failed[0]}): fix the cause and call to_spikes again with resume=True")
        return np.array([outcomes[index] for index in todo], np.int64)


def write_store(writes: SpikeWrites, bits: "da.Array", *, client, overwrite: bool, resume: bool, truth: Truth | None,
                progress: bool, title: str, keep_partial: bool, flag: str) -> dict:
    """Write ``bits`` (t, y, x) bool, as ``writes`` cuts them, into a new spike store (``resume``: finish the one
    there), then ``truth``, on ``client`` (else Dask's own scheduler; a function: the cluster it starts once the store
    is claimed, closed before a failed store is removed); every check of the caller's made before. ``keep_partial``:
    a store left unfinished stays, for a resume; ``flag``: how the caller says ``--overwrite``. -> ``attrs`` (the
    store's final attributes), ``frames``, ``spikes``, ``tasks``, ``tasks_run``, ``tasks_skipped``. Raises
    :class:`SpikesIncomplete` if a task fails."""
    url, plan = writes.url, writes
    with claimed(url), contextlib.ExitStack() as stack:  # one job per store, taken before the store is touched
        if resume:
            check_free(url)  # and no live lease (a job on a machine that shares no claim file with us)
        stack.enter_context(new_output(url, overwrite=overwrite, kind=SPIKE_STORE, flag=flag, resume=resume,
                                       keep_partial=keep_partial))
        if callable(client):  # no task writes once a failed store is removed
            client = stack.enter_context(client())
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
                declare_truth(writer, truth.centres, truth.size, float(plan.meta.fps), with_flow=truth.with_flow)
        todo = [index for index in range(plan.n_tasks) if counts[index] < 0]
        if todo:
            to_write = sum(plan.frames_of(index) for index in todo)
            with held(url), progress_bar(title, to_write, enabled=progress) as advance:
                counts[todo] = (plan.run(bits, todo, advance, client) if plan.capture is None
                                else plan.run_ingest(todo, client, advance))
        if truth is not None and writer.group.attrs.get("state") != "complete":
            with held(url):
                computed(truth.graph, dict.fromkeys(truth.keys, 0), lambda frames: None, client)
        if writer.group.attrs.get("state") != "complete":
            writer.finish(spike_count=int(counts.sum()))
    return {"attrs": dict(writer.group.attrs), "frames": plan.n_frames, "spikes": int(counts.sum()),
            "tasks": plan.n_tasks, "tasks_run": len(todo), "tasks_skipped": plan.n_tasks - len(todo)}


def computed(graph, frames: dict, advance, client, at_once: int | None = None) -> list:
    """The results of the tasks ``frames`` names (key -> frames it writes) of ``graph``, in that order, computed on
    ``client`` (else dask's own scheduler), ``advance(frames)`` as each finishes; the first error raised. The graph
    is handed over culled to what they need (a resume's tasks), its tasks' names kept (nothing fused); ``at_once``:
    that many of them a round, what a round made that later rounds need (a chain's state, the sensor's draws, a
    video's pair) kept for them, so that memory and the scheduler's graph stay bounded however many there are."""
    keys = list(frames)
    if isinstance(graph, HighLevelGraph):
        graph = dict(graph.cull(set(keys)))
    results, held = [], {}  # held: what earlier rounds made that later ones need (futures on a client, else values)
    try:
        for round_keys, round_graph, earlier, kept, needed_later in _rounds(graph, keys, at_once or len(keys) or 1):
            round_graph = round_graph | {key: held[key] for key in earlier}  # what earlier rounds made
            if client is not None:
                from distributed import as_completed

                futures = client.get(round_graph, round_keys + kept, sync=False)
                held |= dict(zip(kept, futures[len(round_keys):]))  # released below, whatever happens
                with released(futures[:len(round_keys)]):  # forgotten by the cluster even while an error holds
                    for future in as_completed(futures[:len(round_keys)]):  # them: a resume computes afresh
                        if future.status == "finished":
                            advance(frames[future.key])
                    results += client.gather(futures[:len(round_keys)])
            else:
                class Advance(Callback):  # dask's local schedulers call it as each task finishes, from their loop
                    def _posttask(self, key, result, dsk, state, worker_id):
                        if key in frames:
                            advance(frames[key])

                with Advance():  # dask's configured scheduler, else its default for arrays and delayed: threads
                    values = (get_scheduler() or dask.threaded.get)(round_graph, round_keys + kept)
                results += values[:len(round_keys)]
                held |= dict(zip(kept, values[len(round_keys):]))
            for key in [key for key in held if key not in needed_later]:
                value = held.pop(key)
                if client is not None:
                    value.release()
    finally:
        if client is not None:
            for future in held.values():
                future.release()
    return results


def _rounds(graph: dict, keys: list, at_once: int):
    """``keys`` of ``graph`` ``at_once`` a round, in order: per round its keys, its graph (what they need that no
    earlier round made), the keys of earlier rounds it reads, the keys it makes that a later round reads, and every
    key made so far that a later round reads."""
    dependencies, dependents = get_deps(graph)
    unread = {key: len(readers) for key, readers in dependents.items()}  # readers not yet made
    made, open_keys = set(), set()
    for start in range(0, len(keys), at_once):
        round_keys = keys[start:start + at_once]
        needed, stack = set(), list(round_keys)
        while stack:
            if (key := stack.pop()) not in needed and key not in made:
                needed.add(key)
                stack.extend(dependencies[key])
        earlier = {dep for key in needed for dep in dependencies[key]} - needed
        made |= needed
        for key in needed:
            for dep in dependencies[key]:
                unread[dep] -= 1
        open_keys = {key for key in open_keys | needed if unread[key]}
        yield round_keys, {key: graph[key] for key in needed}, earlier, sorted(open_keys & needed, key=str), \
            set(open_keys)


def _write_task(bits: np.ndarray, url: str, start: int, index: int) -> np.ndarray:
    """Task ``index``: pack frames ``[start, start + n)`` (n, y, x) bool, write their chunks of ``spikes``, then record
    the task committed (its spike count); -> that count, shape (1,). Run again, it writes the same bytes."""
    return _write_packed(pack_rows(bits), url, start, index)


def _write_packed(packed: np.ndarray, url: str, start: int, index: int) -> np.ndarray:
    """Task ``index``: :func:`_write_task` of frames packed (n, y, ceil(x / 8))."""
    hold_point()  # inert unless a fault test asks (pipeline.compute.hold)
    write_region(url, SPIKES, start, packed)
    count = np.array([count_spikes(packed)], np.int64)
    write_region(url, COMMITTED, index, count)
    return count
