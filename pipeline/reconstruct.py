"""``cscsr reconstruct``: spike store -> HR video store, over a Dask cluster.

Output frame j is centred on spike frame ``c_j = W//2 + j*K`` and made from frames
``[c_j - W//2, c_j + W//2]``. A task is a few consecutive output frames (the method's
``batch``) of one tile; it reads its windows and halo straight from Zarr (no overlap graph),
reconstructs, crops the halo and writes one chunk per (frame, tile), each then recorded in
``committed``. The plan (``pipeline.reconstruct_plan``) is frozen data; ``pipeline.executor`` submits
its tasks in a bounded window. The reconstructor (a model, for
``cscsr``) is built once per worker process and reused. A job that starts its own local
cluster runs its tasks in segments, each in a fresh process and cluster
(``pipeline.executor``), so that memory stays bounded over millions of tasks.

GPU workers: when the cluster has workers that advertise the ``GPU`` resource (one per GPU,
``pipeline.cluster``), network tasks ask for a share of one (``GPU_SHARE``), so they run there and
only there, several at once: one on the device while the others read and write. On GPU workers
the default weights are ``full`` (``lite`` on CPUs), and the default tile is the largest that the
GPU's memory holds (the whole frame where it fits, several frames a pass), else tasks take
several tiles of the same shape (``gpu_batch`` windows in all) as one batch; classic tasks run
anywhere. Without such workers tasks are cut and placed as above.

The gain is fixed for the whole recording before any task runs (``--gain``, else the store's,
else automatic exposure of the middle window), so tiles and frames agree with each other.
"""

import contextlib
import dataclasses
import functools
import sys
import threading
import uuid
from collections.abc import Iterable, Iterator
from typing import NamedTuple

import numpy as np

from pipeline.cluster import (GPU, GPU_SHARE, check_scheduler, check_workers, dashboard_link, dask_client,
                              scheduler_address, visible_gpus)
from pipeline.hold import hold_point
from pipeline.lease import check_free, claimed, held
from pipeline.progress import progress_bar
from pipeline.reconstruct_plan import (DEFAULT_TILE, DEFAULT_WEIGHTS, GPU_BATCH, MADE_FROM, Plan, ReconstructOptions,
                                      made_from, task_groups, tile_blocks)
from pipeline.executor import failure, in_segments, submitted
from pipeline.spike_store import SpikeStore, open_spike_store, read_frames
from pipeline.outputs import VIDEO_STORE, new_output
from pipeline.storage import check_apart, exists, recorded, remove_partial_writes
from pipeline.video_store import VIDEO, TileWriter, committed_mask, create_video_store, open_video_store
from stages.colour import auto_gain
from stages.errors import InputError
from stages.methods import NETWORKS, Reconstructor, Window, classic, output_centres
from stages.tfp import tfp_rate
from stages.tiles import Tile, device_tile, tile_grid

def reconstructor(method: str, weights: str | None, precision: str | None = "fp32", backend: str | None = "torch",
                  weights_sha256: str | None = None, *, fast_gpu: bool = False,
                  device: str | None = None) -> Reconstructor:
    """The method, built once per process and file contents (the cache lives in each worker) and reused
    by its tasks: for the network, loaded from its weights once, onto the worker's GPU if any (or onto
    ``device``: the job's own process checks the weights on the CPU). Keyed by the weights' SHA-256 (a
    job's tasks pass the one the job was planned with; else the file is hashed now), so a long-lived
    worker or watcher never runs a model cached from an older file at that path."""
    if method not in NETWORKS:
        with _building:
            return _built(method, None, None, None, None)
    from cscsr.weights_io import weights_file
    from cscsr.weights_io import weights_sha256 as sha256_of

    with _building:  # the worker's tasks in flight start together: one loads, the others wait for its network
        return _built(method, weights, precision, backend, weights_sha256 or sha256_of(weights_file(weights)),
                      fast_gpu, device)


_building = threading.Lock()


