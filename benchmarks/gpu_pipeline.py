"""The CSCSR pipeline on one GPU worker: how busy it keeps the device (issue #35).

Two modes, both on a simulated RGGB spike recording of ``--side`` x ``--side`` LR pixels with
``41 * --frames`` spike frames (one output frame per 41: the network's window and the default
``--every``), reconstructed at x4 through ``pipeline.reconstruct.reconstruct(..., client=...)`` on
a local cluster of one GPU worker (a Dask worker advertising ``GPU=1``, so that the job takes the
GPU-worker path: ``pipeline.cluster.dask_client(workers=1, gpus=1)`` where it exists, else one
worker with one thread and ``GPU=1``, as compose's ``gpu-worker``).

**``--stand-in S``: the CPU proxy, measured without a GPU.** The network is replaced, in the
worker, by :class:`StandInDevice` (a measuring instrument: it lives here and is never a product
path) with the same input and output shapes: a batch of n windows sleeps n * S seconds, leaving
the CPU free as a GPU kernel does, and returns a fixed, natural-looking uint8 HR image made once
from the recording (its first window's TFP image at the store's gain, enlarged to HR), so that
compressing it costs what real output costs. Everything else is the real GPU-worker path: reads,
the packed transfer, tiling, the overlap of tasks, compression, Zarr writes, commits, Dask. On the
device-side path (``NetworkReconstructor.device_images``) the stand-in replaces ``device_images``
(unpacking, network and exposure all run on the device); on the old path (before #35, which had
none) it replaces the model, and unpacking and exposure run on the CPU as that path ran them (so
does its averaging of views over the float HR rates, ``sum(...) / 1``, which a GPU would run:
``--profile`` measures it alone). It reports, per repeat and as medians:

- ``job_seconds_per_frame``: the wall time of a warm job (cluster started, the job run once untimed
  before) per output frame; goal <= 1.15 S (the device never waits);
- ``non_network_cpu_seconds_per_frame``: CPU time (user + system) of the worker process during the
  timed job per output frame (the stand-in uses none); goal <= 0.15 s. The system share is given
  apart: on a VM it includes the host's cost of guest pages touched for the first time (the page
  cache that each job's ~43 MB per frame of output fills), which varies from run to run;
- the device's busy share (the stand-in's sleeps over the job's wall time), and with ``--profile``
  what each step of a task costs in CPU per frame, measured in this process on one task's data
  (read and decompress, the reconstructor's host work around the stand-in, compress and write).

**Without ``--stand-in``: the real network** (``--device cuda`` on a lent GPU; ``--device cpu``
for a smoke run, ``--quick``), for each of ``--configs`` (lite, full) x ``--precisions`` (fp32,
bf16): ``pipeline_frames_per_second`` (the warm job as above, the pipeline choosing the tile
unless ``--tile`` is given), ``reconstructor_frames_per_second`` (``method.many`` on the same
windows in this process) and ``forward_frames_per_second`` (the model alone on the pipeline's
windows, unpacked and on the device, synchronised before and after each pass, as many windows a pass
as the job's GPU tasks take, fewer if they do not fit beside this process's own), the forward pass
in FLOP/s (counted by ``torch.utils.flop_counter``) and as a share of the GPU's dense bf16 peak,
and GPU-hours per terabyte of capture (8 M spike frames, one output per 41: 195,122 output frames)
at ``pipeline_frames_per_second``. ``--cli`` adds the whole command line as a user runs it, cold.

The recording is made by the project's simulator (``pipeline.simulate``, a still picture, about 20 s
for 984 frames of 1000x1000 on 2 cores) and cached in ``/tmp/cscsr_bench`` by its parameters.

Run: ``python benchmarks/gpu_pipeline.py --stand-in 0.25 --frames 24 --side 1000 --tile 1000
[--repeats 3] [--profile] [--out DIR]``, or ``python benchmarks/gpu_pipeline.py --device cuda
--frames 40 --configs lite,full --precisions fp32,bf16 [--fast-gpu] [--merge] [--out DIR]``.
Results: ``DIR/gpu_pipeline.json`` (default ``benchmarks/results``); ``--merge`` keeps the runs of
other configurations already in that file (one lease command per configuration).
"""

