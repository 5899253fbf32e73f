"""``cscsr reconstruct``: spike store -> HR video store, over a Dask cluster.

Output frame j is centred on spike frame ``c_j = W//2 + j*K`` and made from frames
``[c_j - W//2, c_j + W//2]``. Each (frame, tile) is one task that reads its own window and
halo straight from Zarr (no overlap graph), reconstructs, crops the halo and writes its own
chunk, then records itself in ``committed``. Tasks are submitted in a bounded window. The
reconstructor (a model, for ``cscsr``) is built once per worker process and reused. A job
that starts its own local cluster runs its tasks in segments, each in a fresh process and
cluster (``pipeline.segments``), so that memory stays bounded over millions of tasks.

The gain is fixed for the whole recording before any task runs (``--gain``, else the store's,
else automatic exposure of the middle window), so tiles and frames agree with each other.
"""

import contextlib
import functools
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from pipeline.batches import in_bounded_window, window_size
from pipeline.cluster import dashboard_link, dask_client, scheduler_address
from pipeline.lease import check_free, held
from pipeline.progress import progress_bar
from pipeline.segments import Outcome, in_segments
from pipeline.spike_store import open_spike_store, read_frames
from pipeline.storage import claim_output, exists
from pipeline.video_store import TileWriter, committed_mask, create_video_store, open_video_store
from stages.colour import auto_gain
from stages.errors import InputError
from stages.reconstruct import METHODS, NETWORKS, Window, classic
from stages.tfp import tfp_rate
from stages.tiles import Tile, tile_grid

SEGMENT_TASKS = 10_000  # minutes of work on any real frame size; a fresh process and cluster cost ~5 s
DEFAULT_TILE = 256  # LR pixels: a 1000x1000 frame becomes 16 tasks of 1024x1024 HR


@dataclass(frozen=True)
class ReconstructOptions:
    method: str = "tfp"
    every: int = 41
    window: int = 41
    gain: float | None = None
    scale: int | None = None  # default: the store's scale, else 4
    tile: int = DEFAULT_TILE
    weights: str | None = None
    resume: bool = False
    overwrite: bool = False
    segment_tasks: int = SEGMENT_TASKS  # tasks per fresh cluster when the job starts its own (bounded memory)


@dataclass(frozen=True)
class Plan:
    """What every task shares: where to read and write, and how to reconstruct.

    Constant in size: a task's own centre and tile travel beside it, so task messages do not
    grow with the recording (the scheduler keeps recent messages).
    """

    spikes: str
    out: str
    method: str
    weights: str | None
    window: int
    every: int
    gain: float
    scale: int
    cfa: str
    reset: str
    tile: int  # LR tile side
    run: str  # unique per call: worker-side caches of opened stores never outlive their run

    def attrs(self) -> dict:
        """What the output store records (and ``--resume`` checks)."""
        return {"method": self.method, "weights": self.weights, "window": self.window, "every": self.every,
                "gain": self.gain, "scale": self.scale, "source": self.spikes, "cfa": self.cfa, "reset": self.reset,
                "tile_lr": self.tile}


def output_centres(n_frames: int, window: int, every: int) -> list[int]:
    """Centre spike frames of the output: W//2, W//2 + K, ... while the window fits."""
    half = window // 2
    return list(range(half, n_frames - half, every))


@functools.lru_cache(maxsize=4)
def reconstructor(method: str, weights: str | None):
    """Built once per worker process (this cache lives in the worker) and reused by its tasks:
    for the network, it is loaded from its weights once, onto the worker's GPU if any."""
    if method in NETWORKS:
        from cscsr.reconstructor import load_reconstructor

        return load_reconstructor(weights, self_ensemble=method == "cscsr-ensemble")
    return classic(method)


@functools.lru_cache(maxsize=4)
def _opened(spikes: str, out: str, run: str):
    """The input array and output writer, opened once per worker process and run (opening
    costs several metadata reads; a task's own work can be under a millisecond)."""
    return open_spike_store(spikes).spikes, TileWriter(out)


