"""A spike store written by tasks, as every job and ``lazy.to_spikes`` writes one: :func:`write_store`.

The store is claimed (``pipeline.stores.lease``), replaced only as ``pipeline.stores.outputs`` allows, and written
metadata first (``state: "writing"``, every task -1 in ``committed``); then one task per run of whole chunks
(:class:`SpikeWrites`: no two tasks share a chunk) packs its frames, writes them and records itself committed (its
spike count); the store is finished (spike count, identity, consolidated metadata, ``state: "complete"``) only once
every task is committed. A failed run keeps what it committed when the caller says so, and a resume runs only the
tasks not committed, cut as the store was. The tasks run in bounded rounds (``pipeline.compute.executor.computed``)
on the given client, else on Dask's own scheduler.

What the spikes are is the caller's: a dask graph of bits (``lazy.to_spikes``, the ``simulate`` job: a producer
that makes its blocks packed names them :func:`packed_key`, and each write takes them as they are), or a raw
capture read by byte range (``pipeline.jobs.ingest.CaptureWrites``, the ``ingest`` job and ``lazy.to_spikes`` of
``lazy.open_capture``), which overrides how the tasks run and what a resume compares.
"""

import contextlib
import dataclasses

import numpy as np
import zarr
from dask.base import tokenize
from dask.highlevelgraph import HighLevelGraph

from pipeline.compute.executor import computed
from pipeline.compute.hold import hold_point
from pipeline.compute.progress import progress_bar
from pipeline.stores.ground_truth import declare_truth
from pipeline.stores.lease import check_free, claimed, held
from pipeline.stores.outputs import SPIKE_STORE, new_output
from pipeline.stores.spike_store import (COMMITTED, SPIKES, SpikeMeta, SpikeStore, SpikeStoreWriter, chunk_frames_for,
                                         open_spike_store, write_region)
from pipeline.stores.storage import recorded
from stages.capture.bits import count_spikes, pack_rows
from stages.errors import InputError, describe

COMMITTED_UNITS = "spikes in the task's frames, written once they are stored; -1 = not committed"
WRITES_AT_ONCE = 32  # write tasks a round (computed): what a long recording keeps in flight, and in the scheduler


@dataclasses.dataclass(frozen=True)
class Truth:
    """The ground truth a store of simulated spikes records beside them: pictures (HR ``size``) at spike frames
    ``centres``, and a camera path's flow between them (``with_flow``), written by the tasks ``keys`` of ``graph``."""

    centres: list[int]
    size: tuple[int, int]
    with_flow: bool
    graph: dict
    keys: list


class SpikesIncomplete(RuntimeError):
    """Some :func:`to_spikes` tasks failed: the others are committed in the store, for ``resume=True``."""


def packed_key(bits, k: int) -> tuple[str, int]:
    """The key under which a graph of ``bits`` (t, y, x) bool that makes its blocks packed holds block ``k`` packed
    (t, y, ceil(x / 8)) uint8 (the simulator's: ``pipeline.jobs.simulate.fired_spikes``): a write of that block takes
    it as it is, never unpacked and packed again."""
    return f"{bits.name}-packed", k