import argparse
import contextlib
import dataclasses
import inspect
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from _common import RESULTS, ROOT, load_average, markdown_table, median

CACHE = Path("/tmp/cscsr_bench")
RECORDING_VERSION = 1  # part of the cache key: bump when the recording's recipe changes
WINDOW = 41  # the network's window; output frames every WINDOW spike frames (the default --every)
SCALE = 4
CAPTURE_SPIKE_FRAMES = 8_000_000  # a terabyte of the 1000x1000 camera's capture
OUTPUT_FRAMES_PER_TB = round(CAPTURE_SPIKE_FRAMES / WINDOW)  # 195,122
GOAL_JOB_OVER_STAND_IN = 1.15  # job seconds per frame <= 1.15 S: the device never waits
GOAL_CPU_PER_FRAME = 0.15  # non-network CPU seconds of the worker per output frame
BF16_DENSE_PEAK_TFLOPS = {"H100 PCIe": 756.0, "H100": 989.4, "H200": 989.4, "A100": 312.0}  # by name, first match


# --- the recording ---

def scene(side_hr: int, seed: int = 0) -> np.ndarray:
    """(side_hr, side_hr, 3) uint8: smooth colour gradients plus fine texture (something for the flow net to see)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:side_hr, 0:side_hr].astype(np.float32) * (1000 / side_hr * 4)  # features scale with the side
    channels = [0.5 + 0.25 * np.sin(x / 37 + k) * np.cos(y / 53 - k) + 0.15 * np.sin((x + (0.6 + k / 5) * y) / 23)
                for k in range(3)]
    texture = rng.random((side_hr // 4 + 1, side_hr // 4 + 1), dtype=np.float32)
    texture = np.kron(texture, np.ones((4, 4), np.float32))[:side_hr, :side_hr] - 0.5  # 4-pixel blocks
    image = np.stack([c + 0.1 * texture for c in channels], axis=-1)
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)


def simulate_recording(work: Path, side: int, frames: int) -> str:
    """Simulate ``frames`` spike frames of side x side LR RGGB (a still picture) into ``work/spikes.zarr``."""
    import cv2

    from pipeline.simulate import SimulateOptions, simulate

    picture = work / "scene.png"
    cv2.imwrite(str(picture), scene(side * SCALE)[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1])  # RGB -> BGR
    store = work / "spikes.zarr"
    simulate(str(picture), str(store), SimulateOptions(scale=SCALE, cfa="rggb", frames=frames, motion="static",
                                                       truth_every=frames, overwrite=True), progress=False)
    return str(store)


def cached_recording(side: int, frames: int) -> tuple[str, float]:
    """The recording of ``frames`` spike frames at ``side``, simulated once and kept in :data:`CACHE` under
    a name made of its parameters; -> (its URL, seconds spent simulating now: 0 when it was cached)."""
    folder = CACHE / f"recording-v{RECORDING_VERSION}-side{side}-frames{frames}"
    store = folder / "spikes.zarr"
    if (folder / "done").exists():
        return str(store), 0.0
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    print(f"simulating {frames} spike frames of {side}x{side} RGGB into {folder} ...", file=sys.stderr, flush=True)
    start = time.perf_counter()
    simulate_recording(folder, side, frames)
    seconds = time.perf_counter() - start
    (folder / "done").write_text(f"{seconds:.1f} s\n")
    print(f"simulated in {seconds:.1f} s", file=sys.stderr, flush=True)
    return str(store), seconds


# --- the stand-in: a measuring instrument, not a product path ---

def stand_in_picture(store_url: str) -> Path:
    """The stand-in's output picture, made once per recording and saved beside it: the first window's TFP
    image (``stages.tfp.tfp_image``) at the store's gain, enlarged x4 to HR, (4H, 4W, 3) uint8."""
    path = Path(store_url).parent / "stand_in_picture.npy"
    if not path.exists():
        from pipeline.spike_store import open_spike_store
        from stages.tfp import tfp_image

        store = open_spike_store(store_url)
        meta = store.meta
        image, _ = tfp_image(store.read(0, WINDOW), width=meta.width, cfa=meta.cfa, gain=meta.gain, scale=SCALE,
                             reset=meta.reset)
        np.save(path, image)
    return path


