"""One execution path (#56): the reconstruct job, now a front door to the lazy graph's tasks, against the commit
before that work, side by side in one run.

What: two jobs users run on two workers, through the command line (``cscsr reconstruct --workers 2``: a fresh
local cluster, start-up and shut-down included), each from this tree and from a reference commit checked out
beside it (``git worktree``, default the last commit before #56's work), with the same Python environment:

(a) TFP over a 2,000-frame 256x256 RGGB recording (48 output frames of 1024x1024);
(b) the shipped ``lite`` network on a 64x64 LR region of it (48 output frames of 256x256).

The runs alternate (reference first in odd repetitions, this tree first in even ones); the ratio is the median
of the ratios within each repetition. Each run's video must equal the reference's, so both are given the gain
(:data:`GAIN`: the automatic exposure's window moved after the reference, to the recording's middle window), byte for
byte but for OpenCV's VNG tail (3bed0d8, after the reference: a pixel in 10^5 of TFP a level or two apart, within
:data:`VNG_TAIL_LEVELS` and :data:`VNG_TAIL_SHARE`; reported).
Also measured, once per variant on a ``LocalCluster`` of 2 worker processes passed as ``client=``: the bytes
moved between workers (the sum of each worker's ``transfer_outgoing_bytes_total``, Dask's transfer metric).
And the lines of the code that executes jobs and graphs, here and in the reference.

Goals: wall time <= 1.05x the reference's for each job; bytes moved <= the reference's; fewer lines.

The recording is an integrate-and-fire simulation of a smooth, drifting scene (``reconstruct_overhead``'s),
cached as a raw ``.dat`` in /tmp/cscsr_bench and ingested once. Run:
``python benchmarks/one_path.py [--reference REV] [--repeats R] [--frames N]``.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr
from _common import load_average, markdown_table, median, save_results, write_integrate_and_fire
from reconstruct_overhead import rate_map

ROOT = Path(__file__).resolve().parent.parent
CACHE = Path("/tmp/cscsr_bench")
REFERENCE = "9d5c293"  # the last commit before #56's one path
GOAL_TIME, SIDE = 1.05, 256
GAIN = 2.0  # about the recording's automatic exposure
VNG_TAIL_LEVELS, VNG_TAIL_SHARE = 2, 1e-4  # the most a pixel, and the share of pixels, 3bed0d8's fix moves
JOBS = {"tfp": ["--method", "tfp", "--gain", str(GAIN)],
        "lite-64": ["--method", "cscsr", "--weights", "lite", "--region", "96:160,96:160", "--gain", str(GAIN)]}
EXECUTING = ["pipeline/jobs/reconstruct.py", "pipeline/jobs/reconstruct_tasks.py", "pipeline/jobs/dry_run.py",
             "pipeline/compute/executor.py", "pipeline/lazy/video.py", "pipeline/lazy/written.py",
             "pipeline/lazy/windows.py"]  # the code that executes jobs and graphs
TRANSFERS = """
import sys
from distributed import Client, LocalCluster
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
store, out, method, weights, region, gain = sys.argv[1:7]
with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0") as cluster, Client(cluster) as client:
    options = ReconstructOptions(method=method, weights=weights or None, region=region or None, gain=float(gain))
    reconstruct(store, out, options, client=client, progress=False)
    print(sum(client.run(lambda dask_worker: dask_worker.transfer_outgoing_bytes_total).values()))
