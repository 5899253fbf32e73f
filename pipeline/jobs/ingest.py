"""``cscsr ingest``: a raw capture into a new spike store, in this process or over Dask; resumable.

**Tasks.** The capture is cut into tasks, runs of ``task_frames`` whole frames (a whole number of the
store's chunks, about :data:`BLOCK_BYTES` of packed spikes; ``--task-frames``): task ``i`` is frames
``[i * task_frames, (i + 1) * task_frames)``. A task packs its frames, writes their chunks of ``spikes``
(no two tasks share a chunk), then records itself committed: ``committed[i]`` = the spikes it counted. The store
is written as every spike store is (``pipeline.stores.spike_writes.write_store``: metadata first, ``committed``
recording the capture's fingerprint and the options, finished once every task is committed), and as
``lazy.to_spikes(lazy.open_capture(...))`` writes it: the job is that composition (:class:`CaptureWrites`).

**Where.** Without ``--workers``, a scheduler (``--scheduler``, ``DASK_SCHEDULER_ADDRESS``) or a client the tasks
run in this process, one stream read ahead of the writes: the reference, whose bytes every other way
reproduces. With them each task is
a Dask task that reads its frames by byte range (ranged captures, ``.dat`` and ``.npy``: a ``.npz`` is one
stream) wherever it runs; tasks are idempotent (the same chunks, the same bytes), so a lost worker's
tasks run again (``pipeline.compute.executor``). A local cluster's workers die with the job, in segments of
child processes beyond the first (``in_segments``), so a killed ingest leaves nothing writing.

**Resume.** ``--resume`` checks that the capture is the one the store was ingested from (its size and a
SHA-256 of its first and last MiB: two range reads, even at a terabyte), with the same options and task
size, then runs only the tasks not committed and finishes the store. A failed parallel ingest keeps
what it committed for ``--resume``; a failed one-process ingest is removed, as before.

**Dry run.** :func:`plan_ingest` checks everything a run would, creates nothing, and measures one task
(read, pack, compress into memory) for the store's size at rest and the hours on 1, 8, 64 workers.
"""

import contextlib
import functools
import json
import logging
import time
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
import zarr
from distributed import Client

from pipeline.stores.captures import RANGED_KINDS, default_layout, open_capture
from pipeline.compute.cluster import (check_in_memory, check_scheduler, check_workers, dask_client,
                              scheduler_address)
from pipeline.compute.estimate import hours_table
from pipeline.compute.executor import computed, failure, in_segments, show_dashboard_once, submitted
from pipeline.compute.hold import hold_point
from pipeline.stores.lease import check_free
from pipeline.stores.outputs import SPIKE_STORE, check_existing
from pipeline.compute.progress import is_quiet
from pipeline.stores.spike_store import (CODEC_LEVEL, COMMITTED, WRITE_CONFIG, SpikeMeta, SpikeStore, check_fps,
                                  chunk_frames_for, ingest_task_arrays, open_spike_store)
from pipeline.stores.spike_writes import SpikesIncomplete, SpikeWrites, write_packed, write_store
from pipeline.stores.storage import check_apart, exists, recorded, remove
from stages.capture.bits import count_spikes, packed_width
from stages.reconstruction.cfa import check_cfa, flip_vertically
from stages.errors import InputError, describe
from stages.numbers import as_float, check_flag, check_number, check_text
from stages.prefetch import prefetched
from stages.capture.resets import check_reset
from stages.capture.sps100 import CaptureDamaged, check_layout

BLOCK_BYTES = 64 * 2**20  # packed bytes per task (and per block read): bounds memory, amortises I/O
SEGMENT_TASKS = 10_000  # tasks per segment of a local cluster (a terabyte is ~16,000 tasks)
log = logging.getLogger("cscsr.ingest")  # DEBUG lines (cscsr --verbose): the job's plan, each task's outcome