def _reconstruct_tile(plan: Plan, frames: tuple[tuple[int, int], ...], tile: Tile, ty: int, tx: int) -> int:
    """Task: for each (output frame, centre) read the window + halo of one tile; reconstruct the
    windows as one batch; crop, write and commit each frame's tile."""
    half = plan.window // 2
    spikes, writer = _opened(plan.spikes, plan.out, plan.run)
    method = reconstructor(plan.method, plan.weights)
    width = tile.rx1 - tile.rx0
    region = (slice(tile.ry0, tile.ry1), slice(tile.rx0 // 8, -(-tile.rx1 // 8)))
    windows = [Window(read_frames(spikes, plan.spikes, c - half, c + half + 1, region), width, plan.cfa, plan.reset,
                      plan.gain, plan.scale) for _, c in frames]
    ys, xs = tile.crop(plan.scale)
    for (index, _), image in zip(frames, method.many(windows)):
        writer.write(index, (ty, tx), (tile.y0 * plan.scale, tile.x0 * plan.scale), image[ys, xs])
    return len(frames)


def task_groups(n_frames: int, batch: int, tiles: tuple[int, int], done: np.ndarray) -> Iterator[tuple[range, int, int]]:
    """(frames, ty, tx) of every task still to run: a tile of ``batch`` consecutive output frames.

    Groups are fixed by frame number, not by what is left, so a resumed job runs every batch
    exactly as an uninterrupted one would (a batch's numbers can depend on its size); a group
    with any frame not committed runs whole. Generated as consumed: a terabyte capture has
    millions of tasks, and the job's process should not hold them all.
    """
    for start in range(0, n_frames, batch):
        frames = range(start, min(start + batch, n_frames))
        for ty in range(tiles[0]):
            for tx in range(tiles[1]):
                if not done[frames.start : frames.stop, ty, tx].all():
                    yield frames, ty, tx


def _auto_gain(spikes: str, centre: int, window: int, reset: str) -> float:
    """Task: the automatic exposure of the window around ``centre``, whole frame."""
    store = open_spike_store(spikes)
    half = window // 2
    return auto_gain(tfp_rate(store.read(centre - half, centre + half + 1), store.meta.width, reset))


def check_options(options: ReconstructOptions, n_frames: int) -> None:
    if options.method not in METHODS:
        raise InputError(f"unknown method {options.method!r}: expected one of {', '.join(METHODS)}")
    if options.window <= 0 or options.window % 2 == 0:
        raise InputError(f"--window must be a positive odd number of frames, got {options.window}")
    if options.window > n_frames:
        raise InputError(f"--window {options.window} is longer than the recording ({n_frames} frames)")
    if options.every <= 0:
        raise InputError(f"--every must be >= 1, got {options.every}")
    if options.gain is not None and not options.gain > 0:
        raise InputError(f"--gain must be > 0, got {options.gain}")
    if options.tile <= 0 or options.tile % 8:
        raise InputError(f"--tile must be a positive multiple of 8 LR pixels, got {options.tile}")
    if options.resume and options.overwrite:
        raise InputError("--resume and --overwrite contradict each other: choose one")
    if options.segment_tasks < 1:
        raise InputError(f"--segment-tasks must be >= 1, got {options.segment_tasks}")


def reconstruct(store_url: str, out: str, options: ReconstructOptions = ReconstructOptions(), *,
                workers: int | None = None, scheduler: str | None = None, client=None, progress: bool = True) -> dict:
    """Reconstruct the recording at ``store_url`` into an HR video store at ``out``.

    Runs on ``client`` if given, else on the scheduler named by ``scheduler`` (or the environment),
    else in segments of ``options.segment_tasks`` tasks, each on a fresh local cluster of
    ``workers`` (see :mod:`pipeline.segments`). Returns
    counts: output frames, tasks run now, tasks found already committed.
    """
    store = open_spike_store(store_url)
    meta = store.meta
    check_options(options, store.n_frames)
    scale = options.scale or int(store.attrs.get("scale", 4))
    method = reconstructor(options.method, options.weights)  # loads and checks the weights here too
    method.check(options.window, scale, meta.cfa)
    if options.resume and not exists(out):
        raise InputError(f"cannot resume: {out} does not exist")
    if options.resume:
        check_free(out)
    else:
        claim_output(out, overwrite=options.overwrite, flag="--resume or --overwrite")
    centres = output_centres(store.n_frames, options.window, options.every)
    grid = tile_grid(meta.height, meta.width, options.tile, method.halo)

    with contextlib.ExitStack() as stack:
        if client is None and scheduler_address(scheduler):  # a long-lived cluster: connect once, before any output
            client = stack.enter_context(dask_client(scheduler=scheduler))
        gain = options.gain or meta.gain
        if gain is None:  # one window: on the cluster if there is one, else here (not worth a cluster of its own)
            args = (store_url, centres[len(centres) // 2], options.window, meta.reset)
            gain = client.submit(_auto_gain, *args).result() if client else _auto_gain(*args)
        weights = getattr(method, "weights", options.weights)  # the file actually used: the shipped one by default
        plan = Plan(store_url, out, options.method, weights, options.window, options.every, float(gain),
                    scale, meta.cfa, meta.reset, options.tile, uuid.uuid4().hex)
        done = _prepare_output(plan, options.resume, centres, grid, (meta.height * scale, meta.width * scale))
        groups = task_groups(len(centres), getattr(method, "batch", 1), (len(grid), len(grid[0])), done)
        work = functools.partial(run_groups, plan=plan, centres=centres, grid=grid)
        with held(out), progress_bar(f"reconstruct {options.method}", len(centres), enabled=progress) as advance:
            if client:
                if progress and (link := dashboard_link(client)):
                    print(f"dashboard: {link}")
                outcomes = work(client, groups)
            else:  # our own local cluster: a fresh one per segment keeps memory bounded
                outcomes = in_segments(work, groups, options.segment_tasks, workers=workers, show_dashboard=progress)
            failed = _tally(outcomes, done, advance)
    if failed:
        raise JobIncomplete(out, failed, len(centres))
    open_video_store(out, writable=True).attrs["state"] = "complete"
    skipped = int(done.sum())
    return {"frames": len(centres), "tasks_run": done.size - skipped, "tasks_skipped": skipped}


class JobIncomplete(RuntimeError):
    """Some tasks raised: which output frames are missing and why; the rest is committed."""

    def __init__(self, out: str, failed: dict[int, str], n_frames: int):
        frames = sorted(failed)
        shown = ", ".join(map(str, frames[:20])) + (", ..." if len(frames) > 20 else "")
        first = failed[frames[0]]
        super().__init__(f"{len(frames)} of {n_frames} output frames failed (frames {shown}; frame {frames[0]}: "
                         f"{first}); the other frames are committed in {out}: fix the cause and run again with --resume")
        self.failed = failed


def run_groups(client, groups: Iterable, *, plan: Plan, centres: list[int], grid) -> Iterator[Outcome]:
    """Submit ``groups`` in a bounded window; yield each one's outcome as it finishes."""
    shared = client.scatter(plan, broadcast=True)  # sent to each worker once, not with every task
    group_of = {}  # future key -> (frames, ty, tx) (cheaper than fetching each result)

    def submissions():
        for frames, ty, tx in groups:
            future = client.submit(_reconstruct_tile, shared, tuple((i, centres[i]) for i in frames), grid[ty][tx],
                                   ty, tx, pure=False)
            group_of[future.key] = (frames, ty, tx)
            yield future

    for future in in_bounded_window(submissions(), window_size(client)):
        frames, ty, tx = group_of.pop(future.key)
        error = None
        if future.status != "finished":  # the task raised: report it, go on with the others
            error = " ".join(str(future.exception()).split()) or type(future.exception()).__name__
        yield Outcome(frames.start, frames.stop, ty, tx, error)


def _tally(outcomes: Iterable[Outcome], done: np.ndarray, advance) -> dict[int, str]:
    """Count finished tiles per output frame (a frame is done when all its tiles are); -> {frame: error}."""
    failed = {}
    remaining = done.shape[1] * done.shape[2] - done.sum(axis=(1, 2))  # (frames,) tiles still to come
    advance(int((remaining == 0).sum()))
    for outcome in outcomes:
        frames = range(outcome.start, outcome.stop)
        if outcome.error is not None:
            failed.update({index: f"tile ({outcome.ty}, {outcome.tx}): {outcome.error}" for index in frames})
            continue
        for index in frames:
            if not done[index, outcome.ty, outcome.tx]:
                remaining[index] -= 1
                if remaining[index] == 0:
                    advance(1)
    return failed


def _prepare_output(plan: Plan, resume: bool, centres: list[int], grid: list[list[Tile]], hr_size: tuple[int, int]):
    """Create the output (metadata first), or check a resumed one matches; return the commit mask."""
    tiles = (len(grid), len(grid[0]))
    first = grid[0][0]
    tile_hr = ((first.y1 - first.y0) * plan.scale, (first.x1 - first.x0) * plan.scale)
    if resume:
        group = open_video_store(plan.out, writable=True)
        recorded = {k: group.attrs.get(k) for k in plan.attrs()}
        expected = plan.attrs()
        changed = [k for k in expected if recorded[k] != expected[k]]
        if changed or group["video"].shape[0] != len(centres):
            what = ", ".join(f"{k} {recorded[k]!r} -> {expected[k]!r}" for k in changed) or "frame count"
            raise InputError(f"cannot resume {plan.out}: it was made with other parameters ({what})")
        return committed_mask(group)
    create_video_store(plan.out, centres=centres, hr_size=hr_size, tile_hr=tile_hr, tiles=tiles, attrs=plan.attrs())
    return np.zeros((len(centres), *tiles), bool)