class SpikeWrites:
    """Spikes of ``meta`` and ``n_frames`` frames cut into the tasks that write them into a store at ``url``: its
    chunks of ``chunk`` frames, task ``i`` its frames ``[i * task_frames, (i + 1) * task_frames)``; ``resumed``: the
    store to finish as the caller's checks opened it, before the claim, else None; ``record``: what ``committed``
    records besides its units and cut; ``again``: how the caller says to start again (``overwrite=True``)."""

    again = "overwrite=True"

    def __init__(self, url: str, meta: SpikeMeta, n_frames: int, chunk_frames: int | None, task_frames: int | None):
        self.url, self.meta, self.n_frames = recorded(url), meta, n_frames  # as workers in any folder find it
        # as the caller gave them (None: the default, or the store's cut), at most the whole recording
        chunk_frames, task_frames = (None if n is None else min(n, n_frames) for n in (chunk_frames, task_frames))
        self.asked = (chunk_frames, task_frames)
        self.resumed: SpikeStore | None = None
        self.record: dict = {}
        self.cut(chunk_frames or chunk_frames_for(meta, n_frames), task_frames)

    def cut(self, chunk: int, task_frames: int | None) -> None:
        """Chunks of ``chunk`` frames, tasks of ``task_frames`` rounded up to whole chunks (None: one chunk)."""
        self.chunk = chunk
        self.task_frames = chunk * -(-(task_frames or chunk) // chunk)
        self.n_tasks = -(-self.n_frames // self.task_frames)

    def frames_of(self, index: int) -> int:
        """How many frames task ``index`` writes (the last may hold fewer)."""
        return min(self.task_frames, self.n_frames - index * self.task_frames)

    def same_cut(self, a: int, b: int) -> bool:
        """Whether tasks of ``a`` and of ``b`` frames cut these spikes alike: equal, or each one task of them all (a
        store may record a task larger than its recording, as it was asked)."""
        return a == b or min(a, b) >= self.n_frames

    def resumable(self, store: SpikeStore | None = None) -> np.ndarray:
        """Cut as the unfinished store at ``url`` was (a cut the caller gives must be that one); refuse a store of
        other spikes (:meth:`check_same`) or frames; -> the spike counts of its tasks (-1: not committed).
        ``store``: the store at ``url`` as the caller opened it, else opened now (under the claim: as it is then).
        Reads, never writes."""
        if store is None:
            store = open_spike_store(self.url, allow_incomplete=True)  # a video store, a folder, ...: refused by name
        committed = store.group[COMMITTED] if COMMITTED in store.group else None
        if not isinstance(committed, zarr.Array):
            raise InputError(f"cannot resume {self.url}: it holds no record of its tasks (a store written by a job "
                             f"that records none): write it again with {self.again}")
        self.check_same(store, dict(committed.attrs))
        asked_chunk, asked_task = self.asked
        recorded_task = committed.attrs.get("task_frames")
        recorded_ok = isinstance(recorded_task, int) and not isinstance(recorded_task, bool) and recorded_task > 0
        if recorded_ok and asked_task is not None and self.same_cut(recorded_task, asked_task):
            asked_task = recorded_task
        self.cut(store.spikes.chunks[0], asked_task or (recorded_task if recorded_ok else None))
        if (store.n_frames != self.n_frames or asked_chunk not in (None, self.chunk) or not recorded_ok
                or self.task_frames != recorded_task or committed.shape != (self.n_tasks,)):
            raise InputError(self.cut_refused(store, committed.shape[0], recorded_task))
        return committed[:].astype(np.int64)

    def cut_refused(self, store: SpikeStore, tasks: int, recorded_task) -> str:
        """Why ``store`` (of ``tasks`` tasks of ``recorded_task`` frames) is not resumed with these spikes' cut."""
        asked_chunk, asked_task = self.asked
        return (f"cannot resume {self.url}: it holds {store.n_frames} frames in chunks of {store.spikes.chunks[0]}, "
                f"{tasks} tasks of {recorded_task} frames; these spikes: {self.n_frames} frames"
                f"{'' if asked_chunk is None else f', chunk_frames={asked_chunk}'}"
                f"{'' if asked_task is None else f', task_frames={asked_task}'}: give those, or write it again with "
                f"{self.again}")

    def check_same(self, store: SpikeStore, found: dict) -> None:
        """Refuse to resume ``store`` (``found``: its ``committed`` attributes) with spikes of other attributes."""
        was, now = store.meta.attrs(), self.meta.attrs()
        if changed := [f"{k} {was.get(k)!r} -> {now.get(k)!r}" for k in sorted(was | now) if was.get(k) != now.get(k)]:
            raise InputError(f"cannot resume {self.url}: it records other attributes ({', '.join(changed)}): give "
                             f"the spikes it was written from, or write it again with {self.again}")

    def guarded(self) -> contextlib.AbstractContextManager:
        """What a new store's writes run under (the capture's: removed if found damaged); nothing here."""
        return contextlib.nullcontext()

    def run(self, bits, todo: list[int], advance, client) -> np.ndarray:
        """Tasks ``todo`` of ``bits`` (t, y, x) bool on ``client`` (else Dask's own scheduler), ``advance(frames)`` as
        each is written; -> their spike counts. Raises :class:`SpikesIncomplete` if any fails (what the others
        committed stays)."""
        name = f"to-spikes-{tokenize(bits.name, self.url, self.task_frames, todo)}"
        if bits.chunks[0] == tuple(map(self.frames_of, range(self.n_tasks))) and packed_key(bits, 0) in bits.dask:
            blocks = bits  # made packed, a block a task: each task writes them as they are
            layer = {(name, j): (write_packed, packed_key(bits, index), self.url, index * self.task_frames, index)
                     for j, index in enumerate(todo)}
        else:
            blocks = bits.rechunk((self.task_frames, -1, -1))
            layer = {(name, j): (_write_task, (blocks.name, index, 0, 0), self.url, index * self.task_frames, index)
                     for j, index in enumerate(todo)}
        graph = HighLevelGraph.from_collections(name, layer, dependencies=[blocks])
        frames = {(name, j): self.frames_of(index) for j, index in enumerate(todo)}
        try:
            return np.concatenate(computed(graph, frames, advance, client, at_once=WRITES_AT_ONCE))
        except Exception as error:
            raise self.incomplete(describe(error)) from error

    def incomplete(self, cause: str) -> Exception:
        """The error of a run whose tasks did not all commit, ``cause`` the first failure."""
        done = int((open_spike_store(self.url, allow_incomplete=True).group[COMMITTED][:] >= 0).sum())
        return SpikesIncomplete(f"to_spikes {self.url}: {done} of {self.n_tasks} tasks committed, the others not "
                                f"({cause}): fix the cause and call to_spikes again with resume=True")


def write_store(writes: SpikeWrites, bits, *, client, overwrite: bool, resume: bool, truth: Truth | None,
                progress: bool, title: str, keep_partial: bool, flag: str) -> dict:
    """Write ``bits`` (t, y, x) bool, as ``writes`` cuts and runs them, into a new spike store (``resume``: finish the
    one there), then ``truth``, on ``client`` (else Dask's own scheduler; a function: the cluster it starts once the
    store is claimed, closed before a failed store is removed); every check of the caller's made before.
    ``keep_partial``: a store left unfinished stays, for a resume; ``flag``: how the caller says ``--overwrite``.
    -> ``attrs`` (the store's final attributes), ``frames``, ``spikes``, ``tasks``, ``tasks_run``,
    ``tasks_skipped``. Raises :class:`SpikesIncomplete` (or the writes' own error) if a task fails."""
    url = writes.url
    with claimed(url), contextlib.ExitStack() as stack:  # one job per store, taken before the store is touched
        if resume:
            check_free(url)  # and no live lease (a job on a machine that shares no claim file with us)
        stack.enter_context(new_output(url, overwrite=overwrite, kind=SPIKE_STORE, flag=flag, resume=resume,
                                       keep_partial=keep_partial))
        if not resume:
            stack.enter_context(writes.guarded())
        if callable(client):  # no task writes once a failed store is removed
            client = stack.enter_context(client())
        if resume:
            counts = writes.resumable()  # again, under the claim
            writer = SpikeStoreWriter.reopened(url)
        else:
            writer = SpikeStoreWriter(url, writes.meta, writes.n_frames, chunk_frames=writes.chunk)
            writer.add_array(COMMITTED, (writes.n_tasks,), (1,), np.int64, ("task",),
                             {"units": COMMITTED_UNITS, "task_frames": writes.task_frames, **writes.record},
                             fill_value=-1)
            counts = np.full(writes.n_tasks, -1, np.int64)
            if truth is not None:
                declare_truth(writer, truth.centres, truth.size, float(writes.meta.fps), with_flow=truth.with_flow)
        todo = [index for index in range(writes.n_tasks) if counts[index] < 0]
        if todo:
            to_write = sum(writes.frames_of(index) for index in todo)
            with held(url), progress_bar(title, writes.n_frames, done=writes.n_frames - to_write,
                                         enabled=progress) as advance:
                counts[todo] = writes.run(bits, todo, advance, client)
        if truth is not None and writer.group.attrs.get("state") != "complete":
            with held(url):
                computed(truth.graph, dict.fromkeys(truth.keys, 0), lambda frames: None, client)
        if writer.group.attrs.get("state") != "complete":
            writer.finish(spike_count=int(counts.sum()))
    return {"attrs": dict(writer.group.attrs), "frames": writes.n_frames, "spikes": int(counts.sum()),
            "tasks": writes.n_tasks, "tasks_run": len(todo), "tasks_skipped": writes.n_tasks - len(todo)}


def _write_task(bits: np.ndarray, url: str, start: int, index: int) -> np.ndarray:
    """Task ``index``: pack frames ``[start, start + n)`` (n, y, x) bool, write their chunks of ``spikes``, then record
    the task committed (its spike count); -> that count, shape (1,). Run again, it writes the same bytes."""
    return write_packed(pack_rows(bits), url, start, index)


def write_packed(packed: np.ndarray, url: str, start: int, index: int) -> np.ndarray:
    """Task ``index``: :func:`_write_task` of frames packed (n, y, ceil(x / 8))."""
    hold_point()  # inert unless a fault test asks (pipeline.compute.hold)
    write_region(url, SPIKES, start, packed)
    count = np.array([count_spikes(packed)], np.int64)
    write_region(url, COMMITTED, index, count)
    return count

