"""The lazy graphs (``cscsr.lazy``) against the job they mirror, and the cost of building a long recording's graph.

What (issue #45):

1. **Graph.** ``open_spikes`` + ``windows(every=41)`` + ``tfp`` of a spike store of ``--long`` spike frames (default
   1,000,000) of 64x64 LR RGGB (chunks of the store's ~4 MiB: 8,192 frames), and + ``reconstruct`` with the shipped
   ``lite`` at tile 256 of one of 1000x1000 (a task per batch of output frames and tile: ~10^5 tasks, made only when
   computed), each built in a fresh process: the seconds to build it and the growth of the process's peak resident
   memory (``VmHWM``) over its state after the imports (and the network's weights). The store holds metadata only:
   nothing can be read (computing it would fail). Goals: < 5 s and < 1 GB.
2. **Lazy against the job.** On one ``LocalCluster`` of 2 single-threaded worker processes (started and warmed
   before the clock), ``pipeline.jobs.reconstruct.reconstruct(..., client=)`` (the reference) and
   ``lazy.to_video(lazy.reconstruct(lazy.windows(lazy.open_spikes(...))))`` with the same options, on the same
   recording: TFP of a 256x256 RGGB recording of ``--frames`` (default 2,000) spike frames every 41 (48 output
   frames of 1024x1024, tile 128: 4 tasks a frame), and the shipped ``lite`` network on its region 0:64,0:64 over
   the first 0.05 s (``--lite-stop``: 24 output frames of 256x256, tile 64). Each repetition runs both in
   an alternating order, outputs removed; the outputs must be byte-identical (checked every repetition). The ratio
   is the median of the per-repetition ratios (lazy / job). Goal: <= 1.15.

The recording is ``reconstruct_overhead.py``'s (integrate-and-fire of a smooth drifting colour scene, rates
0.05-0.3, cached under /tmp/cscsr_bench). Run: ``python benchmarks/lazy_graphs.py [--repeats R] [--frames N]
[--long N]``; results in ``benchmarks/results/lazy_graphs.json``.
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import ROOT, load_average, markdown_table, median, save_results
from reconstruct_overhead import spike_store

GOAL_RATIO, GOAL_SECONDS, GOAL_BYTES = 1.15, 5.0, 2**30

BUILD = """
import sys, time
from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter

