"""``cscsr reconstruct``: spike store -> HR video store, over a Dask cluster.

Output frame j is centred on spike frame ``c_j = W//2 + j*K`` and made from frames ``[c_j - W//2, c_j + W//2]``.
The job checks its options, places and builds its method (:func:`prepared`), fixes the gain for the whole recording
(``--gain``, else the store's, else the automatic exposure of its middle window: tiles, frames and parts agree),
cuts the blocks ``lazy.reconstruct`` cuts (``reconstruct_tasks.cut``) and runs their tasks (each reads its windows
and halo from Zarr, reconstructs, writes and commits its tiles) through the executor's bounded window: on the
client's cluster, else in segments on fresh local clusters (``pipeline.compute.executor``). A part (``--start``/
``--stop``, ``--region``: ``reconstruct_plan.job_part``) is recorded in the output, which ``--resume`` checks.
``--dry-run`` prices the plan by a few of its own tasks (``pipeline.jobs.dry_run``), creating nothing.
Where the network runs, its default weights and tile: docs/cluster.md.
"""

import contextlib
import dataclasses
import functools
import logging
import uuid
from collections.abc import Iterable

import numpy as np

from pipeline.compute.cluster import (
    GPU,
    check_in_memory,
    check_scheduler,
    check_workers,
    dask_client,
    scheduler_address,
    visible_gpus,
)
from pipeline.compute.executor import in_segments, result_of, show_dashboard_once
from pipeline.compute.progress import is_quiet, progress_bar
from pipeline.compute.worker_start import NETWORK_PRELOAD
from pipeline.jobs.dry_run import plan_job
from pipeline.jobs.reconstruct_plan import (
    DEFAULT_TILE,
    GPU_BATCH,
    MADE_FROM,
    Placement,
    Plan,
    ReconstructOptions,
    default_weights,
    job_part,
    made_from,
)
from pipeline.jobs.reconstruct_tasks import (  # noqa: F401 - JobIncomplete: what a failed job raises
    JobIncomplete,
    MethodSpec,
    Outcome,
    TileBlocks,
    cut,
    finish_video,
    gain_task,
    reconstructor,
    run_blocks,
    store_gain,
)
from pipeline.stores.lease import check_free, claimed, held
from pipeline.stores.outputs import VIDEO_STORE, check_existing, new_output
from pipeline.stores.spike_store import SpikeStore, open_spike_store, store_identity
from pipeline.stores.storage import check_apart, exists, recorded
from pipeline.stores.video_store import create_video_store, open_video_store, resumed_mask
from stages.errors import InputError
from stages.reconstruction.methods import NETWORKS, Reconstructor
from stages.reconstruction.tiles import device_tile, tile_grid

log = logging.getLogger("cscsr.reconstruct")  # DEBUG lines (cscsr --verbose): the job's plan, each task's outcome


def network_options(options: ReconstructOptions) -> tuple[str | None, str | None]:
    """(precision, backend) of a network job; (None, None) for the classic methods, which have neither."""
    return (options.precision, options.backend) if options.method in NETWORKS else (None, None)


def method_spec(options: ReconstructOptions, method: Reconstructor, where: Placement) -> MethodSpec:
    """What the tasks of a job of ``options`` build: ``method`` (:func:`prepared`) where it runs."""
    weights = recorded(str(method.weights)) if method.weights else None  # as workers in any folder find it
    return MethodSpec(options.method, weights, *network_options(options), method.weights_sha256,
                      bool(options.fast_gpu and where.gpus))


def checked_method(store: SpikeStore, options: ReconstructOptions) -> tuple[int, Reconstructor]:
    """Every check of a job on ``store`` that needs no output or cluster: the options against the recording, and the
    method built with its weights (without ``--weights``, those for CPU workers and the recording's CFA) and checked
    (:func:`_built_method`). -> (scale, method)."""
    options.check()
    if options.window > store.n_frames:
        raise InputError(f"--window {options.window} is longer than the recording ({store.n_frames} frames)")
    if options.method in NETWORKS and not options.weights:
        options = dataclasses.replace(options, weights=default_weights(False, store.meta.cfa))
    return _built_method(options, store.attrs.get("scale"), store.meta.cfa, f"the recording {store.url}")


