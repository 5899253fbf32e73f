"""Dask's own memory per task: the reference for the soak's slow growth.

What: ``--tasks`` trivial tasks (``i + 1``, no Zarr, none of our stages) through the same
bounded submission the pipeline uses (``pipeline.compute.executor.in_bounded_window``), on a local
cluster of 2 worker processes; the current RSS of the client process (which hosts the
scheduler) and of each worker every ``--every`` tasks. If the soak's growth per task
(``benchmarks/soak.py``) reappears here, it comes from Dask's bookkeeping, not from ours.
Not in CI.

Run: ``python benchmarks/dask_task_memory.py [--tasks 40000] [--every 5000]``.
"""

import argparse
import os
import sys
import time

from _common import ROOT, load_average, markdown_table, save_results
from reconstruct_memory import resident


def plus_one(i: int) -> int:
    return i + 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", type=int, default=40000)
    parser.add_argument("--every", type=int, default=5000)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT))
    from distributed import Client, LocalCluster

    from pipeline.compute.executor import in_bounded_window, window_size

    samples = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        pids = list(client.run(os.getpid).values())
        start = time.perf_counter()
        submitted = (client.submit(plus_one, i, pure=False) for i in range(args.tasks))
        for done, future in enumerate(in_bounded_window(submitted, window_size(client)), 1):
            future.result()
            if done % args.every == 0:
                samples.append({"tasks": done, "seconds": time.perf_counter() - start,
                                "workers": [resident(pid) for pid in pids], "client": resident(os.getpid())})
    first = samples[0]
    rows = [[f"{s['tasks']:,}", f"{s['seconds']:.0f}", f"{max(s['workers']) / 2**20:.0f}", f"{s['client'] / 2**20:.0f}"]
            for s in samples]
    last = samples[-1]

    def per_task(before: int, after: int) -> float:
        """KiB of RSS gained per task between the first and the last sample."""
        return (after - before) / (last["tasks"] - first["tasks"]) / 1024

    print(f"\ntrivial tasks, 2 workers; load average {load_average()}\n")
    print(markdown_table(["tasks done", "seconds", "largest worker RSS MiB", "client + scheduler RSS MiB"], rows))
    print(f"\ngrowth per task after the first {first['tasks']:,}: worker "
          f"{per_task(max(first['workers']), max(last['workers'])):.2f} KiB, client "
          f"{per_task(first['client'], last['client']):.2f} KiB")
    save_results("dask_task_memory", {"samples": samples})


if __name__ == "__main__":
    main()