def high_water() -> int:
    return int(next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:"))) * 1024

frames, url, side, stage = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
writer = SpikeStoreWriter(url, SpikeMeta(height=side, width=side, cfa="rggb", fps=20000.0), frames)
writer.finish(spike_count=0)  # metadata only: no chunk to read, and the graph must not read one
from cscsr import lazy  # imports (torch and the weights for the network), then the clock
import dask.array, xarray, distributed
if stage == "lite":
    import torch
    from pipeline.jobs.reconstruct_tasks import reconstructor
    reconstructor("cscsr", "lite", "fp32", "torch", device="cpu")
before = high_water()
began = time.perf_counter()
win = lazy.windows(lazy.open_spikes(url), every=41)
hr = lazy.tfp(win) if stage == "tfp" else lazy.reconstruct(win, method="cscsr", weights="lite", tile=256)
seconds = time.perf_counter() - began
print(seconds, high_water() - before, hr.shape[0], len(hr.data.__dask_graph__()), writer.chunk_frames)
"""
BUILDS = {"tfp": 64, "lite": 1000}  # the stage -> the recording's side (LR pixels)


def graph_build(frames: int, folder: Path, stage: str) -> dict:
    """Part 1 for one stage, in a fresh process."""
    side = BUILDS[stage]
    done = subprocess.run([sys.executable, "-c", BUILD, str(frames), str(folder / "long.zarr"), str(side), stage],
                          capture_output=True, text=True, cwd=ROOT, check=True)
    seconds, grown, outputs, tasks, chunk = done.stdout.split()
    shutil.rmtree(folder / "long.zarr")
    return {"stage": stage, "side": side, "spike_frames": frames, "seconds": float(seconds),
            "memory_bytes": int(grown), "output_frames": int(outputs), "tasks": int(tasks), "chunk_frames": int(chunk)}


def side_by_side(client, store: str, folder: Path, options: dict, repeats: int) -> dict:
    """Part 2 for one method: the job and the lazy graph alternately, ``repeats`` times each."""
    import zarr

    from cscsr import lazy
    from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct

    part = {k: options[k] for k in ("start", "stop", "region") if k in options}
    stage = {k: options[k] for k in ("method", "weights", "tile") if k in options}

    def job(out: str):
        reconstruct(store, out, ReconstructOptions(**options), client=client, progress=False)

    def lazily(out: str):
        lazy.to_video(lazy.reconstruct(lazy.windows(lazy.open_spikes(store), every=options["every"], **part), **stage),
                      out)

    seconds = {"job": [], "lazy": []}
    for repeat in range(repeats):
        order = [("job", job), ("lazy", lazily)][:: 1 if repeat % 2 == 0 else -1]
        for name, run in order:
            out = folder / f"{name}.zarr"
            shutil.rmtree(out, ignore_errors=True)
            began = time.perf_counter()
            run(str(out))
            seconds[name].append(time.perf_counter() - began)
        job_video, lazy_video = (zarr.open_group(str(folder / f"{n}.zarr"), mode="r")["video"][:] for n in ("job", "lazy"))
        if not np.array_equal(job_video, lazy_video):
            raise SystemExit(f"{options['method']}: the lazy graph's video differs from the job's")
    ratios = [lz / jb for lz, jb in zip(seconds["lazy"], seconds["job"])]
    return {"job_seconds": median(seconds["job"]), "lazy_seconds": median(seconds["lazy"]), "ratio": median(ratios),
            "frames": int(zarr.open_group(str(folder / "job.zarr"), mode="r")["frames"].shape[0]),
            "runs": seconds, "options": options}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--long", type=int, default=1_000_000)
    parser.add_argument("--lite-stop", default="0.05s")
    args = parser.parse_args()
    from distributed import Client, LocalCluster

    print(f"load average before: {load_average()}")
    with tempfile.TemporaryDirectory(prefix="cscsr-lazy-bench-") as tmp:
        folder = Path(tmp)
        builds = [graph_build(args.long, folder, stage) for stage in BUILDS]
        store = spike_store(args.frames, 256, 256, folder / "rec.zarr")
        methods = {"tfp": {"method": "tfp", "every": 41, "tile": 128, "gain": None},
                   "lite": {"method": "cscsr", "weights": "lite", "every": 41, "tile": 64, "stop": args.lite_stop,
                            "region": "0:64,0:64"}}
        results = {}
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
                Client(cluster) as client:
            client.run(lambda: __import__("pipeline.jobs.reconstruct") and __import__("cscsr.inference.reconstructor"))  # warm
            for name, options in methods.items():
                options = {k: v for k, v in options.items() if v is not None}
                results[name] = side_by_side(client, store, folder, options, args.repeats)
    rows = [[name, r["frames"], f"{r['job_seconds']:.2f}", f"{r['lazy_seconds']:.2f}", f"{r['ratio']:.3f}",
             "PASS" if r["ratio"] <= GOAL_RATIO else "FAIL"] for name, r in results.items()]
    print(f"\n## Lazy graph against the job (2 worker processes, median of {args.repeats})\n")
    print(markdown_table(["method", "output frames", "job s", "lazy s", f"lazy / job (goal <= {GOAL_RATIO})", ""], rows))
    print(f"\n## Building the graph of {args.long:,} spike frames (chunks of the store's ~4 MiB)\n")
    print(markdown_table(["stage", "LR side", "output frames", "tasks", f"seconds (goal < {GOAL_SECONDS:g})",
                          "memory (goal < 1 GB)", ""],
                         [[b["stage"], b["side"], b["output_frames"], b["tasks"], f"{b['seconds']:.2f}",
                           f"{b['memory_bytes'] / 2**20:.0f} MiB",
                           "PASS" if b["seconds"] < GOAL_SECONDS and b["memory_bytes"] < GOAL_BYTES else "FAIL"]
                          for b in builds]))
    print(f"\nload average after: {load_average()}")
    print(save_results("lazy_graphs", {"repeats": args.repeats, "methods": results, "graphs": builds}))


if __name__ == "__main__":
    main()