def _built_method(options: ReconstructOptions, stored_scale, cfa: str, recording: str | None = None):
    """(the scale: ``--scale``, else the recording's ``stored_scale``, else 4; the method, built on the CPU (this
    process only checks its weights) and checked against the window, scale and ``cfa``, naming ``recording``)."""
    scale = options.scale if options.scale is not None else int(stored_scale or 4)
    method = reconstructor(options.method, options.weights, *network_options(options), device="cpu")
    method.check(options.window, scale, cfa, *((recording,) if recording and options.method in NETWORKS else ()))
    return scale, method


def prepared(options: ReconstructOptions, client, cfa: str, stored_scale, lr_shape: tuple[int, int],
             found: dict, recording: str | None = None) -> tuple[ReconstructOptions, Placement, int, Reconstructor]:
    """The method placed (:func:`placement`), its options :func:`placed` and :func:`sized` for there and for the
    part's ``lr_shape``, and built and checked -> (options, placement, scale, method); ``found``: what a resumed
    output records. The job and ``lazy.reconstruct`` prepare their method here."""
    where = placement(options, client)
    options = placed(options, where, found, cfa)
    scale, method = _built_method(options, stored_scale, cfa, recording)
    return sized(options, where, method, lr_shape, found), where, scale, method


def placement(options: ReconstructOptions, client) -> Placement:
    """On ``client``'s GPU workers if it has any, else (no client: a local cluster) on this machine's GPUs; with the
    smallest one's memory."""
    if options.method not in NETWORKS or options.backend != "torch":
        return Placement(False, None)
    if client is None:
        if not (gpus := visible_gpus()):
            return Placement(False, None)
        import torch

        return Placement(True, min(torch.cuda.get_device_properties(i).total_memory for i in range(gpus)))
    addresses = [address for address, worker in client.scheduler_info()["workers"].items()
                 if (worker.get("resources") or {}).get(GPU, 0) >= 1]
    sizes = [size for size in client.run(gpu_memory_bytes, workers=addresses).values() if size] if addresses else []
    return Placement(bool(addresses), min(sizes) if sizes else None)


def gpu_memory_bytes() -> int | None:
    """Run on a GPU worker: the memory of its GPU (pinned, it sees only its own, as device 0); None without one."""
    import torch

    return torch.cuda.get_device_properties(0).total_memory if torch.cuda.is_available() else None


def placed(options: ReconstructOptions, where: Placement, recorded: dict, cfa: str = "rggb") -> ReconstructOptions:
    """The options with the network's weights filled in: ``--weights``, else what a resumed output records, else
    :func:`reconstruct_plan.default_weights` for ``where`` and the recording's ``cfa``."""
    if options.method not in NETWORKS or options.weights:
        return options
    return dataclasses.replace(options, weights=recorded.get("weights") or default_weights(where.gpus, cfa))


def sized(options: ReconstructOptions, where: Placement, method: Reconstructor, shape: tuple[int, int],
          recorded: dict) -> ReconstructOptions:
    """The options with the tile and the windows per pass filled in: ``--tile`` (else what a resumed output
    records), ``--gpu-batch``; else on GPUs of known memory what the smallest holds (``tiles.device_tile``: the
    whole frame where it fits), and otherwise ``DEFAULT_TILE`` and ``GPU_BATCH``."""
    tile, batch = options.tile or recorded.get("tile_lr"), options.gpu_batch
    if where.gpus and where.memory and (tile is None or batch is None):
        from cscsr.inference.device_memory import bytes_per_lr_pixel, usable_bytes

        fitted = device_tile(*shape, method.halo, usable_bytes(where.memory),
                             bytes_per_lr_pixel(method.model.config.name, options.precision), GPU_BATCH)
        tile, batch = tile or fitted[0], batch or fitted[1]
    return dataclasses.replace(options, tile=tile or DEFAULT_TILE, gpu_batch=batch or GPU_BATCH)


def _recorded_attrs(out: str) -> dict:
    """What the output to resume records, or nothing if it is not a video store (refused later, with why)."""
    try:
        return dict(open_video_store(out).attrs)
    except Exception:  # noqa: BLE001 - refused later, with the reason, by new_output and _prepare_output
        return {}