class StandInDevice:
    """A measuring instrument standing in for the network on a GPU (``--stand-in S``), never a product path.

    Same input and output shapes as what it replaces; a pass of n windows sleeps n * S seconds without
    using the CPU (as a GPU kernel leaves it free) and returns the fixed picture (:func:`stand_in_picture`,
    cropped to the tile's HR size), from buffers made once per shape, so that the output costs the CPU
    what the device's output costs it: nothing until the pipeline compresses and writes it.

    :meth:`device_images` replaces ``NetworkReconstructor.device_images`` (the device-side path: packed
    bits in, uint8 HR images out); :meth:`model` replaces the model of the old path ({"image": float
    rates}, exposed to the picture by the store's gain). Each pass is logged (start, stop, windows)."""

    def __init__(self, seconds: float, picture: str):
        self.seconds = seconds
        self.picture_path = picture
        self._picture = None
        self._buffers = {}
        self._lock = threading.RLock()  # _buffer makes a buffer from picture() while holding it
        self.passes = []  # (perf_counter at start, at stop, windows)

    def picture(self) -> np.ndarray:
        with self._lock:
            if self._picture is None:
                self._picture = np.load(self.picture_path)
            return self._picture

    def _sleep(self, windows: int) -> None:
        start = time.perf_counter()
        time.sleep(windows * self.seconds)
        self.passes.append((start, time.perf_counter(), windows))

    def _buffer(self, key, make):
        with self._lock:
            if key not in self._buffers:
                self._buffers[key] = make()
            return self._buffers[key]

    def device_images(self, packed, window):
        """(B, N, h, ceil(w/8)) uint8 tensor -> (B, s*h, s*w, 3) uint8 tensor, after B * S seconds."""
        import torch

        batch, height, width = packed.shape[0], packed.shape[2] * window.scale, window.width * window.scale
        self._sleep(batch)
        return self._buffer(("uint8", batch, height, width), lambda: torch.from_numpy(
            np.ascontiguousarray(np.broadcast_to(self.picture()[:height, :width], (batch, height, width, 3)))))

    def model(self, spikes, cfa, zero_reset, scale, gain):
        """(B, N, h, w) float tensor -> {"image": (B, 3, s*h, s*w) float32 rates}, after B * S seconds."""
        import torch

        batch, height, width = spikes.shape[0], spikes.shape[-2] * scale, spikes.shape[-1] * scale
        self._sleep(batch)

        def rates():
            rgb = self.picture()[:height, :width].astype(np.float32) / np.float32(255 * gain)
            return torch.from_numpy(np.ascontiguousarray(np.broadcast_to(rgb.transpose(2, 0, 1),
                                                                         (batch, 3, height, width))))

        return {"image": self._buffer(("rates", batch, height, width, gain), rates)}


class _OldModelStandIn:
    """The old path's model (called as ``model(x, cfa, zero_reset, scale)``) answered by the stand-in;
    every other attribute (``config``, ...) is the real model's."""

    def __init__(self, real, stand_in: StandInDevice, gain: float):
        self._real, self._stand_in, self._gain = real, stand_in, gain

    def __call__(self, spikes, cfa, zero_reset=False, scale=SCALE):
        return self._stand_in.model(spikes, cfa, zero_reset, scale, self._gain)

    def __getattr__(self, name):
        return getattr(self._real, name)


