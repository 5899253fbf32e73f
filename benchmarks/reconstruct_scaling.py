"""Scaling of the distributed reconstruction from one worker process to two.

What: ``pipeline.jobs.reconstruct.reconstruct(..., client=...)`` of the same job on a local
cluster of 1 and of 2 worker processes: TFP of a 1000-frame 512x512 RGGB recording, window
41, every 10 (98 output frames of 2048x2048), tile 256 (4 tasks per frame), fixed gain.
Each cluster is started and warmed (every worker imports the pipeline and OpenCV) before the
clock starts, so start-up is excluded. Reference: the one-worker time, same run.
Goal: speed-up t(1) / t(2) >= 1.8 (1.85 for the network). The outputs of 1 and 2 workers must be identical arrays
(checked every repetition).

The workers' CPU time (user + system, from psutil) is recorded too, with the time of this
process (client and scheduler): if two workers use about the CPU one does but do not halve
the wall time, the machine's cores were not free (the machine is shared) or the workers
wait on each other; if they use much more CPU, the work itself got dearer (threads
oversubscribed: the pipeline gives numba/OpenMP ``cores // workers`` threads per worker,
but OpenCV's own pool, used by demosaicking and resizing, takes all cores in every worker).

The recording comes from ``reconstruct_overhead.py`` (an integrate-and-fire simulation of a
smooth colour scene, rates 0.05-0.3, cached as ``.dat`` under /tmp/cscsr_bench, ingested to a
temporary store). Repetitions alternate the order of 1 and 2 workers; the speed-up is the
median of the per-repetition ratios. Outputs are deleted.

``--method cscsr`` times the network instead (each worker runs it on one thread, so one worker
uses one core). Its reference ceiling, ``--ceiling``: the same work with no pipeline at all, the
network's forward pass on one task's tile (with its halo) in one process alone, then in two
processes at once, one thread each: 2 x t(alone) / t(together) is what two cores of this machine
give two independent copies of the work (shared memory bandwidth and caches, and on a VM whatever
the host does), so what the pipeline loses beyond it is ours.

Run: ``python benchmarks/reconstruct_scaling.py [--frames N] [--every K] [--tile T] [--repeats R] [--method tfp|cscsr] [--ceiling]``;
the network case of #25: ``--method cscsr --frames 205 --size 256 --every 41 --tile 128 --ceiling``.
"""

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import psutil
from _common import load_average, markdown_table, median, random_window, save_results, timed
from reconstruct_overhead import (
    CACHE,
    SCALE,
    WINDOW,
    fresh,
    middle_gain,
    options,
    outputs_equal,
    spike_store,
    warm_worker,
)

GOALS = {"tfp": 1.8, "cscsr": 1.85}  # the network's from #25


def cpu_seconds(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        times = psutil.Process(pid).cpu_times()
        total += times.user + times.system
    return total


def _forward_seconds(side: int, repeats: int, start_at: float) -> float:
    """Median seconds of ``lite``'s forward pass on a side x side LR window, one thread, from ``start_at``."""
    import torch

    from cscsr.weights.weights_io import default_weights, load_model

    torch.set_num_threads(1)
    network = load_model(default_weights("lite"))[0]
    spikes = torch.from_numpy(random_window(side, WINDOW))
    with torch.inference_mode():
        network(spikes, "rggb", False, SCALE)  # warm
        while time.time() < start_at:  # both processes time the same moments
            time.sleep(0.01)
        return timed(lambda: network(spikes, "rggb", False, SCALE), repeats)[0]


def machine_ceiling(side: int, repeats: int) -> dict:
    """2 x t(one process alone) / t(two processes at once): the speed-up two independent copies of the
    network's work get from this machine's two cores."""
    import concurrent.futures
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=context) as pool:
        alone = pool.submit(_forward_seconds, side, repeats, time.time() + 20).result()
    with concurrent.futures.ProcessPoolExecutor(2, mp_context=context) as pool:
        start_at = time.time() + 30  # after both have imported torch and loaded the network
        together = [f.result() for f in [pool.submit(_forward_seconds, side, repeats, start_at) for _ in range(2)]]
    return {"side": side, "alone_s": alone, "together_s": together, "speedup": 2 * alone / max(together)}


