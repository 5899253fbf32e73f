"""``gpu_pipeline.py --stand-in S``, the CPU proxy: the job with the stand-in in the worker, and its goals.

:func:`measure_stand_in` runs the warm job with :class:`_gpu_standin.StandInDevice` in place of the
network and gives its figures per repeat and as medians; with ``--profile``, :func:`profile_steps`
(CPU per frame of each step of one task, here) and :func:`picture_against_network` (is the stand-in's
picture as costly to compress as the network's output?).
"""

import time
from pathlib import Path

import numpy as np
from _common import median
from _gpu_job import check_output, device_busy, gpu_worker_client, reconstruct_options, timed_jobs
from _gpu_recording import SCALE, WINDOW
from _gpu_standin import install_stand_in, stand_in_picture, stand_in_plugin

GOAL_JOB_OVER_STAND_IN = 1.15  # job seconds per frame <= 1.15 S: the device never waits
GOAL_CPU_PER_FRAME = 0.15  # non-network CPU seconds of the worker per output frame


def measure_stand_in(args, store: str, work: Path) -> dict:
    """``--stand-in S``: the warm job with the stand-in in the worker; figures per repeat and medians."""
    from cscsr.weights.weights_io import default_weights
    from pipeline.stores.spike_store import open_spike_store

    picture = str(stand_in_picture(store))
    gain = float(open_spike_store(store).meta.gain)
    weights = str(Path(args.weights or default_weights("lite")).resolve())
    options = reconstruct_options(args, weights)
    out = str(work / "stand_in.zarr")
    with gpu_worker_client() as (client, cluster):
        client.register_plugin(stand_in_plugin(args.stand_in, picture, gain))
        path = next(iter(client.run(lambda dask_worker: dask_worker.stand_in_path).values()))
        threads = next(iter(client.nthreads().values()))
        runs = timed_jobs(client, store, out, options, args.repeats)
        busy = device_busy(client, runs)
    output = check_output(out, args.frames, args.side)
    job = [wall / args.frames for wall in runs["wall"]]
    cpu = [seconds / args.frames for seconds in runs["worker_cpu"]]
    result = {
        "mode": "stand-in", "path": path, "stand_in_seconds": args.stand_in, "cluster": cluster,
        "worker_threads": threads, "tile": output["tile"], "chunks_written": runs["tasks"], "weights": weights,
        "output_bytes_per_frame": output["bytes_per_frame"],
        "job_seconds_per_frame": median(job), "job_seconds_per_frame_runs": job,
        "non_network_cpu_seconds_per_frame": median(cpu), "non_network_cpu_seconds_per_frame_runs": cpu,
        "of_which_system_cpu_seconds_per_frame_runs": [s / args.frames for s in runs["worker_system_cpu"]],
        "client_and_scheduler_cpu_seconds_per_frame_runs": [s / args.frames for s in runs["client_cpu"]],
        "job_before_first_task_seconds_runs": runs["before_first_task"],
        "job_after_last_task_seconds_runs": runs["after_last_task"],
        "device_busy": busy, "device_busy_share": median([b["busy_share"] for b in busy]),
        "goals": {"job_seconds_per_frame": GOAL_JOB_OVER_STAND_IN * args.stand_in,
                  "non_network_cpu_seconds_per_frame": GOAL_CPU_PER_FRAME},
    }
    if args.profile:
        result["profile_cpu_seconds_per_frame"] = profile_steps(store, work, weights, picture, gain, output["tile"])
        result["picture_against_network"] = picture_against_network(store, weights, picture)
    return result


