"""Peak memory of the distributed reconstruction against the length of the recording.

What: ``pipeline.jobs.reconstruct.reconstruct(..., client=...)`` on a local cluster of 2 worker
processes, TFP of a 256x256 RGGB recording of 2,000 frames and of one 10x longer (20,000
frames), window 41, every 41 (48 and 487 output frames of 1024x1024), tile 256 (one task per
frame), fixed gain. Measured: the peak resident memory (RSS) of each worker process and of
the client process (which also hosts the scheduler and the nannies of a local cluster).
Reference: the same figures for the shorter recording. Goal: the largest worker peak for
the 10x longer recording within 10 % of the shorter one's (memory must not grow with the
recording: tasks are submitted in a bounded window and each reads only its own window).

Each run is a fresh interpreter (so the client's peak is that run's alone) with a fresh
cluster: peaks are the kernel's high-water marks (``VmHWM`` of each process, read when the
run ends, so nothing between samples is missed); a background thread
also samples every process's RSS every 50 ms (psutil, by pid) to record the RSS after start-up
and warm-up (imports), at the end of the run, and the sampled peak. Repetitions alternate
the order of the two lengths; figures are medians over repetitions.

The recordings come from ``reconstruct_overhead.py`` (an integrate-and-fire simulation of a
smooth colour scene, rates 0.05-0.3, cached as ``.dat`` under /tmp/cscsr_bench, ingested into
temporary stores). Outputs are deleted.

Run: ``python benchmarks/reconstruct_memory.py [--frames N] [--factor F] [--size S] [--repeats R]``.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from _common import ROOT, load_average, markdown_table, median, save_results
from reconstruct_overhead import CACHE, SCALE, WINDOW, fresh, middle_gain, options, spike_store, warm_worker

GOAL = 1.10
WORKERS = 2
EVERY = 41
SAMPLE_S = 0.05
MiB = 2**20


def high_water(pid: int) -> int:
    """A process's high-water RSS, bytes: ``VmHWM`` of its memory map (Linux).

    Not ``ru_maxrss``: Linux carries that across fork + exec, so a fresh interpreter would
    report the peak of the process that started it.
    """
    return memory_field(pid, "VmHWM")


def resident(pid: int) -> int:
    """A process's current RSS, bytes (``VmRSS``)."""
    return memory_field(pid, "VmRSS")


def memory_field(pid: int, field: str) -> int:
    """A memory figure (kB in ``/proc/<pid>/status``) in bytes."""
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {field} in /proc/{pid}/status")


class Sampler(threading.Thread):
    """Samples the RSS of some processes (by pid) until stopped."""

    def __init__(self, pids: dict[str, int]):
        import psutil

        super().__init__(daemon=True)
        self.procs = {name: psutil.Process(pid) for name, pid in pids.items()}
        self.first = {name: p.memory_info().rss for name, p in self.procs.items()}
        self.peak = dict(self.first)
        self.last = dict(self.first)
        self.samples = 0
        self.stopping = threading.Event()

    def run(self) -> None:
        while not self.stopping.is_set():
            for name, proc in self.procs.items():
                rss = proc.memory_info().rss
                self.last[name], self.peak[name] = rss, max(self.peak[name], rss)
            self.samples += 1
            self.stopping.wait(SAMPLE_S)

    def stop(self) -> None:
        self.stopping.set()
        self.join()


def child(store: str, out: str, gain: float, tile: int) -> dict:
    """One measured run (in a fresh interpreter): cluster, warm-up, sampled reconstruct."""
    from pipeline.compute.cluster import dask_client
    from pipeline.jobs.reconstruct import reconstruct

    with dask_client(workers=WORKERS) as client:
        pids = client.run(warm_worker)
        names = {f"worker {i}": pid for i, pid in enumerate(sorted(pids.values()))}
        sampler = Sampler({**names, "client": os.getpid()})
        sampler.start()
        start = time.perf_counter()
        counts = reconstruct(store, out, options(EVERY, gain, tile), client=client, progress=False)
        seconds = time.perf_counter() - start
        sampler.stop()
        peaks = {name: high_water(pid) for name, pid in {**names, "client": os.getpid()}.items()}
    return {"seconds": seconds, "frames": counts["frames"], "tasks": counts["tasks_run"], "samples": sampler.samples,
            "rss_after_warmup": sampler.first, "rss_at_end": sampler.last, "sampled_peak": sampler.peak, "peak": peaks}