@dataclass(frozen=True)
class IngestOptions:
    height: int | None = None
    width: int | None = None
    cfa: str = "mono"
    fps: float = 20000.0
    flip: bool = False
    head_columns: int = 0
    key: str | None = None
    reset: str = "subtract"
    overwrite: bool = False
    resume: bool = False
    task_frames: int | None = None  # frames per task, rounded up to whole chunks (default: ~BLOCK_BYTES)
    layout: str | None = None  # a raw capture's layout (stages.capture.sps100.LAYOUTS); None: by extension

    def __post_init__(self):
        object.__setattr__(self, "fps", as_float(self.fps))  # fps=20000 records the bytes --fps 20000 does

    def check(self) -> None:
        """Every check of the options that needs no capture, types first (only the Python API can get them
        wrong: ``flip="no"`` is a true string, ``height="16"`` no number). The capture and the store's
        metadata check the sizes and ``fps`` against the recording."""
        for name in ("height", "width"):
            if getattr(self, name) is not None:
                check_number(f"--{name}", getattr(self, name), integer=True)
        check_text("--cfa", self.cfa)
        check_fps("--fps", self.fps)
        check_flag("--flip", self.flip)
        check_number("--head-columns", self.head_columns, integer=True)
        check_text("--key", self.key, optional=True)
        check_text("--reset", self.reset)
        check_flag("--overwrite", self.overwrite)
        check_flag("--resume", self.resume)
        if self.task_frames is not None:
            check_number("--task-frames", self.task_frames, at_least=1, integer=True)
        check_text("--layout", self.layout, optional=True)
        if self.layout is not None:
            check_layout(self.layout)
        check_cfa(self.cfa)
        check_reset(self.reset)
        if self.resume and self.overwrite:
            raise InputError("--resume and --overwrite contradict each other: choose one")


JOB_FIELDS = ("overwrite", "resume", "task_frames")  # how a capture is ingested, not what it is taken to be


def capture_fields(options: IngestOptions) -> dict:
    """What the capture is taken to be (every field but :data:`JOB_FIELDS`): the watcher keys its work on these.
    ``layout`` only when one is named: by extension (None), the fields are those before it existed, so the
    watcher's keys of earlier recordings stay as they were."""
    fields = asdict(options)
    for name in JOB_FIELDS:
        del fields[name]
    if fields["layout"] is None:
        del fields["layout"]
    return fields