"""


def tree(reference: str) -> Path:
    """The reference commit checked out beside this tree (made once, kept in the cache)."""
    path = CACHE / f"one-path-{reference}"
    if not path.exists():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), reference], check=True,
                       capture_output=True)
    return path


def recording(frames: int) -> str:
    store = CACHE / f"one-path-{frames}x{SIDE}.zarr"
    if not store.exists():
        dat = CACHE / f"one-path-{frames}x{SIDE}.dat"
        if not dat.exists():
            CACHE.mkdir(parents=True, exist_ok=True)
            write_integrate_and_fire(dat, frames, lambda first: rate_map(SIDE, SIDE, first / 1000))
        subprocess.run([sys.executable, "-m", "pipeline.cli", "-q", "ingest", str(dat), str(store), "--height",
                        str(SIDE), "--width", str(SIDE), "--cfa", "rggb"], check=True, cwd=ROOT)
    return str(store)


def environment(code: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(code)}


def job(code: Path, store: str, out: str, args: list[str]) -> float:
    """Seconds of one CLI job run from ``code`` (in a folder of neither tree: the path decides what imports)."""
    began = time.perf_counter()
    subprocess.run([sys.executable, "-m", "pipeline.cli", "-q", "reconstruct", store, out, "--workers", "2", *args],
                   check=True, env=environment(code), cwd=tempfile.gettempdir(), capture_output=True)
    return time.perf_counter() - began


def moved(code: Path, store: str, out: str, args: list[str]) -> int:
    options = dict(zip(args[::2], args[1::2]))
    result = subprocess.run([sys.executable, "-c", TRANSFERS, store, out, options["--method"],
                             options.get("--weights", ""), options.get("--region", ""), options["--gain"]], check=True,
                            env=environment(code), cwd=tempfile.gettempdir(), capture_output=True, text=True)
    return int(result.stdout.split()[-1])


def lines(code: Path) -> int:
    return sum(len((code / path).read_text().splitlines()) for path in EXECUTING if (code / path).exists())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", default=REFERENCE)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=2000)
    args = parser.parse_args()
    print(f"load average: {load_average()}")
    reference, here = tree(args.reference), ROOT
    store = recording(args.frames)
    work = Path(tempfile.mkdtemp(prefix="cscsr-one-path-"))
    results = {}
    try:
        for name, options in JOBS.items():
            ratios, times = [], {"reference": [], "here": []}
            for repeat in range(args.repeats):
                order = [("reference", reference), ("here", here)][:: 1 if repeat % 2 == 0 else -1]
                seconds = {}
                for label, code in order:
                    out = work / f"{name}-{label}.zarr"
                    shutil.rmtree(out, ignore_errors=True)
                    seconds[label] = job(code, store, str(out), options)
                    times[label].append(seconds[label])
                ratios.append(seconds["here"] / seconds["reference"])
                apart = np.abs(zarr.open_group(str(work / f"{name}-here.zarr"), mode="r")["video"][:].astype(np.int16)
                               - zarr.open_group(str(work / f"{name}-reference.zarr"), mode="r")["video"][:])
                share = float((apart > 0).mean())
                if apart.max() > VNG_TAIL_LEVELS or share > VNG_TAIL_SHARE:
                    raise SystemExit(f"{name}: the video differs from the reference's (at most {apart.max()} levels, "
                                     f"{share:.2e} of the values)")
            transfers = {}
            for label, code in (("reference", reference), ("here", here)):
                out = work / f"{name}-{label}-client.zarr"
                shutil.rmtree(out, ignore_errors=True)
                transfers[label] = moved(code, store, str(out), options)
            results[name] = {"seconds_reference": median(times["reference"]), "seconds_here": median(times["here"]),
                             "ratio": median(ratios), "bytes_moved_reference": transfers["reference"],
                             "bytes_moved_here": transfers["here"], "values_apart": share,
                             "most_levels_apart": int(apart.max())}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    rows = [[name, f"{r['seconds_reference']:.2f}", f"{r['seconds_here']:.2f}", f"{r['ratio']:.3f}",
             "PASS" if r["ratio"] <= GOAL_TIME else "FAIL", r["bytes_moved_reference"], r["bytes_moved_here"],
             "PASS" if r["bytes_moved_here"] <= r["bytes_moved_reference"] else "FAIL",
             f"{r['values_apart']:.1e} (at most {r['most_levels_apart']})"] for name, r in results.items()]
    print(markdown_table(["job (2 workers)", "reference s", "here s", "here/reference", f"<= {GOAL_TIME}",
                          "bytes moved ref", "bytes moved here", "<= ref", "values apart (levels)"], rows))
    counted = {"reference": lines(reference), "here": lines(here)}
    print(f"\nlines that execute jobs and graphs ({', '.join(EXECUTING)}): reference {counted['reference']}, "
          f"here {counted['here']}: {'PASS' if counted['here'] < counted['reference'] else 'FAIL'}")
    save_results("one_path", {"reference": args.reference, "frames": args.frames, "repeats": args.repeats,
                              "jobs": results, "lines": counted, "load_average": load_average()})
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