def reconstruct(store_url: str, out: str, options: ReconstructOptions = ReconstructOptions(), *,
                workers: int | None = None, scheduler: str | None = None, client=None, progress: bool = True,
                dry_run: bool = False) -> dict:
    """Reconstruct the recording at ``store_url`` (or the part ``options`` name) into an HR video store at ``out``,
    on ``client``, else on the scheduler ``scheduler`` names (or the environment), else in segments of
    ``options.segment_tasks`` tasks, each on a fresh local cluster of ``workers``. -> counts: output frames, tasks run
    now, tasks found committed. ``dry_run``: every check, nothing created; -> the plan, priced (:func:`plan_job`)."""
    check_workers(workers, scheduler)
    options.check()
    check_apart(out, store_url, options.weights)
    check_in_memory((store_url, out, options.weights), client=client)  # workers read and write them
    store = open_spike_store(store_url)
    meta = store.meta
    checked_method(store, options)  # the options and the weights given, before any cluster
    part = job_part(options, store.n_frames, meta.fps, meta.height, meta.width, meta.cfa)  # --start/--stop/--region
    if options.resume and not exists(out):
        raise InputError(f"cannot resume: {out} does not exist")
    if client is None:
        check_scheduler(scheduler)  # a named scheduler answers (within seconds) before OUT is claimed or replaced

    with contextlib.ExitStack() as stack:
        if client is None and scheduler_address(scheduler):  # a long-lived cluster: connect once, before any output
            client = stack.enter_context(dask_client(scheduler=scheduler))
        y0, y1, x0, x1 = part.region
        found = _recorded_attrs(out) if options.resume else {}
        options, where, scale, method = prepared(  # the weights by where the network runs
            options, client, meta.cfa, store.attrs.get("scale"), (y1 - y0, x1 - x0), found,
            f"the recording {store.url}")
        spec = method_spec(options, method, where)  # the job's blocks: the lazy graph's for the same options
        centres = part.centres
        grid = tile_grid(meta.height, meta.width, options.tile, method.halo, part.region)
        if dry_run:
            _check_output(out, options)  # what the claim and new_output below refuse, creating nothing
        else:
            stack.enter_context(claimed(out))  # one job per output, taken atomically before OUT is touched
            if options.resume:
                check_free(out)  # and no live lease (a job on a machine that shares no claim file with us)
            # only one of our stores is replaced, kept aside until the new one is complete; a failed one stays
            stack.enter_context(new_output(out, overwrite=options.overwrite, kind=VIDEO_STORE,
                                           flag="--resume or --overwrite", resume=options.resume, keep_partial=True))
        began = found.get("gain")  # a resume: the exposure it began with (an output from before a change of rule)
        gain = options.gain or meta.gain or (began if isinstance(began, float) else None)
        if gain is None:  # one window: on the cluster if there is one, else here (not worth a cluster of its own)
            key, args = gain_task(recorded(store_url), store_identity(store), store.n_frames, meta.width,
                                  options.window, meta.reset)  # the same gain for any part
            gain = result_of(client, store_gain, args, key) if client else store_gain(*args)
        # the spike store and the output as workers find them, whatever their working directory (and as the output
        # records its source)
        plan = Plan(recorded(store_url), recorded(out), options.method, method.weights, options.window, options.every,
                    float(gain), scale, meta.cfa, meta.reset, options.tile, uuid.uuid4().hex, spec.precision,
                    options.gpu_batch, spec.backend, fast_gpu=spec.fast_gpu if options.method in NETWORKS else None,
                    **made_from(store, method.weights_sha256),  # what --resume checks beside the paths
                    start=part.start, stop=part.stop, region=part.region)
        hr_size = ((y1 - y0) * scale, (x1 - x0) * scale)
        blocks = cut(spec, plan.spikes, plan.source_identity, centres, part.first, plan.every, plan.window, grid,
                     method.batch, plan.cfa, plan.reset, plan.scale, plan.gpu_batch, plan.gain, where.gpus,
                     store.n_frames)
        if dry_run:
            done = (_check_resumable(plan, open_video_store(out), centres, blocks) if options.resume
                    else np.zeros((len(centres), len(grid), len(grid[0])), bool))
            return plan_job(plan, part, blocks, done, hr_size, where, client=client, workers=workers,
                            store=store_url, segment_tasks=options.segment_tasks)
        done = _prepare_output(plan, options.resume, centres, blocks, hr_size, fps=meta.fps / options.every)
        to_run, total = blocks.task_counts(done)
        work = functools.partial(run_blocks, blocks=blocks, out=plan.out, run=plan.run)
        log.debug("%s -> %s: %s%s, %d output frames x %d tiles of %d LR pixels (x%d), gain %.4g; %d of %d tiles "
                  "committed already; on %s", store_url, out, options.method,
                  f" (weights {method.weights})" if method.weights else "", len(centres), len(grid) * len(grid[0]),
                  options.tile, scale, gain, int(done.sum()), done.size,
                  f"the cluster at {client.scheduler.address}" if client else
                  f"local clusters of {workers or 'a worker per core'} workers, {options.segment_tasks} tasks each")
        with held(out), progress_bar(f"reconstruct {options.method}", len(centres),
                                     done=int(done.all(axis=(1, 2)).sum()), enabled=progress) as advance:
            if client:
                if progress and not is_quiet():
                    show_dashboard_once(client)
                outcomes = work(client, blocks.units(done))
            else:  # our own local cluster: a fresh one per segment keeps memory bounded
                outcomes = in_segments(work, blocks.units(done), options.segment_tasks, workers=workers,
                                       show_dashboard=progress,
                                       preload=NETWORK_PRELOAD if options.method in NETWORKS else ())
            failed = _tally(outcomes, done, advance)
        finish_video(out, failed, len(centres))  # still under the claim
    return {"frames": len(centres), "tasks_run": to_run, "tasks_skipped": total - to_run}


