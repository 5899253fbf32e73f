"""``cscsr reconstruct --dry-run``: the plan of a checked job, priced by some of its own tasks run for real on the
workers that would run them, into a temporary store that is not OUT's; nothing is created near OUT.
"""

import contextlib
import dataclasses
import functools
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Iterator

import numpy as np

from pipeline.compute.estimate import hours, hours_table, output_bytes
from pipeline.compute.executor import in_segments, submitted
from pipeline.jobs.reconstruct_plan import (
    SEGMENT_TASKS,
    Part,
    Placement,
    Plan,
)
from pipeline.jobs.reconstruct_tasks import TileBlocks, writer
from pipeline.stores.storage import remove, resolve
from pipeline.stores.video_store import VIDEO, create_video_store
from stages.errors import InputError
from stages.reconstruction.methods import NETWORKS


def plan_job(plan: Plan, part: Part, blocks: TileBlocks, done: np.ndarray, hr_size: tuple[int, int],
             where: Placement, *, client=None, workers: int | None = None, store: str | None = None,
             segment_tasks: int = SEGMENT_TASKS) -> dict:
    """The plan of a checked job, priced by some of its own tasks run for real (:func:`_measured`) on the job's
    cluster, or, for a job that would start its own, on a local cluster started as a segment of the job starts one
    (whose fixed cost each segment pays too). Their time and bytes give the hours on 1, 8 and 64 such workers, this
    job's time on its workers, and the output's size (``pipeline.compute.estimate``)."""
    centres = part.centres
    to_run, tasks = blocks.task_counts(done)
    job = (plan, part, blocks, hr_size)
    if client is not None:
        measured = _measured(client, *job, seconds=SAMPLE_SECONDS)
        start_up, segments, on = 0.0, 1, "of the cluster"
    else:  # the job would start a local cluster of its own per segment: measured in a segment alike, whose fixed
        began = time.perf_counter()  # cost (a fresh process and cluster, started, warmed and stopped) each pays
        # its scratch folder made and removed here, once the segment and its cluster are gone: a task still running
        # when the job was stopped could write into it after the segment's own cleanup
        with _folder() as folder:
            measured, = in_segments(functools.partial(_measured_here, job=job, seconds=SAMPLE_SECONDS, folder=folder),
                                    [None], 1, workers=workers, show_dashboard=False)
        start_up = max(0.0, time.perf_counter() - began - measured["seconds"] - measured["seconds_per_task"])
        segments, on = -(-to_run // segment_tasks), "local"
    count = measured["of"]  # the workers the job runs on (measured on at most TRIAL_WORKERS of them)
    total = len(centres) * hr_size[0] * hr_size[1]  # HR pixels of the output
    # tasks differ in size (edge tiles, a range's part-full first and last groups): the time per HR pixel of the
    # tasks measured, over the pixels of the job's average task
    per_task = measured["seconds_per_task"] / (measured["hr_pixels"] / measured["tasks"]) * total / tasks
    runs_on = ("GPU workers" if where.gpus else "CPU workers") if plan.method in NETWORKS else "any worker"
    grid = blocks.grid
    return {
        "store": store, "out": plan.out, "method": plan.method, "weights": plan.weights,
        "runs_on": runs_on, "precision": plan.precision, "backend": plan.backend,
        "frames": len(centres), "spike_frames": f"{centres[0]}..{centres[-1]}", "every": plan.every,
        "window": plan.window, "start": plan.start, "stop": plan.stop, "region": list(plan.region),
        "hr_height": hr_size[0], "hr_width": hr_size[1], "scale": plan.scale, "gain": plan.gain,
        "tile_lr": plan.tile, "tiles_per_frame": len(grid) * len(grid[0]),
        "frames_per_task": max(blocks.frames), "tiles_per_task": max(map(len, blocks.passes)),
        "tasks": tasks, "tasks_to_run": to_run,
        "measured_on": (f"{measured['workers']} {'local ' if on == 'local' else ''}{'GPU ' if where.gpus else ''}"
                        f"worker{'s' if measured['workers'] > 1 else ''}{' of the cluster' if on != 'local' else ''}"),
        "measured": measured,
        "seconds_per_task": per_task,  # on one worker while every worker is busy
        "output_bytes": output_bytes(measured["bytes"], measured["hr_pixels"], total),
        "hours": hours_table(per_task, to_run),
        # this job on the workers it will run on: its tasks, and a fresh local cluster per segment (measured)
        "workers": count, "segment_start_seconds": start_up,
        "job_seconds": hours(per_task, to_run, count) * 3600 + segments * start_up if to_run else 0.0,
    }


def _sampled(blocks: TileBlocks, b: int, k: int, url: str, run: str) -> dict:
    """Task of a dry run: the job's own task of pass ``k`` of block ``b``, run here into the dry run's store ->
    the compressed bytes and HR pixels of video it wrote, which it then drops."""
    from dask.local import get_sync

    key, task = blocks.written(b, k, url, run)
    get_sync({key: task}, [key])
    video = writer(url, run).video
    fs, root = resolve(f"{url}/{VIDEO}")
    written = pixels = 0
    for index in range(blocks.starts[b], blocks.starts[b + 1]):
        for ty, tx in blocks.passes[k]:
            tile = blocks.grid[ty][tx]
            path = f"{root}/{video.metadata.encode_chunk_key((index, ty, tx, 0))}"
            try:  # a task of a small job may run twice at once on a worker of several threads: counted once
                written += fs.size(path)
                fs.rm_file(path)
            except FileNotFoundError:
                continue
            pixels += (tile.y1 - tile.y0) * (tile.x1 - tile.x0) * blocks.scale ** 2
    return {"bytes": written, "hr_pixels": pixels}


def _trial_store(url: str, attrs: dict | None = None, layout: dict | None = None, keep: bool = False) -> None:
    """Create the dry run's video store at ``url``, or (no ``attrs``) remove it unless ``keep``; forget its writer."""
    if attrs is not None:
        create_video_store(url, attrs=attrs, **layout)
        return
    if not keep:
        remove(url.rsplit("/", 1)[0] if url.startswith("memory://") else url)
    writer.cache_clear()  # the writer of a store that is gone


@contextlib.contextmanager
def _folder() -> Iterator[str]:
    """A new folder under this machine's temporary folder, removed after."""
    folder = tempfile.mkdtemp(prefix="cscsr-dry-run-")
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def _scratch(client, workers: list[str], folder: str | None = None) -> Iterator[str]:
    """Where a dry run's tasks write, never at or beside OUT: a store in a new folder under this machine's temporary
    folder (``folder``, whose maker removes it; else one made and removed here) where every one of ``workers`` can
    write it (they pay a write to disk, as the job's tasks do), else a ``memory://`` store in each worker process's
    memory."""
    with contextlib.nullcontext(folder) if folder else _folder() as folder:
        if all(client.run(_writable, folder, workers=workers).values()):
            yield os.path.join(folder, "out.zarr")
        else:
            yield f"memory://cscsr-dry-run-{uuid.uuid4().hex}/out.zarr"


_TOKEN = uuid.uuid4().hex  # this process's, drawn once (a process forked later has a pid of its own)


def _process() -> tuple[int, str]:
    """This process, unlike any other on any machine (pids repeat across machines and containers)."""
    return os.getpid(), _TOKEN


def _writable(folder: str) -> bool:
    """Whether this process (a worker) can write in ``folder``."""
    return os.path.isdir(folder) and os.access(folder, os.W_OK | os.X_OK)


TRIAL_WORKERS = 64  # the most workers a dry run measures on
SAMPLE_SECONDS = 3.0  # about how long a dry run keeps them busy after a task each to warm them
MOST_TASKS = 100  # a worker, in that time (tasks of milliseconds)


def _measured(client, plan: Plan, part: Part, blocks: TileBlocks, hr_size: tuple[int, int], *,
              seconds: float = SAMPLE_SECONDS, folder: str | None = None) -> dict:
    """Run tasks of the job (from its middle on) on every worker that would run them (at most ``TRIAL_WORKERS``),
    all at once as the job keeps them busy (one worker measured alone runs up to twice as fast as in the job), into
    a temporary store (:func:`_scratch`): one task per worker to warm them, then tasks submitted as the job submits
    them for about ``seconds``. -> {"workers" measured on, "of" how many would run the job's tasks, "tasks" timed,
    "seconds" until the last workers went idle, "seconds_per_task" on one worker (the client's and scheduler's work
    included), "bytes" and "hr_pixels" of video they wrote}."""
    workers = client.scheduler_info()["workers"]
    resources = (blocks.annotations or {}).get("resources")
    able = [address for address, worker in workers.items()
            if all((worker.get("resources") or {}).get(k, 0) >= v for k, v in (resources or {}).items())]
    if not able:
        raise InputError("the cluster has no worker that would run this job's tasks: add workers, then plan again")
    job_tasks = sum(1 for _ in blocks.units())
    of, able = len(able), able[:min(TRIAL_WORKERS, job_tasks)]  # a job of fewer tasks keeps no more workers busy
    with _scratch(client, able, folder) as url:
        shared = not url.startswith("memory://")  # one store that every worker reaches, else one in each worker process
        # workers that share a process (a client's in-process workers) share its memory: the store made once there
        owners = list({process: address for address, process in client.run(_process, workers=able).items()}.values())
        trial = dataclasses.replace(plan, out=url, run=uuid.uuid4().hex)
        layout = {"centres": part.centres, "hr_size": hr_size, **blocks.layout}
        groups = _from_the_middle(blocks)

        def submit(unit, where: list[str] = able):
            return client.submit(_sampled, blocks, *unit, trial.out, trial.run, pure=False, workers=where,
                                 allow_other_workers=False, resources=resources)

        most = _most_sampled(job_tasks, len(able))

        def sample() -> Iterator:  # whole rounds for about ``seconds``, one at least: tasks of a minute (a network's
            for n, group in enumerate(groups):  # whole 1000x1000 frame) ran 3 rounds, half the job
                if n >= most or (n >= len(able) and n % len(able) == 0 and time.perf_counter() - began >= seconds):
                    return
                yield group

        if shared:
            _trial_store(url, trial.attrs(), layout)
        else:
            client.run(_trial_store, url, trial.attrs(), layout, workers=owners)
        def forget() -> None:  # the trial store and every worker's writer of it
            client.run(_trial_store, url, None, None, shared, workers=owners)
            if shared:
                _trial_store(url)

        try:
            for future in [submit(group, [address]) for address, group in zip(able, groups)]:  # warm
                future.result()  # each (a gather stopped by a signal left asyncio's "never retrieved" AllExit)
            began, finished, results = time.perf_counter(), [], []
            for _, future in submitted(client, sample(), submit):  # as the job submits them: a bounded window
                results.append(future.result())
                finished.append(time.perf_counter())
        except BaseException as stopped:  # the cause is said, not a failed cleanup after it. Stopped (SIGTERM,
            # Ctrl-C) on our own cluster (``folder``), its workers go with it or went with the signal: nothing to ask
            if folder is None or isinstance(stopped, Exception):
                with contextlib.suppress(Exception):
                    forget()
            raise
        forget()
        # until the last workers go idle: the time of the task that leaves one task a worker to finish; in one round,
        # which began at once on every worker, the time of its last
        counted = len(finished) if len(finished) <= len(able) else len(finished) - len(able) + 1
        seconds = finished[counted - 1] - began
        return {"workers": len(able), "of": of, "tasks": len(results), "seconds": seconds,
                "seconds_per_task": seconds * len(able) / counted, "bytes": sum(r["bytes"] for r in results),
                "hr_pixels": sum(r["hr_pixels"] for r in results)}


def _measured_here(client, items, *, job: tuple, seconds: float, folder: str) -> Iterator[dict]:
    """:func:`_measured` as a segment of the job runs (``executor.in_segments``), on its own cluster, writing into
    ``folder`` (the job's process removes it)."""
    yield _measured(client, *job, seconds=seconds, folder=folder)


def _from_the_middle(blocks: TileBlocks) -> Iterator[tuple[int, int]]:
    """The job's units from its middle frames on, round and round for ever (a recording's ends are often dark)."""
    units = list(blocks.units())
    middle = next(n for n, (b, _) in enumerate(units) if blocks.starts[b + 1] > blocks.starts[-1] // 2)
    while True:
        yield from units[middle:]
        yield from units[:middle]


def _most_sampled(job_tasks: int, workers: int) -> int:
    """The most tasks a dry run times after the warm-up round (a task a worker): no more than the job has with that
    round, in whole rounds of a task a worker, one round at least (a job of one task: two tasks in all) and
    :data:`MOST_TASKS` a worker at most. (Three rounds at least made a dry run of a one-task job run eight.)"""
    return max(1, min(MOST_TASKS, (job_tasks - workers) // workers)) * workers
