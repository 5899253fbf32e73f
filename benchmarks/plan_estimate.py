"""How close ``cscsr reconstruct --dry-run``'s estimate comes to the job it plans.

What: the plan (``pipeline.jobs.reconstruct.reconstruct(..., dry_run=True)``) of TFP over a 1000-frame 512x512
RGGB recording (window 41, every ``--every``, default 10: 96 output frames of 2048x2048; tile 256: 4 tasks a
frame, 384 tasks), then the job itself, timed whole, two ways:

- ``local``: the job starts its own local cluster of ``--workers`` (default 2) processes, as ``cscsr
  reconstruct`` without ``--scheduler`` does (the plan measures on a local cluster alike and adds its
  start-up);
- ``cluster``: a local cluster of ``--workers`` started before both (``pipeline.compute.cluster.dask_client``), passed
  as ``client=``, as a job on a long-lived cluster runs.

The reference is the measured job; the figure is the plan's ``job_seconds`` (this job on its workers) over
it, and the plan's ``output_bytes`` over the size of the job's ``video`` chunks. Goal (issue #36): the
estimated time within 25 % of the job's (0.75 <= ratio <= 1.25; PASS/FAIL, not asserted). Medians of
``--repeats`` (default 3) per-repetition ratios; the plan is made afresh before each job.

The recording is ``reconstruct_overhead.py``'s (an integrate-and-fire simulation of a smooth drifting colour
scene, cached under /tmp/cscsr_bench). Outputs are deleted; the gain is automatic (the middle window's).

Run: ``python benchmarks/plan_estimate.py [--frames N] [--size S] [--every K] [--tile T] [--workers W]
[--repeats R]``.
"""

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

from _common import load_average, markdown_table, median, save_results
from reconstruct_overhead import CACHE, fresh, spike_store

GOAL = 0.25


def video_bytes(out: Path) -> int:
    return sum(path.stat().st_size for path in (out / "video" / "c").rglob("*") if path.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--size", type=int, default=512, help="LR height = width (default 512)")
    parser.add_argument("--every", type=int, default=10)
    parser.add_argument("--tile", type=int, default=256)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    from pipeline.compute.cluster import dask_client
    from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct

    load_start = load_average()
    CACHE.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="plan-estimate-", dir=CACHE))
    options = ReconstructOptions(every=args.every, tile=args.tile, overwrite=True)
    rows, runs = [], {"local": [], "cluster": []}
    try:
        store = spike_store(args.frames, args.size, args.size, work / "spikes.zarr")
        out = work / "out.zarr"
        with dask_client(workers=args.workers) as client:
            for repeat in range(args.repeats):
                for way in ("local", "cluster") if repeat % 2 == 0 else ("cluster", "local"):
                    where = {"client": client} if way == "cluster" else {"workers": args.workers}
                    fresh(out)
                    began = time.perf_counter()
                    plan = reconstruct(store, str(out), options, progress=False, dry_run=True, **where)
                    planning = time.perf_counter() - began
                    assert not out.exists()
                    began = time.perf_counter()
                    reconstruct(store, str(out), options, progress=False, **where)
                    job = time.perf_counter() - began
                    size = video_bytes(out)
                    run = {"repeat": repeat, "tasks": plan["tasks"], "estimated_s": plan["job_seconds"], "job_s": job,
                           "time_ratio": plan["job_seconds"] / job, "seconds_per_task": plan["seconds_per_task"],
                           "segment_start_s": plan["segment_start_seconds"], "planning_s": planning,
                           "estimated_bytes": plan["output_bytes"], "bytes": size,
                           "size_ratio": plan["output_bytes"] / size}
                    runs[way].append(run)
                    print(f"{way} #{repeat}: estimated {run['estimated_s']:.1f} s, job {job:.1f} s "
                          f"(ratio {run['time_ratio']:.2f}); size ratio {run['size_ratio']:.3f}; the plan took "
                          f"{planning:.1f} s", file=sys.stderr)
        for way, done in runs.items():
            ratio = median(r["time_ratio"] for r in done)
            rows.append([way, done[0]["tasks"], f"{median(r['estimated_s'] for r in done):.1f}",
                         f"{median(r['job_s'] for r in done):.1f}", f"{ratio:.2f}",
                         f"{median(r['size_ratio'] for r in done):.3f}", f"{median(r['planning_s'] for r in done):.1f}",
                         "PASS" if abs(ratio - 1) <= GOAL else "FAIL"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"\nTFP, {args.frames} frames of {args.size}x{args.size}, every {args.every}, tile {args.tile}, "
          f"{args.workers} workers; median of {args.repeats}. Load average at start: {load_start}, at end: "
          f"{load_average()}\n")
    print(markdown_table(["job", "tasks", "estimated s", "job s", "estimate / job", "size estimate / size",
                          "plan s", f"goal within {GOAL:.0%}"], rows))
    path = save_results("plan_estimate", {"args": vars(args), "runs": runs, "rows": rows})
    print(f"\nresults: {path}")


if __name__ == "__main__":
    main()