def _check_output(out: str, options: ReconstructOptions) -> None:
    """For a dry run: what a real run refuses about ``out`` once it has claimed it (another live job writing it; an
    output that is not ours, or that we were not asked to resume or replace), creating nothing."""
    if options.resume:  # it exists: checked before
        check_free(out)
    else:
        check_existing(out, overwrite=options.overwrite, kind=VIDEO_STORE, flag="--resume or --overwrite")


def _tally(outcomes: Iterable[Outcome], done: np.ndarray, advance) -> dict[int, str]:
    """Count finished tiles per output frame (a frame is done when all its tiles are; those ``done`` before are on
    the bar already); -> {frame: error}."""
    failed = {}
    remaining = done.shape[1] * done.shape[2] - done.sum(axis=(1, 2))  # (frames,) tiles still to come
    for outcome in outcomes:
        frames = range(outcome.start, outcome.stop)
        log.debug("output frames %d-%d, tile (%d, %d): %s", outcome.start, outcome.stop - 1, outcome.ty, outcome.tx,
                  "committed" if outcome.error is None else f"failed: {outcome.error}")
        if outcome.error is not None:
            failed.update({index: f"tile ({outcome.ty}, {outcome.tx}): {outcome.error}" for index in frames})
            continue
        for index in frames:
            if not done[index, outcome.ty, outcome.tx]:
                remaining[index] -= 1
                if remaining[index] == 0:
                    advance(1)
    return failed


def _prepare_output(plan: Plan, resume: bool, centres: list[int], blocks: TileBlocks, hr_size: tuple[int, int],
                    fps: float):
    """Create the output (metadata first), or check a resumed one matches; return the commit mask."""
    if resume:
        return _check_resumable(plan, open_video_store(plan.out, writable=True), centres, blocks, adopt=True)
    create_video_store(plan.out, centres=centres, hr_size=hr_size, **blocks.layout, attrs=plan.attrs(), fps=fps)
    return np.zeros((len(centres), *blocks.layout["tiles"]), bool)


def _check_resumable(plan: Plan, group, centres: list[int], blocks: TileBlocks, *, adopt: bool = False) -> np.ndarray:
    """Refuse to resume ``group`` (the output) with ``plan`` unless it was made from the same data with the same
    parameters (the part included); -> its commit mask. ``adopt``: an output from before the record of what it was
    made from gets it now (a dry run leaves it as it is)."""
    expected = plan.attrs()
    if other := plan.other_data(dict(group.attrs)):  # the same paths, another recording or other weights
        raise InputError(f"cannot resume {plan.out}: {other}")
    network = plan.method in NETWORKS  # stores from before --precision and --backend:
    before = {"precision": "fp32" if network else None, "backend": "torch" if network else None,
              "fast_gpu": False if network else None, **plan.whole()}  # and before parts: all of the recording
    # stores from before the record of what they were made from: resumed on the paths alone, as they were
    # then, and the record added now (a later resume checks it)
    adopted = {k: expected[k] for k in MADE_FROM if k not in group.attrs}
    before.update(adopted)
    found = {k: group.attrs.get(k, before.get(k)) for k in expected}
    if isinstance(found["source"], str):  # stores from before sources were absolute: as seen from here
        found["source"] = recorded(found["source"])
    done = resumed_mask(group, plan.out, expected, found, (len(centres), *blocks.layout["tiles"]))
    if adopted and adopt:
        group.attrs.update(adopted)
    return done
