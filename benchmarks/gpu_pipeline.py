"""Overhead of ``cscsr reconstruct --method cscsr`` on one (GPU) worker against the network's forward pass alone.

What: a simulated RGGB spike recording of ``--side`` x ``--side`` LR pixels (default 1000x1000,
the camera's size) with ``41 * --frames`` spike frames (default 8 output frames at the default
window 41 and every 41), reconstructed at x4 by the CSCSR network (``--weights``, default the
shipped ``cscsr-lite``), four ways, all on ``--device`` (default: cuda when there is one):

(b) the command line, timed whole as a user sees it: ``python -m cscsr reconstruct STORE OUT
    --method cscsr --weights W --workers 1`` in a subprocess (interpreter and torch start-up,
    model load in the client and in the worker, local Dask cluster start-up and shut-down,
    the tasks, the writes);
(c) ``pipeline.reconstruct.reconstruct(..., client=...)`` on a one-worker local cluster started
    and warmed before the clock starts (the worker has imported the pipeline, loaded the model
    onto the device and run the whole job once untimed): the pipeline's steady-state cost;
(r) the reference, in this process: the same reconstructor (``cscsr.reconstructor
    .load_reconstructor``) called with ``many()`` on exactly the windows the pipeline's tasks
    build (same tiles, same 32-pixel halo, same batches of 4 output frames of one tile),
    read into memory beforehand: unpacking, host-to-device copy, forward, copy back, exposure;
(f) the forward pass alone: the network on the same batches, already unpacked and on the
    device, synchronised before and after each batch (nothing but the model's own time).

Output frames per second are printed for each, and overhead = t / t(f) - 1 (and / t(r) - 1).
(b) on a GPU machine is dominated by fixed start-up costs (CUDA initialisation and model load
in two processes, cluster start-up); (c) shows what the pipeline adds per task.

The recording is made by the project's own simulator (``pipeline.simulate.simulate``, Algorithm
2: a still image through the RGGB sensor, ``--motion static``, one ground-truth frame) from a
generated smooth-plus-texture colour picture of (4 * side)^2 HR pixels, on a local cluster of one
worker per core; its time is printed but is not part of any figure. On CPU the network runs on
one thread per worker (the pipeline's rule, so that bytes do not depend on the worker count),
and (r) and (f) do the same. ``--device cpu`` on a machine with a GPU hides it from the
pipeline (``CUDA_VISIBLE_DEVICES=``), so all variants run on the CPU.

Run: ``python benchmarks/gpu_pipeline.py [--frames N] [--side S] [--weights W] [--device cuda|cpu]
[--repeats R] [--out DIR] [--quick]``; ``--quick`` is a CPU smoke run (side 64, 2 frames, 1 repeat).
Results: ``DIR/gpu_pipeline.json`` (default ``benchmarks/results``). Temporary stores are deleted.
"""

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import RESULTS, ROOT, load_average, markdown_table, median

CACHE = Path("/tmp/cscsr_bench")
WINDOW = 41  # the network's window; output frames every WINDOW spike frames (the default --every)
SCALE = 4


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


def simulate_recording(work: Path, side: int, frames: int) -> tuple[str, float]:
    """Simulate ``frames`` spike frames of side x side LR RGGB into a spike store; (its URL, seconds)."""
    import cv2

    from pipeline.simulate import SimulateOptions, simulate

    picture = work / "scene.png"
    cv2.imwrite(str(picture), scene(side * SCALE)[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1])  # RGB -> BGR
    store = work / "spikes.zarr"
    start = time.perf_counter()
    simulate(str(picture), str(store), SimulateOptions(scale=SCALE, cfa="rggb", frames=frames, motion="static",
                                                       truth_every=frames, overwrite=True), progress=False)
    return str(store), time.perf_counter() - start


# --- the reference: the same tasks, no pipeline ---

