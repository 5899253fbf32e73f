"""The measured job: ``pipeline.jobs.reconstruct.reconstruct`` on a local cluster of one GPU worker.

The cluster (:func:`gpu_worker_client`), the job's options (:func:`reconstruct_options`), the warm
job timed (:func:`timed_jobs`: wall clock, the worker's CPU, the task stream), the stand-in device's
busy time within each job (:func:`device_busy`), the output checked (:func:`check_output`) and the
GPU memory high-water mark of a process (:func:`gpu_peak_mib`). Both modes of ``gpu_pipeline.py``
measure their jobs with these.
"""

import contextlib
import dataclasses
import inspect
import os
import sys
import time
from pathlib import Path

import numpy as np
from _gpu_recording import SCALE, WINDOW
from _gpu_standin import stand_in_passes


@contextlib.contextmanager
def gpu_worker_client():
    """A local cluster of one GPU worker and its client; -> (client, how it was made).

    ``pipeline.compute.cluster.dask_client(workers=1, gpus=1)`` where it takes ``gpus`` (a pinned GPU worker
    running several tasks at once); else one worker process with one thread advertising ``GPU=1``, as
    compose's ``gpu-worker`` (``--nthreads 1 --resources GPU=1``), with ``dask_client``'s settings."""
    import dask
    from distributed import Client, LocalCluster

    import pipeline.compute.cluster as cluster

    if "gpus" in inspect.signature(cluster.dask_client).parameters:
        with cluster.dask_client(workers=1, gpus=1) as client:
            yield client, "pipeline.compute.cluster.dask_client(workers=1, gpus=1)"
        return
    with dask.config.set(getattr(cluster, "PRE_SPAWN", getattr(cluster, "_PRE_SPAWN", {}))), \
            LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                         dashboard_address="127.0.0.1:0", resources={cluster.GPU: 1},
                         env=cluster._thread_env(1), silence_logs=cluster._dask_log_level()) as local, \
            Client(local) as client:
        yield client, "LocalCluster(n_workers=1, threads_per_worker=1, resources={'GPU': 1}) (no gpus= in dask_client)"


def worker_pids(client) -> list[int]:
    return sorted(client.run(os.getpid).values())


def cpu_seconds(pids: list[int]) -> np.ndarray:
    """(user, system) CPU seconds used so far by the processes ``pids``."""
    import psutil

    return np.sum([psutil.Process(pid).cpu_times()[:2] for pid in pids], axis=0)


def reconstruct_options(args, weights: str, precision: str = "fp32"):
    """The job's options: the network, ``--tile`` (None: the pipeline's choice), ``--gpu-batch``, ``--fast-gpu``."""
    from pipeline.jobs.reconstruct_plan import ReconstructOptions

    fields = {f.name for f in dataclasses.fields(ReconstructOptions)}
    extra = {}
    if args.tile is not None:
        extra["tile"] = args.tile
    if args.gpu_batch is not None:
        extra["gpu_batch"] = args.gpu_batch
    if args.fast_gpu:
        if "fast_gpu" not in fields:
            raise SystemExit("--fast-gpu: this checkout's ReconstructOptions has no fast_gpu")
        extra["fast_gpu"] = True
    return ReconstructOptions(method="cscsr", weights=weights, window=WINDOW, every=WINDOW, scale=SCALE,
                              precision=precision, overwrite=True, **extra)


def timed_jobs(client, store: str, out: str, options, repeats: int) -> dict:
    """The warm job: run once untimed (every tile shape, the model loaded and compiled), then ``repeats``
    timed runs; -> per run its wall seconds, the worker processes' CPU seconds and this process's, and
    (from Dask's task stream) the seconds before its first task started and after its last one ended."""
    import psutil
    from distributed import get_task_stream

    from pipeline.jobs.reconstruct import reconstruct

    reconstruct(store, out, options, client=client, progress=False)
    pids = worker_pids(client)
    me = psutil.Process()
    runs = {"wall": [], "worker_cpu": [], "worker_system_cpu": [], "client_cpu": [], "start": [], "stop": [],
            "before_first_task": [], "after_last_task": []}
    for _ in range(repeats):
        cpu, mine, start, clock = cpu_seconds(pids), sum(me.cpu_times()[:2]), time.perf_counter(), time.time()
        with get_task_stream(client) as stream:
            counts = reconstruct(store, out, options, client=client, progress=False)
        stop, clock_stop = time.perf_counter(), time.time()
        computed = [span for task in stream.data for span in task["startstops"] if span["action"] == "compute"]
        runs["before_first_task"].append(min(span["start"] for span in computed) - clock)
        runs["after_last_task"].append(clock_stop - max(span["stop"] for span in computed))
        runs["wall"].append(stop - start)
        user, system = cpu_seconds(pids) - cpu
        runs["worker_cpu"].append(float(user + system))
        runs["worker_system_cpu"].append(float(system))
        runs["client_cpu"].append(sum(me.cpu_times()[:2]) - mine)
        runs["start"].append(start)
        runs["stop"].append(stop)
        print(f"  job: {runs['wall'][-1]:.2f} s, worker CPU {runs['worker_cpu'][-1]:.2f} s", file=sys.stderr,
              flush=True)
    runs["tasks"] = counts["tasks_run"]
    runs["pids"] = pids
    return runs


def device_busy(client, runs: dict) -> list[dict]:
    """For each timed job: the stand-in's busy seconds within it, its share of the wall time, the windows per
    pass, how long the job ran before the first pass (set-up, first reads) and after the last (last writes,
    the job's completion), and the device's idle time between passes (the worker's perf_counter is this
    machine's monotonic clock, as ours)."""
    passes = next(iter(client.run(stand_in_passes).values()))
    out = []
    for start, stop in zip(runs["start"], runs["stop"]):
        inside = sorted((a, b, n) for a, b, n in passes if a >= start and b <= stop)
        busy = sum(b - a for a, b, _ in inside)
        out.append({"busy_seconds": busy, "busy_share": busy / (stop - start), "passes": len(inside),
                    "windows_per_pass": sorted({n for _, _, n in inside}),
                    "before_first_pass_seconds": inside[0][0] - start if inside else None,
                    "after_last_pass_seconds": stop - inside[-1][1] if inside else None,
                    "idle_between_passes_seconds": sum(b[0] - a[1] for a, b in zip(inside, inside[1:]))})
    return out


def check_output(url: str, frames: int, side: int) -> dict:
    """The output is complete and of the expected shape; -> its recorded tile and compressed bytes per frame."""
    from pipeline.stores.video_store import VIDEO, open_video_store

    group = open_video_store(url)
    shape = group[VIDEO].shape
    if group.attrs.get("state") != "complete" or shape != (frames, side * SCALE, side * SCALE, 3):
        raise RuntimeError(f"{url}: state {group.attrs.get('state')!r}, video {shape}: not the expected output")
    video = Path(url) / VIDEO
    size = sum(p.stat().st_size for p in video.rglob("*") if p.is_file())
    return {"tile": group.attrs.get("tile_lr"), "bytes_per_frame": size / frames}



def gpu_peak_mib() -> float | None:
    """This process's high-water mark of GPU memory allocated by torch (MiB) since its start or the last
    reset; None where it has not used CUDA (run in the worker too, through ``client.run``)."""
    import torch

    if not (torch.cuda.is_available() and torch.cuda.is_initialized()):
        return None
    return torch.cuda.max_memory_allocated() / 2**20