def profile_steps(store: str, work: Path, weights: str, picture: str, gain: float, tile: int) -> dict:
    """CPU and wall seconds per output frame of each step of one GPU task, run here on one task's data (as
    the worker runs them, one after the other, no Dask): read and decompress the windows, the
    reconstructor's host work around a stand-in of 0 s (the old path: unpacking, float conversion,
    exposure; the device-side path: stacking the packed bits), and writing (crop, compression, Zarr
    write and commit) into a copy of the output's layout. Medians of 3. On the old path the host work
    includes element-wise work on the float HR rates that a GPU would do (``many`` averages the
    views: ``sum(...) / 1``) but the proxy's CPU device does: measured alone, as "of which"."""
    import psutil

    import pipeline.jobs.reconstruct_tasks as reconstruct_module
    from pipeline.stores.spike_store import open_spike_store, read_frames
    from pipeline.stores.video_store import TileWriter, create_video_store
    from stages.reconstruction.methods import Window, output_centres
    from stages.reconstruction.tiles import tile_grid

    path = install_stand_in(0.0, picture, gain)
    method = reconstruct_module.reconstructor("cscsr", weights)
    spikes = open_spike_store(store)
    meta = spikes.meta
    grid = tile_grid(meta.height, meta.width, tile, method.halo)
    t = grid[0][0]
    centres = output_centres(spikes.n_frames, WINDOW, WINDOW)[: method.batch]
    region = (slice(t.ry0, t.ry1), slice(t.rx0 // 8, -(-t.rx1 // 8)))
    out = str(work / "profile.zarr")
    create_video_store(out, centres=centres, hr_size=(meta.height * SCALE, meta.width * SCALE),
                       tile_hr=((t.y1 - t.y0) * SCALE, (t.x1 - t.x0) * SCALE), tiles=(len(grid), len(grid[0])),
                       attrs={})
    writer = TileWriter(out)
    me = psutil.Process()
    state = {}

    def read():
        state["windows"] = [Window(read_frames(spikes.spikes, store, c - WINDOW // 2, c + WINDOW // 2 + 1, region),
                                   t.rx1 - t.rx0, meta.cfa, meta.reset, gain, SCALE) for c in centres]

    def host_work():
        state["images"] = method.many(state["windows"])

    def write():  # as the task writes: all its frames in one call where the writer can, else one by one
        ys, xs = t.crop(SCALE)
        if hasattr(writer, "write_frames"):
            writer.write_frames(0, (0, 0), (t.y0 * SCALE, t.x0 * SCALE),
                                np.stack([image[ys, xs] for image in state["images"]]))
            return
        for index, image in enumerate(state["images"]):
            writer.write(index, (0, 0), (t.y0 * SCALE, t.x0 * SCALE), image[ys, xs])

    def device_ops():  # the old path's averaging of views (sum, / 1) over float HR rates: a GPU's work there
        import torch

        from cscsr.inference.reconstructor import one_thread_on_cpu

        rates = method.stand_in.model(torch.empty(len(centres), 1, t.ry1 - t.ry0, t.rx1 - t.rx0), meta.cfa,
                                      False, SCALE, gain)["image"]
        with one_thread_on_cpu(method.device):  # as many() runs it
            sum(rate for rate in [rates]) / 1

    steps = {"read_and_decompress": read, "reconstructor_host_work": host_work, "compress_and_write": write}
    if path == "old":
        steps["of_which_device_ops_run_on_the_cpu"] = device_ops
    result = {}
    for name, step in steps.items():
        cpu, wall = [], []
        for _ in range(3):
            before, start = sum(me.cpu_times()[:2]), time.perf_counter()
            step()
            wall.append((time.perf_counter() - start) / len(centres))
            cpu.append((sum(me.cpu_times()[:2]) - before) / len(centres))
        result[name] = {"cpu": median(cpu), "wall": median(wall)}
    result["frames_per_task"] = len(centres)
    return result


def picture_against_network(store: str, weights: str, picture: str, side: int = 256) -> dict:
    """Is the stand-in's picture as costly to compress as the network's output? Both at ``side`` x ``side`` LR
    (x4 HR) from the first window: zstd level 1 (the video store's codec) on one thread, bytes at rest per
    HR pixel and seconds per HR megapixel (median of 5). The network runs here, on the CPU (seconds)."""
    from numcodecs import Zstd

    from cscsr.inference.reconstructor import load_reconstructor
    from pipeline.stores.spike_store import open_spike_store
    from stages.reconstruction.methods import Window

    spikes = open_spike_store(store)
    meta = spikes.meta
    side = min(side, meta.height, meta.width) // 8 * 8
    window = Window(spikes.read(0, WINDOW)[:, :side, : side // 8], side, meta.cfa, meta.reset, float(meta.gain), SCALE)
    images = {"stand_in": np.load(picture)[: side * SCALE, : side * SCALE],
              "network": load_reconstructor(weights, "cpu")(window)}
    codec, result = Zstd(level=1), {}
    for name, image in images.items():
        data = np.ascontiguousarray(image)
        times = []
        for _ in range(5):
            start = time.perf_counter()
            size = len(codec.encode(data))
            times.append(time.perf_counter() - start)
        result[name] = {"bytes_per_hr_pixel": size / (data.shape[0] * data.shape[1]),
                        "seconds_per_hr_megapixel": median(times) / (data.shape[0] * data.shape[1] / 1e6)}
    result["lr_side"] = side
    return result