def install_stand_in(seconds: float, picture: str, gain: float) -> str:
    """In this process: wrap ``pipeline.reconstruct.reconstructor`` so that every reconstructor it returns
    runs :class:`StandInDevice` instead of the network; -> which path the reconstructor has: "device-side"
    (it has ``device_images``) or "old". Idempotent."""
    import pipeline.reconstruct as reconstruct_module
    from cscsr.reconstructor import NetworkReconstructor

    path = "device-side" if hasattr(NetworkReconstructor, "device_images") else "old"
    original = getattr(reconstruct_module.reconstructor, "measured_original", reconstruct_module.reconstructor)
    stand_in = StandInDevice(seconds, picture)

    def reconstructor(*args, **kwargs):
        method = original(*args, **kwargs)
        if isinstance(method, NetworkReconstructor) and getattr(method, "stand_in", None) is None:
            method.stand_in = stand_in
            if path == "device-side":
                method.device_images = stand_in.device_images
            else:
                method.model = _OldModelStandIn(method.model, stand_in, gain)
        return method

    reconstructor.measured_original = original
    reconstructor.stand_in = stand_in
    reconstruct_module.reconstructor = reconstructor
    return path


def stand_in_passes() -> list:
    """In a worker: the stand-in's passes so far, (start, stop, windows) on this process's perf_counter."""
    import pipeline.reconstruct as reconstruct_module

    return list(reconstruct_module.reconstructor.stand_in.passes)


def stand_in_plugin(seconds: float, picture: str, gain: float):
    """A WorkerPlugin installing the stand-in (:func:`install_stand_in`) in every worker, one that joins later too."""
    from distributed import WorkerPlugin

    class StandInPlugin(WorkerPlugin):
        name = "benchmark-stand-in"

        def setup(self, worker):
            worker.stand_in_path = install_stand_in(seconds, picture, gain)

    return StandInPlugin()


# --- the cluster ---

@contextlib.contextmanager
def gpu_worker_client():
    """A local cluster of one GPU worker and its client; -> (client, how it was made).

    ``pipeline.cluster.dask_client(workers=1, gpus=1)`` where it takes ``gpus`` (a pinned GPU worker
    running several tasks at once); else one worker process with one thread advertising ``GPU=1``, as
    compose's ``gpu-worker`` (``--nthreads 1 --resources GPU=1``), with ``dask_client``'s settings."""
    import dask
    from distributed import Client, LocalCluster

    import pipeline.cluster as cluster

    if "gpus" in inspect.signature(cluster.dask_client).parameters:
        with cluster.dask_client(workers=1, gpus=1) as client:
            yield client, "pipeline.cluster.dask_client(workers=1, gpus=1)"
        return
    with dask.config.set(getattr(cluster, "_PRE_SPAWN", {})), \
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
    from pipeline.reconstruct_plan import ReconstructOptions

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

    from pipeline.reconstruct import reconstruct

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
    from pipeline.video_store import VIDEO, open_video_store

    group = open_video_store(url)
    shape = group[VIDEO].shape
    if group.attrs.get("state") != "complete" or shape != (frames, side * SCALE, side * SCALE, 3):
        raise RuntimeError(f"{url}: state {group.attrs.get('state')!r}, video {shape}: not the expected output")
    video = Path(url) / VIDEO
    size = sum(p.stat().st_size for p in video.rglob("*") if p.is_file())
    return {"tile": group.attrs.get("tile_lr"), "bytes_per_frame": size / frames}


# --- the stand-in mode ---

def measure_stand_in(args, store: str, work: Path) -> dict:
    """``--stand-in S``: the warm job with the stand-in in the worker; figures per repeat and medians."""
    from cscsr.weights_io import default_weights
    from pipeline.spike_store import open_spike_store

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

    import pipeline.reconstruct as reconstruct_module
    from pipeline.spike_store import open_spike_store, read_frames
    from pipeline.video_store import TileWriter, create_video_store
    from stages.methods import Window, output_centres
    from stages.tiles import tile_grid

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

        from cscsr.reconstructor import one_thread_on_cpu

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

    from cscsr.reconstructor import load_reconstructor
    from pipeline.spike_store import open_spike_store
    from stages.methods import Window

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


