"""Local cluster start-up: workers forked from one server (``pipeline.compute.worker_start.forked_workers``) against
workers spawned as Dask does by default, in one run.

Each measurement is a fresh process that opens ``--clusters`` local clusters of 2 CPU workers one after another (a
job's segments; a test module's jobs) and, on each, runs one task per worker that reads a Zarr array (what a job's
first task does); it reports the whole process's wall time, server start included. Alternating pairs, medians.

    python benchmarks/cluster_start.py [--clusters 3] [--repeats 3] [--json]
"""

import argparse
import json
import subprocess
import sys

from _common import ROOT, markdown_table, median, save_results

CHILD = """
import sys, time
sys.path.insert(0, {root!r})
from pipeline.compute import cluster

def first_task(path):
    import zarr
    return int(zarr.open_array(path, mode="r")[:].sum())

if __name__ == "__main__":
    import tempfile, zarr
    if {mode!r} == "spawned":
        cluster.forked_workers = lambda: {{}}  # as dask_client looks it up; the reference: Dask's default start method
    path = tempfile.mkdtemp() + "/a.zarr"
    zarr.create_array(path, shape=(64, 64), chunks=(32, 32), dtype="u1")[:] = 1
    start = time.perf_counter()
    for _ in range({clusters}):
        with cluster.dask_client(workers=2, gpus=0) as client:
            assert client.gather(client.map(first_task, [path] * 2, pure=False)) == [4096, 4096]
    print(time.perf_counter() - start)
"""


def measure(mode: str, clusters: int) -> float:
    done = subprocess.run([sys.executable, "-c", CHILD.format(root=str(ROOT), mode=mode, clusters=clusters)],
                          capture_output=True, text=True, timeout=600)
    if done.returncode:
        raise SystemExit(f"{mode}: {done.stderr[-2000:]}")
    return float(done.stdout.split()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clusters", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    seconds = {"spawned": [], "forked": []}
    for _ in range(args.repeats):  # alternating, so that a slower minute of the machine hits both
        for mode in seconds:
            seconds[mode].append(measure(mode, args.clusters))
    result = {"clusters": args.clusters, "repeats": args.repeats, "seconds": seconds,
              "median_s": {mode: median(times) for mode, times in seconds.items()},
              "ratio_forked_to_spawned": median(f / s for f, s in zip(seconds["forked"], seconds["spawned"]))}
    save_results("cluster_start", result)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(markdown_table(["workers", f"{args.clusters} clusters of 2 workers, s (median of {args.repeats})"],
                         [[mode, f"{result['median_s'][mode]:.2f}"] for mode in seconds]))
    print(f"\nforked / spawned: {result['ratio_forked_to_spawned']:.2f}x")


if __name__ == "__main__":
    main()