def task_windows(store_url: str, batch: int, halo: int, tile: int):
    """What each pipeline task reconstructs, in the pipeline's order: a list of lists of Windows."""
    from stages.methods import output_centres
    from pipeline.spike_store import open_spike_store, read_frames
    from stages.methods import Window
    from stages.tiles import tile_grid

    store = open_spike_store(store_url)
    meta = store.meta
    centres = output_centres(store.n_frames, WINDOW, WINDOW)
    grid = tile_grid(meta.height, meta.width, tile, halo)
    half = WINDOW // 2
    tasks = []
    for start in range(0, len(centres), batch):
        group = centres[start : start + batch]
        for row in grid:
            for t in row:
                region = (slice(t.ry0, t.ry1), slice(t.rx0 // 8, -(-t.rx1 // 8)))
                tasks.append([Window(read_frames(store.spikes, store_url, c - half, c + half + 1, region),
                                     t.rx1 - t.rx0, meta.cfa, meta.reset, float(meta.gain), SCALE) for c in group])
    return tasks, len(centres), len(grid) * len(grid[0])


def time_reconstructor(method, tasks) -> float:
    """(r): ``method.many`` on every task's windows, one after the other."""
    import torch

    start = time.perf_counter()
    for windows in tasks:
        method.many(windows)
    if method.device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


def time_forward(method, tasks) -> float:
    """(f): the model alone on each task's batch, input already unpacked and on the device; summed."""
    import torch

    from cscsr.reconstructor import one_thread_on_cpu
    from stages.bits import unpack_rows

    cuda = method.device.type == "cuda"
    total = 0.0
    for windows in tasks:
        first = windows[0]
        spikes = np.stack([unpack_rows(w.packed, w.width) for w in windows])
        with one_thread_on_cpu(method.device), torch.inference_mode():
            x = torch.from_numpy(spikes).to(method.device, torch.float32)
            if cuda:
                torch.cuda.synchronize()
            start = time.perf_counter()
            method.model(x, first.cfa, first.reset == "zero", first.scale)["image"]
            if cuda:
                torch.cuda.synchronize()
            total += time.perf_counter() - start
    return total


# --- the pipeline ---

def cli_env(device: str) -> dict:
    """The environment of the command line run: this checkout importable; the GPU hidden for --device cpu."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    if device == "cpu":
        env["CUDA_VISIBLE_DEVICES"] = ""
    return env


def run_cli(store: str, out: Path, weights: str, device: str) -> float:
    """(b): ``python -m cscsr reconstruct ... --workers 1``, wall clock of the whole command."""
    command = [sys.executable, "-m", "cscsr", "reconstruct", store, str(out), "--method", "cscsr",
               "--weights", weights, "--workers", "1", "--overwrite"]
    start = time.perf_counter()
    run = subprocess.run(command, check=False, cwd=ROOT, env=cli_env(device), capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode:
        raise RuntimeError(f"{' '.join(command)} failed ({run.returncode}):\n"
                           f"{run.stdout[-2000:]}\n{run.stderr[-4000:]}")
    return seconds


def warm_network_worker(weights: str) -> dict:
    """Run on the worker before timing: import the pipeline, load the model onto its device."""
    import torch

    from pipeline.reconstruct import reconstructor

    method = reconstructor("cscsr", weights)
    return {"pid": os.getpid(), "device": str(method.device),
            "gpu": torch.cuda.get_device_name() if method.device.type == "cuda" else None}


def check_output(url: str, frames: int, side: int) -> None:
    from pipeline.video_store import VIDEO, open_video_store

    group = open_video_store(url)
    shape = group[VIDEO].shape
    if group.attrs.get("state") != "complete" or shape != (frames, side * SCALE, side * SCALE, 3):
        raise RuntimeError(f"{url}: state {group.attrs.get('state')!r}, video {shape}: not the expected output")


def save(folder: Path, data: dict) -> Path:
    """``folder/gpu_pipeline.json`` with the machine's description beside the data (as ``_common.save_results``)."""
    folder.mkdir(parents=True, exist_ok=True)
    machine = {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
               "load_average_at_end": os.getloadavg()}
    path = folder / "gpu_pipeline.json"
    path.write_text(json.dumps({"benchmark": "gpu_pipeline", "machine": machine, **data}, indent=2) + "\n")
    return path


def main() -> None:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8, help="output frames (41 spike frames each; default 8)")
    parser.add_argument("--side", type=int, default=1000, help="LR height = width, even (default 1000)")
    parser.add_argument("--weights", default=None, help="network weights (default: the shipped cscsr-lite)")
    parser.add_argument("--device", choices=["cuda", "cpu"], default=None,
                        help="default: cuda if torch sees a GPU, else cpu")
    parser.add_argument("--repeats", type=int, default=2, help="timed runs of (c), (r) and (f) (default 2)")
    parser.add_argument("--out", type=Path, default=RESULTS, help=f"folder for the JSON (default {RESULTS})")
    parser.add_argument("--quick", action="store_true", help="a CPU smoke run: side 64, 2 frames, 1 repeat")
    args = parser.parse_args()
    if args.quick:
        args.side, args.frames, args.repeats = 64, 2, 1
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch sees no GPU")
    if args.side < 8 or args.side % 2 or args.frames < 1 or args.repeats < 1:
        parser.error("--side must be an even number >= 8, --frames and --repeats >= 1")
    from cscsr.weights_io import default_weights

    weights = str(Path(args.weights or default_weights("lite")).resolve())
    if device == "cpu":
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # the pipeline's workers (spawned from here) pick their device alone
    gpu = torch.cuda.get_device_name() if device == "cuda" else None

    from cscsr.reconstructor import load_reconstructor
    from pipeline.cluster import dask_client
    from pipeline.reconstruct import ReconstructOptions, reconstruct
    from pipeline.reconstruct_plan import DEFAULT_TILE

    load_start = load_average()
    CACHE.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="gpu-pipeline-", dir=CACHE))
    spike_frames = WINDOW * args.frames
    timings = {"c": [], "r": [], "f": []}
    try:
        print(f"simulating {spike_frames} spike frames of {args.side}x{args.side} RGGB ...", file=sys.stderr,
              flush=True)
        store, simulate_seconds = simulate_recording(work, args.side, spike_frames)
        print(f"simulated in {simulate_seconds:.1f} s", file=sys.stderr, flush=True)

        # (b): the command line, cold, as a user runs it
        cli_seconds = run_cli(store, work / "b.zarr", weights, device)
        check_output(str(work / "b.zarr"), args.frames, args.side)
        print(f"(b) cscsr reconstruct --workers 1: {cli_seconds:.2f} s", file=sys.stderr, flush=True)

        # (c): a warm one-worker cluster
        opts = ReconstructOptions(method="cscsr", weights=weights, window=WINDOW, every=WINDOW, scale=SCALE,
                                  tile=DEFAULT_TILE, overwrite=True)
        start = time.perf_counter()
        with dask_client(workers=1) as client:
            worker = next(iter(client.run(warm_network_worker, weights).values()))
            reconstruct(store, str(work / "c.zarr"), opts, client=client, progress=False)  # warm-up: every tile shape
            startup = time.perf_counter() - start
            for rep in range(args.repeats):
                start = time.perf_counter()
                counts = reconstruct(store, str(work / "c.zarr"), opts, client=client, progress=False)
                timings["c"].append(time.perf_counter() - start)
                print(f"(c) rep {rep}: {timings['c'][-1]:.2f} s", file=sys.stderr, flush=True)
        check_output(str(work / "c.zarr"), args.frames, args.side)
        if worker["device"].split(":")[0] != device:
            raise RuntimeError(f"the pipeline's worker ran the network on {worker['device']}, not {device}")

        # (r) and (f): the same windows in this process, no pipeline
        method = load_reconstructor(weights, device)
        tasks, frames, tiles = task_windows(store, method.batch, method.halo, DEFAULT_TILE)
        time_reconstructor(method, tasks)  # warm-up: every tile shape
        for rep in range(args.repeats):
            timings["r"].append(time_reconstructor(method, tasks))
            timings["f"].append(time_forward(method, tasks))
            print(f"(r) rep {rep}: {timings['r'][-1]:.2f} s, (f): {timings['f'][-1]:.2f} s", file=sys.stderr,
                  flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    med = {name: median(values) for name, values in timings.items()}
    med["b"] = cli_seconds
    fps = {name: frames / seconds for name, seconds in med.items()}
    overhead = {name: med[name] / med["f"] - 1 for name in "bcr"}
    over_r = {name: med[name] / med["r"] - 1 for name in "bc"}
    labels = {
        "b": "(b) `cscsr reconstruct --method cscsr --workers 1`, whole command (start-up included)",
        "c": "(c) reconstruct(client=...), 1 warm worker (start-up excluded)",
        "r": "(r) reconstructor.many() on the same windows, in memory, one process",
        "f": "(f) forward pass alone (input on the device, synchronised)",
    }
    rows = [[labels[n], f"{med[n]:.2f}", f"{fps[n]:.2f}", f"{1000 * med[n] / frames:.0f}",
             f"{100 * overhead[n]:+.0f} %" if n != "f" else "reference",
             f"{100 * over_r[n]:+.0f} %" if n in over_r else "-"] for n in "bcrf"]
    print(f"## CSCSR pipeline overhead: {frames} output frames of {args.side}x{args.side} RGGB -> "
          f"{args.side * SCALE}x{args.side * SCALE} on {device}{f' ({gpu})' if gpu else ''}\n")
    print(f"Window {WINDOW}, every {WINDOW}, tile {DEFAULT_TILE} + halo {method.halo} ({tiles} tiles per frame), "
          f"batches of {method.batch} frames per task ({len(tasks)} tasks), weights {Path(weights).name}, "
          f"torch {torch.__version__}.\n")
    print(markdown_table(["variant", "seconds (median)", "output frames/s", "ms/frame", "overhead vs (f)",
                          "overhead vs (r)"], rows))
    print(f"\nSimulation of the recording ({spike_frames} spike frames): {simulate_seconds:.1f} s (not in any figure). "
          f"(c)'s cluster start-up, worker warm-up (model load) and untimed first run: {startup:.2f} s. "
          f"Medians of {args.repeats} runs except (b) (one cold run). Load average at start {load_start}, at end "
          f"{load_average()}.")
    path = save(args.out, {
        "device": device, "gpu": gpu, "torch": torch.__version__, "side": args.side, "scale": SCALE,
        "window": WINDOW, "every": WINDOW, "tile": DEFAULT_TILE, "halo": method.halo, "batch": method.batch,
        "output_frames": frames, "spike_frames": spike_frames, "tiles_per_frame": tiles, "tasks": len(tasks),
        "weights": weights, "worker": worker, "simulate_seconds": simulate_seconds, "cli_seconds": cli_seconds,
        "runs_seconds": timings, "median_seconds": med, "output_frames_per_second": fps,
        "overhead_vs_forward": overhead, "overhead_vs_reconstructor": over_r,
        "warm_cluster_startup_seconds": startup, "tasks_run": counts["tasks_run"],
        "load_average_at_start": load_start,
    })
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
