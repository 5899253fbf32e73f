"""``lazy.to_video`` on dask's own threads, against a reference commit, side by side in one run.

What: ``to_video(tfp(windows(open_spikes(store), every=41), tile=128))`` of a 256x256 RGGB recording of ``--frames``
spike frames (default 2,000: 48 output frames of 1024x1024, 4 tiles each), and the shipped ``lite`` network on
its region 0:64,0:64 over the first 0.05 s (24 output frames of 256x256), with no ``distributed`` client (dask's
threaded scheduler, 2 threads), from this tree and from a reference checkout (``git worktree``, default c6e16e5:
the last commit before such a call ran a store's reconstruction through ``executor.computed``, its read and its
write two tasks, rather than in rounds of its own of the job's one read-and-write task). Each run in a fresh
interpreter, the order alternating; measured: the call's wall time and the process's peak resident memory
(``VmHWM``). The stores must be byte-identical, so both are given the gain (:data:`GAIN`): the automatic exposure's
window moved after the references (the recording's middle window, not its middle output frame's).

Goals: wall time <= 1.05x the reference's; peak memory <= 1.1x.

``python benchmarks/to_video_threads.py [--reference REV] [--repeats R] [--frames N] [--stages tfp lite]``
"""

import argparse
import tempfile
from pathlib import Path

from _common import (HIGH_WATER, load_average, markdown_table, median, reference_checkout, save_results,
                     side_by_side)
from reconstruct_overhead import spike_store

REFERENCE = "c6e16e5"
GOAL_TIME, GOAL_MEMORY = 1.05, 1.1
GAIN = 2.0  # about the recording's automatic exposure
RUN = f"""
import json, os, sys, time
sys.path.insert(0, os.getcwd())
import dask
from cscsr import lazy
{HIGH_WATER}
store, stage, out = sys.argv[1:4]
spikes = lazy.open_spikes(store)
if stage == "tfp":
    hr = lazy.tfp(lazy.windows(spikes, every=41), tile=128, gain={GAIN})
else:
    hr = lazy.reconstruct(lazy.windows(spikes, every=41, stop="0.05s", region="0:64,0:64"), method="cscsr",
                          weights="lite", tile=64, gain={GAIN})
with dask.config.set(scheduler="threads", num_workers=2):
    start = time.perf_counter()
    lazy.to_video(hr, out)
    seconds = time.perf_counter() - start
print(json.dumps({{"seconds": seconds, "process": high_water()}}))
"""
STAGES = ("tfp", "lite")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default=REFERENCE)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--stages", nargs="+", choices=STAGES, default=list(STAGES))
    args = parser.parse_args()
    store = Path(tempfile.gettempdir()) / f"cscsr-to-video-threads-{args.frames}.zarr"
    if not store.exists():
        spike_store(args.frames, 256, 256, store)
    load_before = load_average()
    rows, measured = [], {}
    with reference_checkout(args.reference, "cscsr-to-video-threads-") as (work, reference):
        trees = {"this tree": Path(__file__).resolve().parents[1], "reference": reference}
        for stage in args.stages:
            runs = side_by_side(trees, args.repeats, work, stage, RUN, store, stage)
            now, before = (median([run["seconds"] for run in runs[name]]) for name in trees)
            peaks = [max(run["process"] for run in runs[name]) / 2**20 for name in trees]
            measured[stage] = {"seconds": now, "reference_seconds": before, "ratio": now / before,
                               "peak_mib": peaks[0], "reference_peak_mib": peaks[1],
                               "memory_ratio": peaks[0] / peaks[1], "runs": runs}
            rows.append([stage, f"{now:.2f}", f"{before:.2f}", f"{now / before:.2f}",
                         f"{peaks[0]:.0f} / {peaks[1]:.0f}"])
    print(markdown_table(["stage", "s (median)", args.reference, "ratio", "peak MiB (now / before)"], rows))
    met = all(m["ratio"] <= GOAL_TIME and m["memory_ratio"] <= GOAL_MEMORY for m in measured.values())
    print(f"goals (time <= {GOAL_TIME}x, memory <= {GOAL_MEMORY}x): {'met' if met else 'NOT met'}")
    save_results("to_video_threads", {"reference": args.reference, "repeats": args.repeats, "frames": args.frames,
                                      "load_before": load_before, "load_after": load_average(),
                                      "stages": measured, "goals_met": met})


if __name__ == "__main__":
    main()
