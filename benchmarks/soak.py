"""Soak: reconstruction of very long recordings (up to 1,000,000 frames) in bounded memory and graph size.

What: for recordings of ``--lengths`` frames (default 10,000, 100,000 and 1,000,000) of small
16x16 RGGB frames (an integrate-and-fire simulation of a slowly changing scene, written
straight into a spike store in blocks), ``pipeline.reconstruct.reconstruct`` with TFP, window
41, an output frame every 41 spike frames (244, 2,439 and 24,390 output frames; one task
each), on a local cluster of 2 worker processes. Measured per length, in a fresh interpreter:
wall time, output frames per second, the kernel's peak RSS (VmHWM) of each worker and of the
client process (which hosts the scheduler), and the largest number of tasks the scheduler
held at once (sampled every 20 ms). Reference: the shortest recording. Goal: memory and the
scheduler's task count flat across lengths (a bounded submission window, tasks reading only
their own window). Peaks alone cannot tell a leak from caches filling up to their bounds, so
the current RSS of workers and client is also sampled every second: the table gives it at the
half-way point and at the end of each run (a leak keeps growing over the second half; bounded
caches have stopped). Not in CI: the longest run takes minutes.

Run: ``python benchmarks/soak.py [--lengths 10000,100000,1000000] [--size 16]``.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time

from _common import ROOT, load_average, markdown_table, save_results
from reconstruct_memory import high_water, resident


def write_recording(url: str, frames: int, size: int) -> None:
    import numpy as np

    from pipeline.spike_store import SpikeMeta, SpikeStoreWriter
    from stages.bits import pack_rows

    meta = SpikeMeta(height=size, width=size, cfa="rggb", gain=2.0)
    writer = SpikeStoreWriter(url, meta, frames)
    rng = np.random.default_rng(0)
    acc = rng.random((size, size), dtype=np.float32)
    block = writer.chunk_frames
    count = 0
    for start in range(0, frames, block):
        n = min(block, frames - start)
        rate = (0.1 + 0.2 * (0.5 + 0.5 * np.sin(start / 5000 + np.arange(size)[None, :] / 4))).astype(np.float32)
        rate = np.broadcast_to(rate, (size, size))
        bits = np.empty((n, size, size), np.uint8)
        for i in range(n):
            acc += rate
            fired = acc >= 1
            acc -= fired
            bits[i] = fired
        packed = pack_rows(bits)
        writer.spikes[start : start + n] = packed
        count += int(bits.sum())
    writer.finish(spike_count=count)


def child(store: str, out: str) -> dict:
    from distributed import Client, LocalCluster

    from pipeline.reconstruct import ReconstructOptions, reconstruct

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        most, stop = [0], threading.Event()
        pids = list(client.run(os.getpid).values())
        timeline = []  # (seconds, largest worker RSS, client RSS), every second

        def sample():
            tick = time.perf_counter()
            while not stop.wait(0.02):
                most[0] = max(most[0], len(cluster.scheduler.tasks))
                if time.perf_counter() - tick >= 1:
                    tick = time.perf_counter()
                    timeline.append((tick - start, max(map(resident, pids)), resident(os.getpid())))

        start = time.perf_counter()
        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        counts = reconstruct(store, out, ReconstructOptions(every=41, tile=256, gain=2.0), client=client, progress=False)
        seconds = time.perf_counter() - start
        stop.set()
        sampler.join()
        workers = [high_water(pid) for pid in pids]
    half = [row for row in timeline if row[0] >= seconds / 2][:1] or timeline[-1:]
    return {"seconds": seconds, "frames": counts["frames"], "worker_peaks": workers,
            "client_peak": high_water(os.getpid()), "most_scheduler_tasks": most[0],
            "rss_half": half[0][1:] if half else None, "rss_end": timeline[-1][1:] if timeline else None,
            "timeline": timeline}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lengths", default="10000,100000,1000000")
    parser.add_argument("--size", type=int, default=16)
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(*args.child)))
        return
    sys.path.insert(0, str(ROOT))
    rows, results = [], []
    with tempfile.TemporaryDirectory() as scratch:
        for frames in map(int, args.lengths.split(",")):
            store, out = f"{scratch}/rec{frames}.zarr", f"{scratch}/out{frames}.zarr"
            write_recording(store, frames, args.size)
            run = subprocess.run([sys.executable, __file__, "--child", store, out], cwd=ROOT, capture_output=True,
                                 text=True, check=True)
            result = {"spike_frames": frames, **json.loads(run.stdout.strip().splitlines()[-1])}
            results.append(result)
            print(f"{frames} frames: {result['seconds']:.1f} s", file=sys.stderr, flush=True)
    base = results[0]
    for r in results:
        rows.append([f"{r['spike_frames']:,}", f"{r['frames']:,}", f"{r['seconds']:.1f}", f"{r['frames'] / r['seconds']:.0f}",
                     f"{max(r['worker_peaks']) / 2**20:.0f} ({max(r['worker_peaks']) / max(base['worker_peaks']):.2f}x)",
                     f"{r['client_peak'] / 2**20:.0f} ({r['client_peak'] / base['client_peak']:.2f}x)",
                     f"{r['most_scheduler_tasks']}", _growth(r, 0), _growth(r, 1)])
    print(f"\n{args.size}x{args.size} RGGB, TFP, every 41, 2 workers; load average {load_average()}\n")
    print(markdown_table(["spike frames", "output frames (tasks)", "seconds", "output frames / s",
                          "largest worker peak RSS MiB (vs shortest)", "client + scheduler peak RSS MiB (vs shortest)",
                          "most tasks held by the scheduler", "worker RSS MiB half-way -> end",
                          "client RSS MiB half-way -> end"], rows))
    save_results("soak", {"size": args.size, "runs": results})


def _growth(run: dict, which: int) -> str:
    if not run["rss_half"]:
        return "(run under 1 s)"
    return f"{run['rss_half'][which] / 2**20:.0f} -> {run['rss_end'][which] / 2**20:.0f}"


if __name__ == "__main__":
    main()