@functools.lru_cache(maxsize=4)
def _built(method: str, weights: str | None, precision: str | None, backend: str | None,
           weights_sha256: str | None, fast_gpu: bool = False, device: str | None = None) -> Reconstructor:
    if method in NETWORKS:
        from cscsr.reconstructor import load_reconstructor

        loaded = load_reconstructor(weights, device, self_ensemble=method == "cscsr-ensemble",
                                    precision=precision or "fp32", backend=backend or "torch", fast_gpu=fast_gpu)
        if loaded.weights_sha256 != weights_sha256:
            raise InputError(f"weights file {loaded.weights} changed since the job started (sha256 "
                             f"{weights_sha256[:12]}… -> {loaded.weights_sha256[:12]}…): run the job again")
        return loaded
    return classic(method)


@functools.lru_cache(maxsize=4)
def _opened(spikes: str, out: str, run: str):
    """The input array and output writer, opened once per worker process and run (opening
    costs several metadata reads; a task's own work can be under a millisecond)."""
    return open_spike_store(spikes).spikes, TileWriter(out)


def _reconstruct_tiles(plan: Plan, frames: tuple[tuple[int, int], ...],
                       tiles: tuple[tuple[int, int, Tile], ...]) -> int:
    """Task: for each tile (ty, tx, tile) and each (output frame, centre), read the window + halo;
    reconstruct each tile's windows as one batch (on a GPU, the windows of all tiles of one shape
    together); crop, write and commit each frame's tile."""
    hold_point()  # inert unless a fault test asks (pipeline.hold)
    half = plan.window // 2
    spikes, writer = _opened(plan.spikes, plan.out, plan.run)
    method = reconstructor(plan.method, plan.weights, plan.precision, plan.backend, plan.weights_sha256,
                           fast_gpu=bool(plan.fast_gpu))
    windows = []
    for _, _, tile in tiles:
        region = (slice(tile.ry0, tile.ry1), slice(tile.rx0 // 8, -(-tile.rx1 // 8)))
        windows.append([Window(read_frames(spikes, plan.spikes, c - half, c + half + 1, region), tile.rx1 - tile.rx0,
                               plan.cfa, plan.reset, plan.gain, plan.scale) for _, c in frames])
    first = frames[0][0]  # a task's output frames are consecutive
    for (ty, tx, tile), images in zip(tiles, method.many_tiles(windows, plan.gpu_batch)):
        ys, xs = tile.crop(plan.scale)
        writer.write_frames(first, (ty, tx), (tile.y0 * plan.scale, tile.x0 * plan.scale),
                            [image[ys, xs] for image in images])  # compressed and stored together
    return len(frames) * len(tiles)


def _auto_gain(spikes: str, centre: int, window: int, reset: str) -> float:
    """Task: the automatic exposure of the window around ``centre``, whole frame."""
    store = open_spike_store(spikes)
    half = window // 2
    return auto_gain(tfp_rate(store.read(centre - half, centre + half + 1), store.meta.width, reset))


def check_options(options: ReconstructOptions, n_frames: int) -> None:
    options.check()
    if options.window > n_frames:
        raise InputError(f"--window {options.window} is longer than the recording ({n_frames} frames)")


def network_options(options: ReconstructOptions) -> tuple[str | None, str | None]:
    """(precision, backend) of a network job; (None, None) for the classic methods, which have neither."""
    return (options.precision, options.backend) if options.method in NETWORKS else (None, None)


def checked_method(store: SpikeStore, options: ReconstructOptions) -> tuple[int, Reconstructor]:
    """Every check of a job on ``store`` that needs no output: the options against the recording, the
    scale (``--scale``, else the store's, else 4) and the method, its weights loaded (on the CPU: this
    process only checks them; without ``--weights``, those for CPU workers). -> (scale, method)."""
    check_options(options, store.n_frames)
    scale = options.scale if options.scale is not None else int(store.attrs.get("scale", 4))
    weights = options.weights or (DEFAULT_WEIGHTS["cpu"] if options.method in NETWORKS else None)
    method = reconstructor(options.method, weights, *network_options(options), device="cpu")  # loads and checks them
    method.check(options.window, scale, store.meta.cfa)
    return scale, method


class Placement(NamedTuple):
    """Where a job's network tasks run: on GPU workers or not, and the memory of the smallest GPU (None
    when not known: no GPU, or workers that advertise one without CUDA, as in the tests)."""

    gpus: bool
    memory: int | None


def placement(options: ReconstructOptions, client) -> Placement:
    """On ``client``'s GPU workers if it has any, else (no client: a local cluster) on this machine's GPUs."""
    if options.method not in NETWORKS or options.backend != "torch":
        return Placement(False, None)
    if client is None:
        gpus = visible_gpus()
        if not gpus:
            return Placement(False, None)
        import torch

        return Placement(True, min(torch.cuda.get_device_properties(i).total_memory for i in range(gpus)))
    addresses = [address for address, worker in client.scheduler_info()["workers"].items()
                 if (worker.get("resources") or {}).get(GPU, 0) >= 1]
    if not addresses:
        return Placement(False, None)
    sizes = [size for size in client.run(gpu_memory_bytes, workers=addresses).values() if size]
    return Placement(True, min(sizes) if sizes else None)


def gpu_memory_bytes() -> int | None:
    """Run on a GPU worker: the memory of its GPU (pinned, it sees only its own, as device 0); None without one."""
    import torch

    return torch.cuda.get_device_properties(0).total_memory if torch.cuda.is_available() else None


def placed(options: ReconstructOptions, where: Placement, recorded: dict) -> ReconstructOptions:
    """The options with the weights that depend on where the network runs filled in: ``--weights``, else
    what a resumed output records, else ``full`` on GPU workers and ``lite`` on CPUs. Chosen once per
    job; the output records it."""
    if options.method not in NETWORKS or options.weights:
        return options
    return dataclasses.replace(options, weights=recorded.get("weights") or DEFAULT_WEIGHTS["gpu" if where.gpus else "cpu"])


def sized(options: ReconstructOptions, where: Placement, method: Reconstructor, shape: tuple[int, int],
          recorded: dict) -> ReconstructOptions:
    """The options with the tile and the windows per pass filled in: ``--tile`` (else what a resumed output
    records), ``--gpu-batch``; else on GPUs of known memory what the smallest holds
    (:func:`stages.tiles.device_tile`: the whole frame where it fits), and otherwise ``DEFAULT_TILE`` and
    ``GPU_BATCH``."""
    tile, batch = options.tile or recorded.get("tile_lr"), options.gpu_batch
    if where.gpus and where.memory and (tile is None or batch is None):
        from cscsr.device_memory import bytes_per_lr_pixel, usable_bytes

        fitted = device_tile(*shape, method.halo, usable_bytes(where.memory),
                             bytes_per_lr_pixel(method.model.config.name, options.precision), GPU_BATCH)
        tile, batch = tile or fitted[0], batch or fitted[1]
    return dataclasses.replace(options, tile=tile or DEFAULT_TILE, gpu_batch=batch or GPU_BATCH)


def _recorded_attrs(out: str) -> dict:
    """What the output to resume records, or nothing if it cannot be read as a video store (the resume's
    own checks then refuse it, in their words)."""
    try:
        return dict(open_video_store(out).attrs)
    except Exception:  # noqa: BLE001 - refused later, with the reason, by new_output and _prepare_output
        return {}


def reconstruct(store_url: str, out: str, options: ReconstructOptions = ReconstructOptions(), *,
                workers: int | None = None, scheduler: str | None = None, client=None, progress: bool = True) -> dict:
    """Reconstruct the recording at ``store_url`` into an HR video store at ``out``.

    Runs on ``client`` if given, else on the scheduler named by ``scheduler`` (or the environment),
    else in segments of ``options.segment_tasks`` tasks, each on a fresh local cluster of
    ``workers`` (see :mod:`pipeline.executor`). Returns
    counts: output frames, tasks run now, tasks found already committed.
    """
    check_workers(workers)
    options.check()
    check_apart(out, store_url, options.weights)
    store = open_spike_store(store_url)
    meta = store.meta
    checked_method(store, options)  # the options and the weights given, before any cluster
    if options.resume and not exists(out):
        raise InputError(f"cannot resume: {out} does not exist")
    if client is None:
        check_scheduler(scheduler)  # a named scheduler answers (within seconds) before OUT is claimed or replaced

    with contextlib.ExitStack() as stack:
        if client is None and scheduler_address(scheduler):  # a long-lived cluster: connect once, before any output
            client = stack.enter_context(dask_client(scheduler=scheduler))
        where = placement(options, client)
        found = _recorded_attrs(out) if options.resume else {}
        options = placed(options, where, found)
        scale, method = checked_method(store, options)  # the weights by where the network runs
        options = sized(options, where, method, (meta.height, meta.width), found)
        precision, backend = network_options(options)
        centres = output_centres(store.n_frames, options.window, options.every)
        grid = tile_grid(meta.height, meta.width, options.tile, method.halo)
        stack.enter_context(claimed(out))  # one job per output, taken atomically before OUT is touched
        if options.resume:
            check_free(out)  # and no live lease (a job on a machine that shares no claim file with us)
        # only one of our stores is replaced, and kept aside until the new one is complete (pipeline.outputs); a
        # failed job's new store stays for --resume
        stack.enter_context(new_output(out, overwrite=options.overwrite, kind=VIDEO_STORE,
                                       flag="--resume or --overwrite", resume=options.resume, keep_partial=True))
        gain = options.gain or meta.gain
        if gain is None:  # one window: on the cluster if there is one, else here (not worth a cluster of its own)
            args = (store_url, centres[len(centres) // 2], options.window, meta.reset)
            gain = client.submit(_auto_gain, *args).result() if client else _auto_gain(*args)
        # the spike store as workers find it, whatever their working directory (and as the output records it)
        plan = Plan(recorded(store_url), out, options.method, method.weights, options.window, options.every, float(gain),
                    scale, meta.cfa, meta.reset, options.tile, uuid.uuid4().hex, precision, options.gpu_batch, backend,
                    fast_gpu=options.fast_gpu and where.gpus if options.method in NETWORKS else None,
                    **made_from(store, method.weights_sha256))  # what --resume checks beside the paths
        batch = method.batch
        done = _prepare_output(plan, options.resume, centres, grid, (meta.height * scale, meta.width * scale),
                               fps=meta.fps / options.every)
        blocks = tile_blocks(grid, max(1, options.gpu_batch // batch) if where.gpus else 1)
        groups = task_groups(len(centres), batch, blocks, done)
        work = functools.partial(run_groups, plan=plan, centres=centres, grid=grid,
                                 resources={GPU: GPU_SHARE} if where.gpus else None)
        with held(out), progress_bar(f"reconstruct {options.method}", len(centres), enabled=progress) as advance:
            if client:
                if progress and (link := dashboard_link(client)):
                    print(f"dashboard: {link}", file=sys.stderr)  # never mixed with results on stdout
                outcomes = work(client, groups)
            else:  # our own local cluster: a fresh one per segment keeps memory bounded
                outcomes = in_segments(work, groups, options.segment_tasks, workers=workers, show_dashboard=progress)
            failed = _tally(outcomes, done, advance)
        if failed:
            raise JobIncomplete(out, failed, len(centres))
        remove_partial_writes(out)  # a worker killed mid-write leaves its temporary file
        open_video_store(out, writable=True).attrs["state"] = "complete"  # still under the claim
    skipped = int(done.sum())
    return {"frames": len(centres), "tasks_run": done.size - skipped, "tasks_skipped": skipped}


class JobIncomplete(RuntimeError):
    """Some tasks raised: which output frames are missing and why; the rest is committed."""

    def __init__(self, out: str, failed: dict[int, str], n_frames: int):
        frames = sorted(failed)
        shown = ", ".join(map(str, frames[:20])) + (", ..." if len(frames) > 20 else "")
        first = failed[frames[0]]
        causes = {why.split("): ", 1)[-1] if why.startswith("tile (") else why for why in failed.values()}
        if len(causes) == 1 and len(frames) > 1:  # one cause (a full disk): named once, not per tile
            first = f"each: {causes.pop()}"
        else:
            first = f"frame {frames[0]}: {first}"
        rest = (f"the other frames are committed in {out}" if len(frames) < n_frames
                else f"what was written is kept in {out}")
        super().__init__(f"{len(frames)} of {n_frames} output frames failed (frames {shown}; {first}); {rest}: "
                         f"fix the cause and run again with --resume")
        self.failed = failed


class Outcome(NamedTuple):
    """One finished task: output frames ``start:stop`` of tile (ty, tx), and its error if it raised."""

    start: int
    stop: int
    ty: int
    tx: int
    error: str | None


def run_groups(client, groups: Iterable, *, plan: Plan, centres: list[int], grid,
               resources: dict | None = None) -> Iterator[Outcome]:
    """Run the plan's ``groups`` on ``client`` (``pipeline.executor``), each task needing ``resources``
    (e.g. ``{"GPU": 1}``: only workers that advertise them run it); yield the outcome of each of a
    group's tiles as it finishes."""
    def submit(group):  # the plan travels in each task (scattered data dies with the workers holding it)
        frames, block = group
        return client.submit(_reconstruct_tiles, plan, tuple((i, centres[i]) for i in frames),
                             tuple((ty, tx, grid[ty][tx]) for ty, tx in block), pure=False, resources=resources)

    for (frames, block), future in submitted(client, groups, submit, idempotent=True):
        error = failure(future)  # the task raised, or the cluster failed it: report it, go on with the others
        for ty, tx in block:
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


def _prepare_output(plan: Plan, resume: bool, centres: list[int], grid: list[list[Tile]], hr_size: tuple[int, int],
                    fps: float | None = None):
    """Create the output (metadata first), or check a resumed one matches; return the commit mask."""
    tiles = (len(grid), len(grid[0]))
    first = grid[0][0]
    tile_hr = ((first.y1 - first.y0) * plan.scale, (first.x1 - first.x0) * plan.scale)
    if resume:
        group = open_video_store(plan.out, writable=True)
        expected = plan.attrs()
        if other := plan.other_data(dict(group.attrs)):  # the same paths, another recording or other weights
            raise InputError(f"cannot resume {plan.out}: {other}")
        network = plan.method in NETWORKS  # stores from before --precision and --backend:
        before = {"precision": "fp32" if network else None, "backend": "torch" if network else None,
                  "fast_gpu": False if network else None}
        # stores from before the record of what they were made from: resumed on the paths alone, as they were
        # then, and the record added now (a later resume checks it)
        adopted = {k: expected[k] for k in MADE_FROM if k not in group.attrs}
        before.update(adopted)
        found = {k: group.attrs.get(k, before.get(k)) for k in expected}
        if isinstance(found["source"], str):  # stores from before sources were absolute: as seen from here
            found["source"] = recorded(found["source"])
        changed = [k for k in expected if found[k] != expected[k]]
        if changed or group[VIDEO].shape[0] != len(centres):
            what = ", ".join(f"{k} {found[k]!r} -> {expected[k]!r}" for k in changed) or "frame count"
            raise InputError(f"cannot resume {plan.out}: it was made with other parameters ({what})")
        if adopted:
            group.attrs.update(adopted)
        return committed_mask(group)
    create_video_store(plan.out, centres=centres, hr_size=hr_size, tile_hr=tile_hr, tiles=tiles,
                       attrs=plan.attrs(), fps=fps)
    return np.zeros((len(centres), *tiles), bool)