@dataclass(frozen=True)
class IngestPlan:
    """What every task needs, a few hundred bytes travelling in each task: the capture as workers open it
    (absolute, or a URL), the store, and the cut into tasks."""

    capture: "CaptureFrames"
    dest: str
    task_frames: int
    run: str  # this run's id: workers open the capture and the store once per run

    @property
    def n_frames(self) -> int:
        return self.capture.n_frames

    @property
    def n_tasks(self) -> int:
        return -(-self.n_frames // self.task_frames)

    def frames(self, index: int) -> tuple[int, int]:
        """Frames ``[start, stop)`` of task ``index``."""
        start = index * self.task_frames
        return start, min(start + self.task_frames, self.n_frames)


@dataclass
class _Job:
    """An ingest checked and cut into tasks, before anything is written."""

    capture: object  # the reader, opened
    writes: "CaptureWrites"
    plan: IngestPlan
    counts: np.ndarray  # the spike counts of its tasks, -1: not committed (of the store to resume, when checked)


def default_task_frames(chunk: int, frame_bytes: int) -> int:
    """Frames per task without ``--task-frames``: whole chunks, about :data:`BLOCK_BYTES` of packed frames (a
    ``--task-frames`` is rounded up to whole chunks by ``SpikeWrites.cut``)."""
    return chunk * max(1, BLOCK_BYTES // (chunk * frame_bytes))


def _prepare(src: str, dest: str, options: IngestOptions, *, parallel: bool, client) -> _Job:
    """Every check of an ingest that writes nothing: the options, the places, the capture, whether it can be
    read in parallel, and for ``--resume`` the store to finish (``SpikeWrites.resumable``); reads, never writes."""
    options.check()
    check_apart(dest, src)
    if options.resume and not exists(dest):
        raise InputError(f"cannot resume: {dest} does not exist")
    if parallel:  # a client whose workers are in this process shares its memory://
        check_in_memory((src, dest), client=client, instead=", or ingest without --workers or --scheduler")
    capture = opened_capture(src, options)
    if parallel and not capture.ranged:
        raise InputError(f"{src}: a .npz is read as one stream, and parallel ingest (--workers, --scheduler, "
                         f"DASK_SCHEDULER_ADDRESS) reads "
                         f"a capture by frame range ({', '.join(RANGED_KINDS)}): ingest it without them, or save "
                         f"the array as .npy")
    sensor_cfa, meta = capture_meta(src, options, capture)
    chunk = chunk_frames_for(meta, capture.n_frames)
    resumed = _resumed(dest) if options.resume else None
    asked = options.task_frames
    if asked is None and resumed is not None and isinstance(found := resumed.group[COMMITTED].attrs.get("task_frames"),
                                                            int) and found > 0:
        asked = found  # resumed as it was cut
    record = capture_record(src, options, capture, sensor_cfa)
    frames = CaptureFrames(recorded(src), options.height, options.width, options.flip, options.head_columns,
                           options.layout, capture.n_frames, capture.height, packed_width(capture.width),
                           json.dumps(record), options.key)
    writes = CaptureWrites(dest, meta, capture.n_frames, chunk,
                           asked or default_task_frames(chunk, capture.height * packed_width(capture.width)), frames,
                           cli=True)
    writes.given_task = options.task_frames
    counts = writes.resumable(resumed) if resumed is not None else np.full(writes.n_tasks, -1, np.int64)
    return _Job(capture, writes, writes.plan(), counts)


def opened_capture(src: str, options: IngestOptions):
    """The reader of capture ``src`` as ``options`` take it (``pipeline.stores.captures.open_capture``: the sizes, the
    layout and its first frame checked; nothing read but headers and sizes)."""
    return open_capture(src, height=options.height, width=options.width, flip=options.flip,
                        head_columns=options.head_columns, key=options.key, layout=options.layout)


def capture_meta(src: str, options: IngestOptions, capture) -> tuple[str, SpikeMeta]:
    """(the sensor's colour pattern, the metadata of the store ingesting ``capture`` writes): with ``flip`` the
    store records the pattern of the upright image it holds. ``lazy.open_capture``'s attributes too."""
    sensor_cfa = check_cfa(options.cfa, capture.height, capture.width)
    meta = SpikeMeta(
        height=capture.height, width=capture.width,
        cfa=flip_vertically(sensor_cfa, capture.height) if options.flip else sensor_cfa,
        fps=options.fps, source=recorded(src), flipped=options.flip, head_columns=options.head_columns, reset=options.reset,
    )
    return sensor_cfa, meta


def capture_record(src: str, options: IngestOptions, capture, sensor_cfa: str) -> dict:
    """What ``committed`` records of the capture a store is ingested from, for a resume to compare
    (:func:`check_same_capture`): its fingerprint (size, SHA-256 of its ends) and how it was read. ``cscsr ingest``
    and ``lazy.to_spikes`` of ``lazy.open_capture`` record it alike, so either resumes the other's store."""
    return {"capture": capture.fingerprint(),
            "options": {"height": capture.height, "width": capture.width, "cfa": sensor_cfa, "fps": options.fps,
                        "flip": options.flip, "head_columns": options.head_columns,
                        "key": getattr(capture, "key", None), "reset": options.reset,
                        "layout": options.layout or default_layout(src)}}


def capture_change(was: dict, now: dict) -> str | None:
    """How a capture's fingerprint ``now`` differs from the one recorded, ``was`` (:func:`capture_record`), or None."""
    if was == now:
        return None
    if was.get("bytes") != now["bytes"]:
        return f"{was.get('bytes')} bytes -> {now['bytes']} bytes"
    return "the same size, but its first or last MiB differ"


def check_same_capture(dest: str, src: str, found: dict, record: dict, *, task_frames: int | None = None,
                       again: str = "--overwrite") -> None:
    """Refuse to resume ``dest`` (``found``: its ``committed`` attributes) from a capture other than the one it was
    ingested from, or read with other options (``record``: :func:`capture_record` of ``src`` now), or, given
    ``task_frames``, cut into other tasks."""
    was = found.get("capture")
    if not isinstance(was, dict):
        raise InputError(f"cannot resume {dest}: it records no capture to compare {src} with (written from other "
                         f"spikes, or before captures were recorded): start again with {again}")
    if why := capture_change(was, record["capture"]):
        raise InputError(f"cannot resume {dest}: {src} is not the capture it was ingested from ({why}): give that "
                         f"capture, or start again with {again}")
    options = dict(found.get("options") or {})
    options.setdefault("layout", default_layout(src))  # recorded before layouts: read by extension, as now
    changed = [f"{k} {options.get(k)!r} -> {v!r}" for k, v in record["options"].items() if options.get(k) != v]
    if task_frames is not None and found.get("task_frames") != task_frames:
        changed.append(f"task_frames {found.get('task_frames')!r} -> {task_frames!r}")
    if changed:
        raise InputError(f"cannot resume {dest}: it was ingested with other options ({', '.join(changed)}): give "
                         f"those, or start again with {again}")


def unread_parts(src: str, capture, n_frames: int) -> list[str]:
    """The lines that say which bytes of ``capture`` are not read: those before its first whole frame (an sps100
    capture begun mid-frame) and those after its ``n_frames`` whole frames (a frame cut short, its packets checked
    with the last frames: ``captures.RawCapture._packed``); none for most captures."""
    lines = []
    if lead := capture.unread_lead:
        lines.append(f"{src}: its first {lead:,} bytes, before frame 0, are a frame the capture began inside of: "
                     f"not read")
    if unread := capture.unread_bytes:
        lines.append(f"{src}: its last {unread:,} bytes, after frame {n_frames - 1}, are a frame cut short (its "
                     f"packets in sequence): not read")
    return lines


def _resumed(dest: str) -> SpikeStore:
    """The store to resume; refuses a store that holds no record of ingest tasks."""
    store = open_spike_store(dest, allow_incomplete=True)  # a video store, a folder, ...: refused by name
    if COMMITTED not in store.group or not isinstance(store.group[COMMITTED], zarr.Array):
        raise InputError(f"cannot resume {dest}: it holds no record of ingest tasks (a simulated store, or one "
                         f"ingested by cscsr before resumable ingest): ingest it again with --overwrite")
    return store


def on_dask(client, workers: int | None, scheduler: str | None) -> bool:
    """Whether the tasks run on Dask: a client, ``--workers``, or a scheduler named by ``--scheduler``,
    ``DASK_SCHEDULER_ADDRESS`` or Dask's ``scheduler-address``, as for every other job (so an ingest under
    ``deploy/slurm.py`` runs on its cluster, not on the login node)."""
    return client is not None or workers is not None or scheduler_address(scheduler) is not None


def _one_local_task(plan: IngestPlan, client, scheduler: str | None) -> bool:
    """Whether a parallel ingest would start a local cluster (``--workers``, no client or scheduler) for one task:
    then it runs in this process, one stream, the same bytes sooner (a cluster of a long-lived scheduler is
    used whatever the tasks: an ingest under ``deploy/slurm.py`` never runs on the login node)."""
    return plan.n_tasks <= 1 and client is None and scheduler_address(scheduler) is None


def ingest(src: str, dest: str, options: IngestOptions = IngestOptions(), *, progress: bool = True,
           workers: int | None = None, scheduler: str | None = None, client=None) -> dict:
    """Copy ``src`` into a spike store at ``dest``; return the store's final attributes (:func:`run_ingest`)."""
    return run_ingest(src, dest, options, progress=progress, workers=workers, scheduler=scheduler,
                      client=client)["attrs"]


def run_ingest(src: str, dest: str, options: IngestOptions = IngestOptions(), *, progress: bool = True,
               workers: int | None = None, scheduler: str | None = None, client=None) -> dict:
    """Copy ``src`` into a spike store at ``dest`` (``options.resume``: finish the one there); return
    ``attrs`` (the store's final attributes), ``frames``, ``tasks``, ``tasks_run``, ``tasks_skipped``.

    In this process unless ``client``, ``workers`` or ``scheduler`` is given (then on Dask, as the other
    jobs: the client, else the named scheduler or ``DASK_SCHEDULER_ADDRESS``, else a local cluster of
    ``workers``). ``options.cfa`` is the pattern as recorded by the sensor; with ``flip`` the store
    records the pattern of the upright image it holds. The store is written as ``lazy.to_spikes`` writes
    ``lazy.open_capture``'s spikes (``pipeline.stores.spike_writes.write_store`` of :class:`CaptureWrites`).
    """
    check_workers(workers, scheduler)
    check_text("--scheduler", scheduler, optional=True)
    parallel = on_dask(client, workers, scheduler)
    job = _prepare(src, dest, options, parallel=parallel, client=client)
    if parallel and _one_local_task(job.plan, client, scheduler):
        parallel = False
        log.info("%s: one task of %d frames: ingested in this process (a local cluster of --workers would only add "
                 "its start-up)", src, job.plan.n_frames)
    if parallel and client is None:
        check_scheduler(scheduler)  # a named scheduler answers (within seconds) before DEST is claimed or replaced
    plan, writes, meta = job.plan, job.writes, job.writes.meta
    writes.stream = None if parallel else job.capture  # in this process: one stream (a .npz too)
    writes.dashboard = progress and not is_quiet()
    with contextlib.ExitStack() as stack:
        if parallel and client is None and scheduler_address(scheduler):  # a long-lived cluster: connect once
            client = stack.enter_context(dask_client(scheduler=scheduler))
        elif parallel and client is None:
            client = LocalClusters(workers)
        log.debug("%s -> %s: %d frames of %dx%d, cfa %s; %d tasks of %d frames, %d committed already; %s", src, dest,
                  plan.n_frames, meta.height, meta.width, meta.cfa, plan.n_tasks, plan.task_frames,
                  int((job.counts >= 0).sum()), "in this process, one stream" if not parallel else
                  f"on the cluster at {client.scheduler.address}" if isinstance(client, Client) else
                  f"on local clusters of {workers or 'a worker per core'} workers, {SEGMENT_TASKS} tasks each")
        written = write_store(writes, None, client=client, overwrite=options.overwrite, resume=options.resume,
                              truth=None, progress=progress, title=f"ingest {src}", keep_partial=parallel,
                              flag="--resume or --overwrite")
    for line in unread_parts(src, job.capture, plan.n_frames):
        log.warning("%s", line)
    return {name: written[name] for name in ("attrs", "frames", "tasks", "tasks_run", "tasks_skipped")}


@dataclass(frozen=True)
class LocalClusters:
    """Where a parallel ingest with neither client nor scheduler runs its tasks: local clusters of ``workers``,
    :data:`SEGMENT_TASKS` tasks each (``pipeline.compute.executor.in_segments``)."""

    workers: int | None


@dataclass(frozen=True)
class CaptureFrames:
    """A capture's packed frames as tasks read them, a block at a time, each one byte-range read through ingest's
    reader, opened once per process (:func:`opened_frames`); a few fields, pickled into every task. ``lazy.open_capture``
    reads its blocks through it (``da.from_array``)."""

    url: str
    height: int | None  # as given (None: the capture's own)
    width: int | None
    flip: bool
    head_columns: int
    layout: str | None
    n_frames: int
    rows: int  # the frames' height
    packed_columns: int  # bytes a packed row
    record: str  # what a store written from it records of the capture (capture_record), as JSON
    key: str | None = None  # a .npz's array

    ndim = 3
    dtype = np.dtype(np.uint8)

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.n_frames, self.rows, self.packed_columns

    def __getitem__(self, key: tuple[slice, slice, slice]) -> np.ndarray:
        frames, *rest = key
        start, stop, _ = frames.indices(self.n_frames)
        return opened_frames(self).read(start, stop)[(slice(None), *rest)]


@functools.lru_cache(maxsize=8)
def opened_frames(frames: CaptureFrames):
    """The capture's reader, opened once per process; refused if the capture changed since the graph was built."""
    options = IngestOptions(frames.height, frames.width, flip=frames.flip, head_columns=frames.head_columns,
                            key=frames.key, layout=frames.layout)
    capture = opened_capture(frames.url, options)
    if capture.n_frames != frames.n_frames:
        raise InputError(f"{frames.url} changed since it was opened: {capture.n_frames} frames, not "
                         f"{frames.n_frames}: open it again")
    return capture


class CaptureWrites(SpikeWrites):
    """A raw capture's frames (``capture``) written into a spike store as ``cscsr ingest`` writes them: each task
    reads its frames packed by one byte range and writes them as they are (:func:`ingest_task`: no unpacked bits
    made or moved), on a client through the job's executor, on :class:`LocalClusters` in segments, in this process
    as one stream read ahead of the writes (``stream``: the opened reader, the one-process job's, which reads a
    ``.npz`` too), else on Dask's own scheduler. The store records the capture (its fingerprint, how it was read),
    a resume compares it (:func:`check_same_capture`), and a capture found damaged removes a new store (the damage
    stays: a resume cannot help). ``cli``: errors in the command line's words."""

    def __init__(self, url: str, meta: SpikeMeta, n_frames: int, chunk_frames: int | None, task_frames: int | None,
                 capture: CaptureFrames, *, cli: bool = False, stream=None):
        super().__init__(url, meta, n_frames, chunk_frames, task_frames)
        self.capture, self.stream, self.cli = capture, stream, cli
        self.dashboard = False  # the job's: show the cluster's dashboard link when its tasks go there
        self.given_task = None  # the job's --task-frames, if given
        self.record = json.loads(capture.record)
        if cli:
            self.again = "--overwrite"

    def check_same(self, store: SpikeStore, found: dict) -> None:
        """The capture it was written from, read as it was (its other attributes, but where it lies, follow from
        those), and cut as ``--task-frames`` asks, if it does (one task of the whole capture, however large, is one
        cut); the rest of the cut is :meth:`resumable`'s to check, with the store's chunks."""
        task_frames, recorded_task = self.task_frames if self.given_task else None, found.get("task_frames")
        if isinstance(recorded_task, int) and task_frames is not None and self.same_cut(recorded_task, task_frames):
            task_frames = recorded_task
        check_same_capture(self.url, self.capture.url, found, self.record, task_frames=task_frames, again=self.again)

    def cut_refused(self, store: SpikeStore, tasks: int, recorded_task) -> str:
        if not self.cli:
            return super().cut_refused(store, tasks, recorded_task)
        return (f"cannot resume {self.url}: its arrays do not match the capture ({store.n_frames} frames in chunks "
                f"of {store.spikes.chunks[0]}, {tasks} tasks): start again with --overwrite")

    def plan(self) -> IngestPlan:
        """What each of its tasks carries (:func:`ingest_task`), for one run."""
        return IngestPlan(self.capture, recorded(self.url), self.task_frames, uuid.uuid4().hex)

    def guarded(self) -> contextlib.AbstractContextManager:
        return _removed_if_damaged(self.url)

    def run(self, bits, todo: list[int], advance, client) -> np.ndarray:
        plan = self.plan()
        if client is None and self.stream is not None:
            return self._streamed(todo, advance)
        if isinstance(client, Client) and self.dashboard:
            show_dashboard_once(client)
        if isinstance(client, LocalClusters):
            outcomes = in_segments(functools.partial(run_tasks, plan=plan), todo, SEGMENT_TASKS,
                                   workers=client.workers, show_dashboard=self.dashboard)
        elif client is not None:
            outcomes = run_tasks(client, todo, plan=plan)
        else:
            outcomes, advance = self._threaded(plan, todo, advance), lambda frames: None  # advanced as they ran
        counts, failed, damaged = {}, {}, {}
        for outcome in outcomes:
            start, stop = plan.frames(outcome.index)
            log.debug("task %d (frames %d-%d): %s", outcome.index, start, stop - 1, f"failed: {outcome.error}"
                      if outcome.error is not None else f"{outcome.spikes} spikes, committed")
            if outcome.error is not None:
                (damaged if outcome.damaged else failed)[outcome.index] = outcome.error
                continue
            counts[outcome.index] = outcome.spikes
            advance(stop - start)
        if damaged:  # the first in the capture: the tasks after a dropped packet are all out of sequence
            raise CaptureDamaged(damaged[min(damaged)])
        if failed:
            raise IngestIncomplete(self.url, plan, failed) if self.cli else self.incomplete(failed[min(failed)])
        return np.array([counts[index] for index in todo], np.int64)

    def _streamed(self, todo: list[int], advance) -> np.ndarray:
        """Tasks ``todo`` in this process: one stream of blocks read ahead of the writes."""
        skip = {index * self.task_frames for index in range(self.n_tasks)} - {index * self.task_frames
                                                                             for index in todo}
        counts = []
        for start, packed in prefetched(self.stream.blocks(self.task_frames, skip)):
            index = start // self.task_frames
            counts.append(int(write_packed(packed, self.url, start, index)[0]))
            log.debug("task %d (frames %d-%d): %d spikes, committed", index, start, start + packed.shape[0] - 1,
                      counts[-1])
            advance(packed.shape[0])
        return np.array(counts, np.int64)

    def _threaded(self, plan: IngestPlan, todo: list[int], advance) -> list["Outcome"]:
        """Tasks ``todo`` on Dask's own scheduler (``lazy.to_spikes`` without a client), ``advance(frames)`` as each
        finishes."""
        tasks = dict(ingest_task(plan, index) for index in todo)
        try:
            done = computed(tasks, {key: self.frames_of(index) for key, index in zip(tasks, todo)}, advance, None)
        except Exception as error:  # noqa: BLE001 - every failure is said, as on a cluster
            return [Outcome(index, None, describe(error)) for index in todo]
        return [Outcome(index, None, count, damaged=True) if isinstance(count, str) else Outcome(index, count, None)
                for index, count in zip(todo, done)]


@contextlib.contextmanager
def _removed_if_damaged(dest: str):
    """A capture found damaged (``stages.capture.sps100.CaptureDamaged``) mid-ingest removes the new store, even a
    parallel ingest's, which keeps its committed tasks for ``--resume`` on any other failure."""
    try:
        yield
    except CaptureDamaged:
        remove(dest)
        raise


class Outcome(NamedTuple):
    """One finished task: its index, the spikes it counted, or its error (``damaged``: the capture's own, in
    its layout's words: :class:`stages.capture.sps100.CaptureDamaged`)."""

    index: int
    spikes: int | None
    error: str | None
    damaged: bool = False


def run_tasks(client, tasks: Iterable[int], *, plan: IngestPlan) -> Iterator[Outcome]:
    """Run ingest tasks on ``client`` (``pipeline.compute.executor``: a bounded window, lost workers survived, tasks the
    cluster drops submitted again); yield each outcome as it finishes. ``lazy.to_spikes`` of ``lazy.open_capture``
    runs its tasks here too."""
    def submit(index: int):  # the plan travels in each task
        key, task = ingest_task(plan, index)
        return client.get({key: task}, [key], sync=False)[0]

    for index, future in submitted(client, tasks, submit, idempotent=True):
        error = failure(future)
        result = None if error else future.result()
        if isinstance(result, str):  # the capture is damaged: said, not raised (_ingest_task)
            yield Outcome(index, None, result, damaged=True)
        else:
            yield Outcome(index, None if error else int(result), error)


@functools.lru_cache(maxsize=4)
def _opened(plan: IngestPlan):
    """The capture and the store's arrays, opened once per worker process and run."""
    return (opened_frames(plan.capture), *ingest_task_arrays(plan.dest))


def ingest_task(plan: IngestPlan, index: int):
    """(key, task) of ingest task ``index``: :func:`_ingest_task`, under the key of ``lazy.to_spikes``'s writes
    (``to-spikes-<run>``), so a job's tasks and the lazy graph's have one name on a cluster's dashboard."""
    from dask._task_spec import Task

    key = (f"to-spikes-{plan.run}", index)
    return key, Task(key, _ingest_task, plan, index)


def _ingest_task(plan: IngestPlan, index: int) -> int | str:
    """Task: read frames of task ``index`` by byte range, pack them, write their chunks, record the task
    committed (its spike count); -> that count, or the line saying how its frames are damaged (checked before
    anything is written; the job then removes the store). Idempotent: run again, it writes the same bytes."""
    hold_point()  # inert unless a fault test asks (pipeline.compute.hold)
    capture, spikes, committed = _opened(plan)
    start, stop = plan.frames(index)
    try:
        packed = capture.read(start, stop)
    except CaptureDamaged as error:
        return str(error)
    with zarr.config.set(WRITE_CONFIG):
        spikes[start:stop] = packed
    count = count_spikes(packed)
    committed[index] = count
    return count


class IngestIncomplete(SpikesIncomplete):
    """Some tasks failed: which frames are missing and why; the rest is committed in the store."""

    def __init__(self, dest: str, plan: IngestPlan, failed: dict[int, str]):
        indices = sorted(failed)
        ranges = [f"{plan.frames(i)[0]}..{plan.frames(i)[1] - 1}" for i in indices]
        shown = ", ".join(ranges[:4]) + (", ..." if len(ranges) > 4 else "")
        causes = set(failed.values())
        cause = (f"each: {causes.pop()}" if len(causes) == 1 and len(indices) > 1  # one cause (a full disk): once
                 else f"frames {ranges[0]}: {failed[indices[0]]}")
        super().__init__(f"{len(indices)} of {plan.n_tasks} ingest tasks failed (frames {shown}; {cause}); the other "
                         f"tasks are committed in {dest}: fix the cause and run again with --resume")
        self.failed = failed


def plan_ingest(src: str, dest: str, options: IngestOptions = IngestOptions(), *, workers: int | None = None,
                scheduler: str | None = None, client=None) -> dict:
    """``ingest --dry-run``: every check a run makes, nothing created, and the plan: frames, the capture's bytes,
    tasks, chunks, the store's size at rest and the hours on 1, 8 and 64 workers, both from one task read,
    packed and compressed into memory here (the middle task; the first of a ``.npz``)."""
    check_workers(workers, scheduler)
    check_text("--scheduler", scheduler, optional=True)
    parallel = on_dask(client, workers, scheduler)
    job = _prepare(src, dest, options, parallel=parallel, client=client)
    if parallel and client is None:
        check_scheduler(scheduler)
    if options.resume:  # _prepare checked the store: as resumable
        check_free(dest)
    else:  # what new_output would refuse, refused now
        check_existing(dest, overwrite=options.overwrite, kind=SPIKE_STORE, flag="--resume or --overwrite")
    plan, meta, counts, chunk = job.plan, job.writes.meta, job.counts, job.writes.chunk
    seconds, stored, measured = _measure(job)
    todo = int((counts < 0).sum())
    task_frames = min(plan.task_frames, plan.n_frames)  # a task holds no more frames than the capture has
    per_task = seconds * task_frames / measured  # a whole task's worth
    pixels = plan.n_frames * meta.height * meta.width
    estimate = stored * plan.n_frames / measured
    here = not parallel or _one_local_task(plan, client, scheduler)
    where = ("this process" if here else "the given client" if client is not None
             else f"scheduler {scheduler_address(scheduler)}" if scheduler_address(scheduler)
             else f"a local cluster of {workers} workers")
    return {
        "source": str(src), "store": str(dest), "runs_on": where, "resume": options.resume,
        "frames": plan.n_frames, "height": meta.height, "width": meta.width,
        "capture_bytes": job.writes.record["capture"]["bytes"],
        "chunk_frames": chunk, "chunks": -(-plan.n_frames // chunk),
        "task_frames": task_frames, "tasks": plan.n_tasks, "tasks_committed": plan.n_tasks - todo,
        "tasks_to_run": todo,
        "store_bytes_estimate": int(round(estimate)), "bits_per_pixel_estimate": 8 * estimate / pixels,
        "measured_frames": measured, "seconds_per_task": per_task,
        "hours": hours_table(per_task, todo),
    }


def _measure(job: _Job) -> tuple[float, int, int]:
    """One task read and packed from the capture, then written to an in-memory array chunked and compressed as
    the store's: -> (seconds, compressed bytes of its chunks, frames)."""
    plan, capture = job.plan, job.capture
    index = plan.n_tasks // 2 if capture.ranged else 0

    def write(packed: np.ndarray) -> int:
        memory = zarr.storage.MemoryStore()
        array = zarr.create_array(memory, shape=packed.shape, chunks=(job.writes.chunk, *packed.shape[1:]), dtype=np.uint8,
                                  fill_value=0, compressors=zarr.codecs.ZstdCodec(level=CODEC_LEVEL),
                                  config={"write_empty_chunks": True})
        with zarr.config.set(WRITE_CONFIG):
            array[:] = packed
        count_spikes(packed)
        return sum(len(value) for key, value in memory._store_dict.items() if key.startswith("c/"))

    began = time.perf_counter()
    if capture.ranged:
        packed = capture.read(*plan.frames(index))
    else:
        packed = next(iter(capture.blocks(plan.task_frames)))[1]
    read = time.perf_counter() - began
    write(packed[: min(len(packed), job.writes.chunk)])  # warm-up: the codec and Zarr's threads
    began = time.perf_counter()
    stored = write(packed)
    return read + time.perf_counter() - began, stored, packed.shape[0]