# --- the real network ---

def task_windows(store_url: str, tile: int, halo: int, batch: int):
    """The windows the job reads, in passes of ``batch`` consecutive output frames of one tile."""
    from pipeline.spike_store import open_spike_store, read_frames
    from stages.methods import Window, output_centres
    from stages.tiles import tile_grid

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
    ``--gpu-batch``, else what the device's memory holds (``pipeline.reconstruct.sized``, where it exists)."""
    most = args.gpu_batch
    if most is None and method.device.type == "cuda":
        import torch

        with contextlib.suppress(ImportError):
            from pipeline.reconstruct import Placement, sized

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

    from stages.bits import unpack_rows

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

    from cscsr.reconstructor import one_thread_on_cpu

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

    from cscsr.reconstructor import load_reconstructor
    from cscsr.weights_io import default_weights

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


def gpu_peak_mib() -> float | None:
    """This process's high-water mark of GPU memory allocated by torch (MiB) since its start or the last
    reset; None where it has not used CUDA (run in the worker too, through ``client.run``)."""
    import torch

    if not (torch.cuda.is_available() and torch.cuda.is_initialized()):
        return None
    return torch.cuda.max_memory_allocated() / 2**20


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


# --- reporting ---

def save(folder: Path, data: dict, merge: bool = False) -> Path:
    """``folder/gpu_pipeline.json`` with the machine's description beside the data; with ``merge``, the runs
    already there of configurations not measured now are kept."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "gpu_pipeline.json"
    if merge and path.exists() and "runs" in data:
        key = lambda run: (run["config"], run["precision"], run.get("fast_gpu", False))  # noqa: E731
        now = {key(run) for run in data["runs"]}
        data["runs"] = [r for r in json.loads(path.read_text()).get("runs", []) if key(r) not in now] + data["runs"]
    machine = {"cpus": os.cpu_count(), "cpu": cpu_model(), "python": platform.python_version(),
               "platform": platform.platform(), "load_average_at_end": os.getloadavg()}
    path.write_text(json.dumps({"benchmark": "gpu_pipeline", "machine": machine, **data}, indent=2) + "\n")
    return path


def cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor()


def verdict(value: float, goal: float) -> str:
    return "PASS" if value <= goal else "FAIL"


def print_stand_in(result: dict, args) -> None:
    s = args.stand_in
    job, cpu = result["job_seconds_per_frame_runs"], result["non_network_cpu_seconds_per_frame_runs"]
    rows = [["job seconds per output frame", f"{result['job_seconds_per_frame']:.3f}",
             f"{min(job):.3f} - {max(job):.3f}", f"<= {GOAL_JOB_OVER_STAND_IN * s:.3f} (1.15 x {s})",
             verdict(result["job_seconds_per_frame"], GOAL_JOB_OVER_STAND_IN * s)],
            ["worker CPU seconds per output frame", f"{result['non_network_cpu_seconds_per_frame']:.3f}",
             f"{min(cpu):.3f} - {max(cpu):.3f}", f"<= {GOAL_CPU_PER_FRAME}",
             verdict(result["non_network_cpu_seconds_per_frame"], GOAL_CPU_PER_FRAME)],
            ["of which system (kernel) CPU", f"{median(result['of_which_system_cpu_seconds_per_frame_runs']):.3f}",
             "", "", ""],
            ["device busy share", f"{result['device_busy_share']:.2f}", "", "", ""]]
    first = result["device_busy"][len(result["device_busy"]) // 2]
    middle = len(result["device_busy"]) // 2
    idle = (f"the device idle {first['before_first_pass_seconds']:.2f} s before the first pass, "
            f"{first['idle_between_passes_seconds']:.2f} s between passes and {first['after_last_pass_seconds']:.2f} s "
            f"after the last ({first['passes']} passes of {first['windows_per_pass']} windows); the job's first task "
            f"began {result['job_before_first_task_seconds_runs'][middle]:.2f} s after the job, which ended "
            f"{result['job_after_last_task_seconds_runs'][middle]:.2f} s after its last task")
    print(f"## GPU pipeline, CPU proxy: stand-in of {s} s per window, {result['path']} path\n")
    print(f"{args.frames} output frames of {args.side}x{args.side} RGGB -> x{SCALE}, tile {result['tile']}, "
          f"{result['chunks_written']} chunks written, {result['worker_threads']} worker thread(s) "
          f"({result['cluster']}), "
          f"{result['output_bytes_per_frame'] / 1e6:.1f} MB per output frame at rest; medians of {args.repeats}; "
          f"in the middle run {idle}.\n")
    print(markdown_table(["figure", "median", "range", "goal", ""], rows))
    if "profile_cpu_seconds_per_frame" in result:
        profile = result["profile_cpu_seconds_per_frame"]
        steps = [[name, f"{v['cpu']:.3f}", f"{v['wall']:.3f}"] for name, v in profile.items() if isinstance(v, dict)]
        print(f"\nOne task's steps, here, one after the other ({profile['frames_per_task']} frames), "
              f"per output frame:\n")
        print(markdown_table(["step", "CPU s", "wall s"], steps))
    if "picture_against_network" in result:
        against = result["picture_against_network"]
        rows = [[name, f"{v['bytes_per_hr_pixel']:.2f}", f"{1000 * v['seconds_per_hr_megapixel']:.1f}"]
                for name, v in against.items() if isinstance(v, dict)]
        print(f"\nThe stand-in's picture against the network's output ({against['lr_side']}x{against['lr_side']} LR, "
              f"zstd level 1, one thread):\n")
        print(markdown_table(["image", "bytes per HR pixel", "ms per HR megapixel"], rows))


def print_network(result: dict, args) -> None:
    rows = [[r["config"], r["precision"], r["tile"], f"{r['forward_frames_per_second']:.2f}",
             f"{r['reconstructor_frames_per_second']:.2f}", f"{r['pipeline_frames_per_second']:.2f}",
             f"{100 * r['pipeline_share_of_forward']:.0f} %", f"{r['forward_tflops_per_second']:.1f}",
             f"{100 * r['forward_share_of_bf16_peak']:.1f} %" if r["forward_share_of_bf16_peak"] else "-",
             f"{r['gpu_hours_per_terabyte']:.1f}"] for r in result["runs"]]
    print(f"## GPU pipeline: {args.frames} output frames of {args.side}x{args.side} RGGB -> x{SCALE} on "
          f"{result['device']}{' (' + result['gpu'] + ')' if result['gpu'] else ''}\n")
    print(markdown_table(["config", "precision", "tile", "forward frames/s", "reconstructor frames/s",
                          "pipeline frames/s", "pipeline / forward", "forward TFLOP/s", "of bf16 peak",
                          "GPU-hours per TB"], rows))
    print(f"\nGPU-hours per terabyte: {OUTPUT_FRAMES_PER_TB:,} output frames (8 M spike frames, one per {WINDOW}) "
          f"at the pipeline's frames/s. Medians of {args.repeats}. Goals (H100): pipeline >= 85 % of the forward "
          f"pass; full bf16 >= 6 frames/s; lite >= 15.")
    if result.get("cli_seconds") is not None:
        print(f"The command line, cold ({result['runs'][0]['config']}): {result['cli_seconds']:.1f} s.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stand-in", type=float, default=None, metavar="S",
                        help="the CPU proxy: a stand-in network of S seconds per window (no GPU needed)")
    parser.add_argument("--frames", type=int, default=40, help="output frames (41 spike frames each; default 40)")
    parser.add_argument("--side", type=int, default=1000, help="LR height = width, even (default 1000)")
    parser.add_argument("--tile", type=int, default=None, help="LR tile (default: the pipeline's choice)")
    parser.add_argument("--gpu-batch", type=int, default=None, help="windows per pass on the GPU worker (default: "
                        "the pipeline's choice)")
    parser.add_argument("--configs", default="lite", help="network configurations, comma-separated (lite,full)")
    parser.add_argument("--precisions", default="fp32", help="fp32,bf16")
    parser.add_argument("--weights", default=None, help="a weights file instead of the shipped ones (one config)")
    parser.add_argument("--fast-gpu", action="store_true", help="ReconstructOptions(fast_gpu=True): channels-last, "
                        "cuDNN autotuning, torch.compile on the GPU worker")
    parser.add_argument("--forward-batch", type=int, default=None, help="windows per pass of the forward pass alone "
                        "(default: the reconstructor's batch)")
    parser.add_argument("--device", choices=["cuda", "cpu"], default=None,
                        help="the real network's device (default: cuda if torch sees a GPU, else cpu)")
    parser.add_argument("--repeats", type=int, default=None, help="timed runs (default 3 with --stand-in, else 2)")
    parser.add_argument("--profile", action="store_true", help="with --stand-in: CPU per frame of each task step")
    parser.add_argument("--cli", action="store_true", help="also time the command line, cold (real network)")
    parser.add_argument("--merge", action="store_true", help="keep other configurations' runs already in the JSON")
    parser.add_argument("--out", type=Path, default=RESULTS, help=f"folder for the JSON (default {RESULTS})")
    parser.add_argument("--quick", action="store_true", help="a smoke run: side 64, 2 frames, 1 repeat")
    args = parser.parse_args()
    if args.quick:
        args.side, args.frames, args.repeats = 64, 2, 1
    args.repeats = args.repeats or (3 if args.stand_in is not None else 2)
    configs, precisions = args.configs.split(","), args.precisions.split(",")
    if args.side < 8 or args.side % 2 or args.frames < 1 or args.repeats < 1:
        parser.error("--side must be an even number >= 8, --frames and --repeats >= 1")
    if args.stand_in is not None and args.stand_in < 0:
        parser.error("--stand-in must be >= 0 seconds")
    if args.weights and len(configs) > 1:
        parser.error("--weights names one network: give one --configs")

    import torch

    if args.stand_in is not None:
        device = "cpu"
    else:
        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        if device == "cuda" and not torch.cuda.is_available():
            parser.error("--device cuda: torch sees no GPU")
    if device == "cpu":
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # the workers (spawned from here) pick their device alone
    gpu = torch.cuda.get_device_name() if device == "cuda" else None

    load_start = load_average()
    spike_frames = WINDOW * args.frames
    store, simulate_seconds = cached_recording(args.side, spike_frames)
    work = Path(tempfile.mkdtemp(prefix="gpu-pipeline-", dir=CACHE))
    common = {"side": args.side, "scale": SCALE, "window": WINDOW, "every": WINDOW, "output_frames": args.frames,
              "spike_frames": spike_frames, "repeats": args.repeats, "recording": store,
              "simulate_seconds_now": simulate_seconds, "torch": torch.__version__, "device": device, "gpu": gpu,
              "load_average_at_start": load_start}
    try:
        if args.stand_in is not None:
            result = {**common, **measure_stand_in(args, store, work)}
            print_stand_in(result, args)
        else:
            runs = [measure_network(args, store, work, config, precision, device, gpu)
                    for config in configs for precision in precisions]
            result = {**common, "mode": "network", "output_frames_per_terabyte": OUTPUT_FRAMES_PER_TB, "runs": runs}
            if args.cli:
                result["cli_seconds"] = run_cli(store, work / "cli.zarr", runs[0]["weights"], device)
            print_network(result, args)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"\nLoad average at start {load_start}, at end {load_average()}.")
    print(f"(results: {save(args.out, result, args.merge)})")


if __name__ == "__main__":
    main()