def timed_run(store: str, out: Path, workers: int, every: int, gain: float, tile: int, method: str) -> dict:
    """Start and warm a cluster, then time reconstruct(client=...) on it alone."""
    from pipeline.compute.cluster import dask_client
    from pipeline.jobs.reconstruct import reconstruct

    fresh(out)
    with dask_client(workers=workers) as client:
        pids = list(client.run(warm_worker).values())
        cv2_threads = sorted(set(client.run(lambda: __import__("cv2").getNumThreads()).values()))
        worker_cpu, own_cpu = cpu_seconds(pids), cpu_seconds([os.getpid()])
        start = time.perf_counter()
        counts = reconstruct(store, str(out), options(every, gain, tile, method), client=client, progress=False)
        seconds = time.perf_counter() - start
        worker_cpu, own_cpu = cpu_seconds(pids) - worker_cpu, cpu_seconds([os.getpid()]) - own_cpu
    return {"seconds": seconds, "worker_cpu_seconds": worker_cpu, "client_cpu_seconds": own_cpu,
            "tasks": counts["tasks_run"], "frames": counts["frames"], "cv2_threads_per_worker": cv2_threads}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000, help="spike frames of the recording (default 1000)")
    parser.add_argument("--size", type=int, default=512, help="LR height = width (default 512)")
    parser.add_argument("--every", type=int, default=10, help="spike frames between output frames (default 10)")
    parser.add_argument("--tile", type=int, default=256, help="tile size, LR pixels (default 256: 4 tasks per frame)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions of each worker count (default 3)")
    parser.add_argument("--method", default="tfp", choices=("tfp", "cscsr"), help="tfp (default) or the network")
    parser.add_argument("--ceiling", action="store_true", help="also the machine's own 1 -> 2 process ceiling (cscsr)")
    args = parser.parse_args()

    load_start = load_average()
    CACHE.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="reconstruct-scaling-", dir=CACHE))
    runs = []
    try:
        store = spike_store(args.frames, args.size, args.size, work / "spikes.zarr")
        gain = middle_gain(store, WINDOW, args.every)
        out = {1: work / "w1.zarr", 2: work / "w2.zarr"}
        for rep in range(args.repeats):
            order = (1, 2) if rep % 2 == 0 else (2, 1)
            result = {"rep": rep, "order": list(order), "load_average": load_average()}
            for workers in order:
                result[workers] = timed_run(store, out[workers], workers, args.every, gain, args.tile, args.method)
                print(f"rep {rep} workers={workers}: {result[workers]['seconds']:.2f} s", file=sys.stderr)
            result["identical"] = outputs_equal(str(out[1]), str(out[2]))
            runs.append(result)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    ceiling = None
    if args.ceiling:
        from pipeline.jobs.reconstruct_tasks import reconstructor

        halo = reconstructor("cscsr", None).halo  # a task's tile is read with this margin on each side
        ceiling = machine_ceiling(args.tile + 2 * halo, args.repeats)

    goal = GOALS[args.method]
    t1, t2 = median(r[1]["seconds"] for r in runs), median(r[2]["seconds"] for r in runs)
    speedup = median(r[1]["seconds"] / r[2]["seconds"] for r in runs)
    cpu1, cpu2 = median(r[1]["worker_cpu_seconds"] for r in runs), median(r[2]["worker_cpu_seconds"] for r in runs)
    identical = all(r["identical"] for r in runs)
    first = runs[0][1]
    summary = [
        ["1 worker, start-up excluded", f"{t1:.2f}", f"{cpu1:.1f}", f"{cpu1 / t1:.2f}", "1.00", "reference", "-"],
        ["2 workers, start-up excluded", f"{t2:.2f}", f"{cpu2:.1f}", f"{cpu2 / t2:.2f}", f"{speedup:.2f}",
         f">= {goal}", "PASS" if speedup >= goal else "FAIL"],
        ["outputs of 1 and 2 workers identical", "yes" if identical else "NO", "-", "-", "-", "identical",
         "PASS" if identical else "FAIL"],
    ]
    per_run = [[r["rep"], " then ".join(map(str, r["order"])), f"{r[1]['seconds']:.2f}", f"{r[2]['seconds']:.2f}",
                f"{r[1]['seconds'] / r[2]['seconds']:.2f}", f"{r[1]['worker_cpu_seconds']:.1f}",
                f"{r[2]['worker_cpu_seconds']:.1f}", f"{r[1]['client_cpu_seconds']:.1f} / {r[2]['client_cpu_seconds']:.1f}",
                r["load_average"].split(" (")[0]] for r in runs]
    if ceiling:
        summary.append([f"machine ceiling: lite forward on {ceiling['side']}x{ceiling['side']}, 2 processes vs 1, "
                        f"no pipeline", f"{ceiling['alone_s']:.2f} / {max(ceiling['together_s']):.2f}", "-", "-",
                        f"{ceiling['speedup']:.2f}", "reference", "-"])
    print(f"## Reconstruction scaling, 1 -> 2 workers: {args.method} of {args.frames} frames of {args.size}x{args.size} RGGB -> "
          f"{first['frames']} frames of {args.size * SCALE}x{args.size * SCALE} (window {WINDOW}, every {args.every}, "
          f"tile {args.tile}: {first['tasks']} tasks, gain {gain:.3f})\n")
    print(markdown_table(["run", "seconds (median)", "worker CPU s", "cores busy (CPU s / s)", "speed-up", "goal",
                          "result"], summary))
    print()
    print(markdown_table(["rep", "order (workers)", "1 worker s", "2 workers s", "speed-up", "CPU s, 1 worker",
                          "CPU s, 2 workers", "client+scheduler CPU s (1 / 2)", "load avg 1/5/15 at rep start"], per_run))
    print(f"\nMedians of {args.repeats} repetitions; the speed-up is the median of per-repetition ratios. OpenCV "
          f"threads per worker: {runs[0][1]['cv2_threads_per_worker']} with 1 worker, "
          f"{runs[0][2]['cv2_threads_per_worker']} with 2, on {os.cpu_count()} CPUs. Load average at start {load_start}, "
          f"at end {load_average()}: other work on the machine makes timings noisy.")
    path = save_results("reconstruct_scaling", {
        "frames": args.frames, "size": args.size, "scale": SCALE, "window": WINDOW, "every": args.every,
        "tile": args.tile, "method": args.method, "machine_ceiling": ceiling, "gain": gain, "runs": [{**{k: v for k, v in r.items() if k not in (1, 2)},
                                                    "workers_1": r[1], "workers_2": r[2]} for r in runs],
        "median_seconds_1": t1, "median_seconds_2": t2, "speedup": speedup, "median_worker_cpu_seconds_1": cpu1,
        "median_worker_cpu_seconds_2": cpu2, "outputs_identical": identical, "load_average_at_start": load_start,
        "goal_speedup": goal, "goal_met": speedup >= goal,
    })
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
