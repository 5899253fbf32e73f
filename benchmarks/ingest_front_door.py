"""The ``ingest`` job as ``to_spikes(open_capture(...))`` (#56): wall time and peak memory against a reference commit,
side by side in one run.

What: ``ingest()`` of a 1000x1000 ``.dat`` of integrate-and-fire spikes (``benchmarks/ingest_throughput.py``'s
scene, cached under /tmp), from this tree and from a reference checkout (``git worktree``, default the commit before
the ingest job wrote its store through ``pipeline.stores.spike_writes``), each run in a fresh interpreter, in two
ways: in one process (one stream read ahead of the writes: the job's reference path) and on a given client of a
local cluster of 2 worker processes (the executor's window). Measured: the wall time of the ingest, the high-water
resident memory (``VmHWM``) of the process that runs it and, on the cluster, of each worker. Every store's spikes
and committed record must equal the reference's, byte for byte.

Goals: wall time <= 1.05x the reference's; peak memory <= 1.1x.

``python benchmarks/ingest_front_door.py [--reference REV] [--repeats R] [--frames N]``
"""

import argparse
import tempfile
from pathlib import Path

from _common import (HIGH_WATER, ROOT, load_average, markdown_table, median, reference_checkout, save_results,
                     side_by_side, write_integrate_and_fire)

REFERENCE = "eaa410d"  # the last commit before the ingest job wrote its store as lazy.to_spikes does
GOAL_TIME, GOAL_MEMORY = 1.05, 1.1
RUN = f"""
import json, os, sys, time
sys.path.insert(0, os.getcwd())
from pipeline.jobs.ingest import IngestOptions, ingest
{HIGH_WATER}
src, way, dest = sys.argv[1:4]
options = IngestOptions(1000, 1000, cfa="rggb")
if way == "one process":
    start = time.perf_counter()
    ingest(src, dest, options, progress=False)
    seconds, workers = time.perf_counter() - start, []
else:
    from distributed import Client, LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0") as cluster, Client(cluster) as client:
        client.run(lambda: None)
        start = time.perf_counter()
        ingest(src, dest, options, progress=False, client=client)
        seconds = time.perf_counter() - start
        workers = sorted(client.run(high_water).values())
print(json.dumps({{"seconds": seconds, "workers": workers, "process": high_water()}}))
"""
WAYS = ("one process", "2 workers")


def capture(frames: int) -> Path:
    """The .dat of ``frames`` 1000x1000 frames, made once (ingest_throughput.py's smooth drifting scene)."""
    import numpy as np

    path = Path(tempfile.gettempdir()) / f"cscsr-ingest-front-door-{frames}.dat"
    if not path.exists() or path.stat().st_size != frames * 125_000:
        y, x = np.mgrid[0:1000, 0:1000].astype(np.float32) / 1000

        def rate_at(first: int):
            drift = first / 2000
            return (0.05 + 0.25 * (0.5 + 0.5 * np.sin(6 * (x + drift)) * np.cos(4 * y))).astype(np.float32)

        write_integrate_and_fire(path, frames, rate_at)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default=REFERENCE)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=4000, help="frames of the capture (125,000 bytes each)")
    args = parser.parse_args()
    src = capture(args.frames)
    with reference_checkout(args.reference, "cscsr-ingest-front-door-") as (work, reference):
        trees = {"this tree": ROOT, "reference": reference}
        results = {}
        for way in WAYS:
            for name, runs in side_by_side(trees, args.repeats, work, way, RUN, src, way).items():
                results[(way, name)] = runs
        rows, figures = [], {}
        for way in WAYS:
            mine, ref = results[(way, "this tree")], results[(way, "reference")]
            ratio = median([a["seconds"] / b["seconds"] for a, b in zip(mine, ref)])
            peak = {name: median([max([r["process"], *r["workers"]]) for r in runs]) / 2**20
                    for name, runs in (("this tree", mine), ("reference", ref))}
            figures[way] = {"time_ratio": ratio, "seconds": median([r["seconds"] for r in mine]),
                            "reference_seconds": median([r["seconds"] for r in ref]), "peak_mib": peak,
                            "memory_ratio": peak["this tree"] / peak["reference"]}
            rows.append([way, f"{figures[way]['seconds']:.2f}", f"{figures[way]['reference_seconds']:.2f}",
                         f"{ratio:.3f}", f"{peak['this tree']:.0f} / {peak['reference']:.0f}"])
        print(f"\n## ingest of {args.frames} frames of 1000x1000 ({args.frames * 125_000 / 1e6:.0f} MB), median of "
              f"{args.repeats} (reference {args.reference}); bytes identical\n")
        print(markdown_table(["where", "s", "reference s", "time ratio (goal <= 1.05)",
                              "largest process peak MiB (this / ref)"], rows))
        print(f"\nLoad average {load_average()}.")
        save_results("ingest_front_door", {"reference": args.reference, "repeats": args.repeats,
                                           "frames": args.frames, "figures": figures,
                                           "runs": {" / ".join(key): value for key, value in results.items()}})


if __name__ == "__main__":
    main()
