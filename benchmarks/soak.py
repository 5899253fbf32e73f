"""Soak: reconstruction of very long recordings (up to 1,000,000 frames) in bounded memory and graph size.

What: for recordings of ``--lengths`` frames (default 100,000, 300,000 and 1,000,000) of small
16x16 RGGB frames (an integrate-and-fire simulation of a slowly changing scene, written
straight into a spike store in blocks), ``pipeline.jobs.reconstruct.reconstruct`` with TFP, window
41, an output frame every 41 spike frames (2,439, 7,317 and 24,390 output frames; one task
each), as ``cscsr reconstruct --workers 2`` runs it: in segments of ``--segment`` tasks, each in
a fresh process with a fresh local cluster of 2 workers (``pipeline.compute.executor.in_segments``). Measured per
length, in a fresh interpreter, by sampling the job's process tree every second: wall time,
output frames per second, peak RSS (VmHWM) of the largest worker, of the largest segment
process (client and scheduler) and of the job's own process. Reference: the shortest
recording. Goal: every peak flat across lengths. Peaks alone cannot tell a leak from caches
filling to their bounds, so the current RSS is given half-way and at the end of each run too.
The graph stays bounded by construction (at most ``4 * workers + 4`` tasks submitted and
unfinished; ``tests/test_reconstruct.py::test_submission_stays_in_a_bounded_window``).
Not in CI: the longest run takes minutes.

Run: ``python benchmarks/soak.py [--lengths 100000,300000,1000000] [--size 16] [--segment 2500]``.
"""

import argparse
import contextlib
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

    from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter
    from stages.capture.bits import pack_rows

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


def child(store: str, out: str, segment: int) -> dict:
    """Run the job as ``cscsr reconstruct`` does (its own clusters, in segments); sample the process tree."""
    import psutil

    from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct

    me = psutil.Process()
    stop = threading.Event()
    timeline = []  # (seconds, largest worker RSS, largest segment RSS, this process's RSS), every second
    peaks = {"worker": 0, "segment": 0}

    def sample():
        while not stop.wait(1.0):
            now = {"worker": 0, "segment": 0}  # largest current RSS per role
            for process, depth in descendants(me):
                role = "segment" if depth == 1 else "worker"  # depth 2: nannies, 3: worker processes
                with contextlib.suppress(psutil.Error, OSError):  # a process may end between listing and reading
                    peaks[role] = max(peaks[role], high_water(process.pid))
                    now[role] = max(now[role], resident(process.pid))
            timeline.append((time.perf_counter() - start, now["worker"], now["segment"], resident(os.getpid())))

    start = time.perf_counter()
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    counts = reconstruct(store, out, ReconstructOptions(every=41, tile=256, gain=2.0, segment_tasks=segment), workers=2,
                         progress=False)
    seconds = time.perf_counter() - start
    stop.set()
    sampler.join()
    busy = [row for row in timeline if row[1]]  # samples while a segment's workers were up
    half = [row for row in busy if row[0] >= seconds / 2][:1] or busy[-1:]
    return {"seconds": seconds, "frames": counts["frames"], "segments": -(-counts["tasks_run"] // segment),
            "worker_peak": peaks["worker"], "segment_peak": peaks["segment"], "job_peak": high_water(os.getpid()),
            "rss_half": half[0][1:] if half else None, "rss_end": busy[-1][1:] if busy else None, "timeline": timeline}


def descendants(process, depth: int = 1):
    """(process, depth) for every process below ``process``."""
    for kid in process.children():
        yield kid, depth
        yield from descendants(kid, depth + 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lengths", default="100000,300000,1000000")
    parser.add_argument("--size", type=int, default=16)
    parser.add_argument("--segment", type=int, default=2500,
                        help="tasks per segment (cscsr reconstruct's --segment-tasks; under the shortest run's tasks)")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(*args.child, args.segment)))
        return
    sys.path.insert(0, str(ROOT))
    rows, results = [], []
    with tempfile.TemporaryDirectory() as scratch:
        for frames in map(int, args.lengths.split(",")):
            store, out = f"{scratch}/rec{frames}.zarr", f"{scratch}/out{frames}.zarr"
            write_recording(store, frames, args.size)
            command = [sys.executable, __file__, "--child", store, out, "--segment", str(args.segment)]
            run = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=True)
            result = {"spike_frames": frames, **json.loads(run.stdout.strip().splitlines()[-1])}
            results.append(result)
            print(f"{frames} frames: {result['seconds']:.1f} s", file=sys.stderr, flush=True)
    base = results[0]
    for r in results:
        rows.append([f"{r['spike_frames']:,}", f"{r['frames']:,}", f"{r['segments']}", f"{r['seconds']:.1f}",
                     f"{r['frames'] / r['seconds']:.0f}", _peak(r, base, "worker_peak"), _peak(r, base, "segment_peak"),
                     _peak(r, base, "job_peak"), _growth(r, 0), _growth(r, 1)])
    print(f"\n{args.size}x{args.size} RGGB, TFP, every 41, 2 workers, {args.segment:,} tasks per segment; "
          f"load average {load_average()}\n")
    print(markdown_table(["spike frames", "output frames (tasks)", "segments", "seconds", "output frames / s",
                          "largest worker peak RSS MiB (vs shortest)", "segment (client + scheduler) peak MiB",
                          "job process peak MiB", "worker RSS MiB half-way -> end",
                          "segment RSS MiB half-way -> end"], rows))
    save_results("soak", {"size": args.size, "segment": args.segment, "runs": results})


def _peak(run: dict, base: dict, key: str) -> str:
    return f"{run[key] / 2**20:.0f} ({run[key] / base[key]:.2f}x)"


def _growth(run: dict, which: int) -> str:
    if not run["rss_half"]:
        return "(run under 1 s)"
    return f"{run['rss_half'][which] / 2**20:.0f} -> {run['rss_end'][which] / 2**20:.0f}"


if __name__ == "__main__":
    main()
