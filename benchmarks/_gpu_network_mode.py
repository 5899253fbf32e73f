"""``gpu_pipeline.py`` without ``--stand-in``: the real network, one configuration and precision at a time.

:func:`measure_network` runs the warm job (pipeline frames/s), then in this process the model alone
and the reconstructor on the job's windows (:func:`task_windows`, :func:`time_passes`: forward and
reconstructor frames/s, the forward pass's FLOPs), and the share of the GPU's bf16 peak;
:func:`run_cli` times the whole command line, cold (``--cli``).
"""

import contextlib
import dataclasses
import inspect
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import ROOT, median
from _gpu_job import check_output, gpu_peak_mib, gpu_worker_client, reconstruct_options, timed_jobs
from _gpu_recording import OUTPUT_FRAMES_PER_TB, SCALE, WINDOW

BF16_DENSE_PEAK_TFLOPS = {"H100 PCIe": 756.0, "H100": 989.4, "H200": 989.4, "A100": 312.0}  # by name, first match


def task_windows(store_url: str, tile: int, halo: int, batch: int):
    """The windows the job reads, in passes of ``batch`` consecutive output frames of one tile."""
    from pipeline.stores.spike_store import open_spike_store, read_frames
    from stages.reconstruction.methods import Window, output_centres
    from stages.reconstruction.tiles import tile_grid

    store = open_spike_store(store_url)
    meta = store.meta
    centres = output_centres(store.n_frames, WINDOW, WINDOW)
    half = WINDOW // 2
    passes = []
    for row in tile_grid(meta.height, meta.width, tile, halo):
        for t in row:
            region = (slice(t.ry0, t.ry1), slice(t.rx0 // 8, -(-t.rx1 // 8)))
            for start in range(0, len(centres), batch):
                passes.append([Window(read_frames(store.spikes, store_url, c - half, c + half + 1, region),
                                      t.rx1 - t.rx0, meta.cfa, meta.reset, float(meta.gain), SCALE)
                               for c in centres[start : start + batch]])
    return passes


def pipeline_batch(args, method, precision: str, tile: int) -> int:
    """Windows per pass as the job's GPU tasks run them: a task's frames of one tile (``method.batch``), at most
    ``--gpu-batch``, else what the device's memory holds (``pipeline.jobs.reconstruct.sized``, where it exists)."""
    most = args.gpu_batch
    if most is None and method.device.type == "cuda":
        import torch

        with contextlib.suppress(ImportError):
            from pipeline.jobs.reconstruct import Placement, sized

            where = Placement(True, torch.cuda.get_device_properties(method.device).total_memory)
            options = dataclasses.replace(reconstruct_options(args, method.weights, precision), tile=tile)
            most = sized(options, where, method, (args.side, args.side), {}).gpu_batch
    return max(1, min(method.batch, most or method.batch))


def synchronise(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize()


def forward_pass(method, windows):
    """The model alone on ``windows``: unpacked and on the device beforehand (not timed); -> a callable
    running one pass, synchronised, under the reconstructor's precision (autocast for bf16)."""
    import torch

    from stages.capture.bits import unpack_rows

    first = windows[0]
    x = torch.from_numpy(np.stack([unpack_rows(w.packed, w.width) for w in windows])).to(method.device, torch.float32)
    network = getattr(method, "forward", None) or method.model

    def run():
        autocast = (torch.autocast(method.device.type, dtype=torch.bfloat16) if method.precision == "bf16"
                    else contextlib.nullcontext())
        with torch.inference_mode(), autocast:
            network(x, first.cfa, first.reset == "zero", first.scale)["image"]
        synchronise(method.device)

    return run


def time_passes(method, passes, repeats: int) -> dict:
    """Forward and reconstructor seconds over all ``passes`` (each a median of ``repeats``, after one untimed
    pass of each shape), and the forward pass's FLOPs (convolutions and matrix products, 2 per multiply-add)."""
    from torch.utils.flop_counter import FlopCounterMode

    from cscsr.inference.reconstructor import one_thread_on_cpu

    forward, many, flops = 0.0, 0.0, 0
    counted = {}  # (window shape, windows) -> FLOPs of one pass
    with one_thread_on_cpu(method.device):
        for windows in passes:
            run = forward_pass(method, windows)
            shape = (windows[0].packed.shape, len(windows))
            if shape not in counted:  # the first pass of a shape: untimed (autotuning, compiling), then counted
                run()
                method.many(windows)
                with FlopCounterMode(display=False) as counter:
                    run()
                counted[shape] = counter.get_total_flops()
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                run()
                times.append(time.perf_counter() - start)
            forward += median(times)
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                method.many(windows)
                synchronise(method.device)
                times.append(time.perf_counter() - start)
            many += median(times)
            flops += counted[shape]
    return {"forward_seconds": forward, "reconstructor_seconds": many, "forward_flops": flops}


def bf16_peak_tflops(gpu: str | None) -> float | None:
    """The GPU's dense bf16 peak (TFLOP/s) from its name, where :data:`BF16_DENSE_PEAK_TFLOPS` knows it."""
    for name, peak in BF16_DENSE_PEAK_TFLOPS.items():
        if gpu and name in gpu:
            return peak
    return None


def measure_network(args, store: str, work: Path, config: str, precision: str, device: str, gpu: str | None) -> dict:
    """One configuration and precision: the warm job (pipeline frames/s), then in this process the model alone
    and the reconstructor on the job's windows (forward and reconstructor frames/s). The job runs first and
    its cluster is closed before the model is loaded here, so the two never share the device's memory."""
    import torch

    from cscsr.inference.reconstructor import load_reconstructor
    from cscsr.weights.weights_io import default_weights

    weights = str(Path(args.weights or default_weights(config)).resolve())
    options = reconstruct_options(args, weights, precision)
    out = str(work / f"{config}-{precision}.zarr")
    print(f"{config} {precision}: the warm job ...", file=sys.stderr, flush=True)
    with gpu_worker_client() as (client, cluster):
        runs = timed_jobs(client, store, out, options, args.repeats)
        worker_peak = max((mib for mib in client.run(gpu_peak_mib).values() if mib is not None), default=None)
    output = check_output(out, args.frames, args.side)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    method = load_reconstructor(weights, device, precision=precision, fast_gpu=args.fast_gpu) \
        if "fast_gpu" in inspect.signature(load_reconstructor).parameters \
        else load_reconstructor(weights, device, precision=precision)
    batch = args.forward_batch or pipeline_batch(args, method, precision, output["tile"])
    while True:
        print(f"{config} {precision}: forward and reconstructor on tile {output['tile']}, {batch} windows a pass ...",
              file=sys.stderr, flush=True)
        try:
            timing = time_passes(method, task_windows(store, output["tile"], method.halo, batch), args.repeats)
            break
        except torch.cuda.OutOfMemoryError:
            if batch == 1:
                raise
            batch //= 2  # this process's passes do not fit beside what it holds: fewer windows a pass
            torch.cuda.empty_cache()
    forward_peak = gpu_peak_mib()
    del method
    if device == "cuda":
        torch.cuda.empty_cache()
    job = median(runs["wall"])
    pipeline_fps, forward_fps = args.frames / job, args.frames / timing["forward_seconds"]
    tflops = timing["forward_flops"] / timing["forward_seconds"] / 1e12
    peak = bf16_peak_tflops(gpu)
    return {
        "config": config, "precision": precision, "fast_gpu": args.fast_gpu, "weights": weights, "cluster": cluster,
        "tile": output["tile"], "tasks": runs["tasks"], "forward_batch": batch,
        "output_bytes_per_frame": output["bytes_per_frame"],
        "job_seconds_runs": runs["wall"], "worker_cpu_seconds_runs": runs["worker_cpu"],
        "pipeline_frames_per_second": pipeline_fps,
        "reconstructor_frames_per_second": args.frames / timing["reconstructor_seconds"],
        "forward_frames_per_second": forward_fps,
        "pipeline_share_of_forward": pipeline_fps / forward_fps,
        "forward_flops_per_frame": timing["forward_flops"] / args.frames, "forward_tflops_per_second": tflops,
        "forward_share_of_bf16_peak": tflops / peak if peak else None,
        "gpu_hours_per_terabyte": OUTPUT_FRAMES_PER_TB / pipeline_fps / 3600,
        "forward_gpu_hours_per_terabyte": OUTPUT_FRAMES_PER_TB / forward_fps / 3600,
        "worker_gpu_peak_mib": worker_peak, "forward_gpu_peak_mib": forward_peak,
    }



def run_cli(store: str, out: Path, weights: str, device: str) -> float:
    """``python -m cscsr reconstruct ... --workers 1``, wall clock of the whole command (start-up included)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    if device == "cpu":
        env["CUDA_VISIBLE_DEVICES"] = ""
    command = [sys.executable, "-m", "cscsr", "reconstruct", store, str(out), "--method", "cscsr",
               "--weights", weights, "--workers", "1", "--overwrite"]
    start = time.perf_counter()
    run = subprocess.run(command, check=False, cwd=ROOT, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode:
        raise RuntimeError(f"{' '.join(command)} failed ({run.returncode}):\n"
                           f"{run.stdout[-2000:]}\n{run.stderr[-4000:]}")
    return seconds