def measure(store: str, out: Path, gain: float, tile: int) -> dict:
    fresh(out)
    proc = subprocess.run([sys.executable, __file__, "--child", store, str(out), repr(gain), str(tile)], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    if proc.returncode:
        raise RuntimeError(f"measured run failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.splitlines()[-1])


def mib(value: float) -> str:
    return f"{value / MiB:.0f}"


def main() -> None:
    if len(sys.argv) == 6 and sys.argv[1] == "--child":
        print(json.dumps(child(sys.argv[2], sys.argv[3], float(sys.argv[4]), int(sys.argv[5]))))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000, help="frames of the shorter recording (default 2000)")
    parser.add_argument("--factor", type=int, default=10, help="how many times longer the other one is (default 10)")
    parser.add_argument("--size", type=int, default=256, help="LR height = width (default 256)")
    parser.add_argument("--tile", type=int, default=256, help="tile size, LR pixels (default 256)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions of each length (default 3)")
    args = parser.parse_args()

    load_start = load_average()
    lengths = (args.frames, args.frames * args.factor)
    CACHE.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="reconstruct-memory-", dir=CACHE))
    runs = {n: [] for n in lengths}
    try:
        stores = {n: spike_store(n, args.size, args.size, work / f"spikes-{n}.zarr") for n in lengths}
        gain = middle_gain(stores[lengths[0]], WINDOW, EVERY)  # one gain for both: the same work per task
        for rep in range(args.repeats):
            for n in lengths[:: 1 if rep % 2 == 0 else -1]:
                result = measure(stores[n], work / "out.zarr", gain, args.tile)
                result["load_average"] = load_average()
                runs[n].append(result)
                print(f"rep {rep} {n} frames: {result['seconds']:.1f} s, worker peaks "
                      f"{[mib(v) for k, v in result['peak'].items() if k != 'client']} MiB, "
                      f"client {mib(result['peak']['client'])} MiB", file=sys.stderr)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    def med(n: int, what: str, name: str) -> float:
        return median(r[what][name] for r in runs[n])

    def worst_worker(n: int, what: str) -> float:
        return median(max(v for k, v in r[what].items() if k != "client") for r in runs[n])

    short, long = lengths
    worker_ratio = worst_worker(long, "peak") / worst_worker(short, "peak")
    client_ratio = med(long, "peak", "client") / med(short, "peak", "client")
    summary = [
        ["largest worker peak RSS, MiB", mib(worst_worker(short, "peak")), mib(worst_worker(long, "peak")),
         f"{worker_ratio:.3f}", f"<= {GOAL:.2f}", "PASS" if worker_ratio <= GOAL else "FAIL"],
        ["client + scheduler process peak RSS, MiB", mib(med(short, "peak", "client")), mib(med(long, "peak", "client")),
         f"{client_ratio:.3f}", "(reported)", "-"],
    ]
    names = sorted(runs[short][0]["peak"], key=lambda k: (k == "client", k))
    detail = []
    for name in names:
        for n in lengths:
            detail.append([name, n, f"{median(r['seconds'] for r in runs[n]):.1f}", mib(med(n, "rss_after_warmup", name)),
                           mib(med(n, "sampled_peak", name)), mib(med(n, "peak", name)), mib(med(n, "rss_at_end", name))])
    first = {n: runs[n][0] for n in lengths}
    print(f"## Reconstruction memory: TFP of {args.size}x{args.size} RGGB recordings of {short} and {long} frames "
          f"({first[short]['frames']} and {first[long]['frames']} output frames of {args.size * SCALE}x{args.size * SCALE}; "
          f"window {WINDOW}, every {EVERY}, tile {args.tile}, {WORKERS} workers, gain {gain:.3f})\n")
    print(markdown_table(["figure", f"{short} frames", f"{long} frames", "ratio", "goal", "result"], summary))
    print()
    print(markdown_table(["process", "frames", "run s", "RSS after start-up + warm-up, MiB", "sampled peak, MiB",
                          "high-water (VmHWM), MiB", "RSS at end, MiB"], detail))
    print(f"\nMedians of {args.repeats} runs per length, each in a fresh interpreter with a fresh cluster; RSS sampled every "
          f"{1000 * SAMPLE_S:.0f} ms. Worker processes are numbered by pid. Load average at start {load_start}, at end "
          f"{load_average()}.")
    path = save_results("reconstruct_memory", {
        "lengths": list(lengths), "size": args.size, "scale": SCALE, "window": WINDOW, "every": EVERY, "tile": args.tile,
        "workers": WORKERS, "gain": gain, "runs": {str(n): runs[n] for n in lengths},
        "largest_worker_peak_bytes": {str(n): worst_worker(n, "peak") for n in lengths},
        "client_peak_bytes": {str(n): med(n, "peak", "client") for n in lengths},
        "ratio_worker_peak": worker_ratio, "ratio_client_peak": client_ratio, "load_average_at_start": load_start,
        "goal_ratio": GOAL, "goal_met": worker_ratio <= GOAL,
    })
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
