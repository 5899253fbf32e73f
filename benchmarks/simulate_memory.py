"""The ``simulate`` job as a front door to the lazy stages (#56): wall time and peak memory against a reference
commit, side by side in one run, on a short and a 10x longer recording.

What: ``cscsr simulate`` of a picture under random camera motion (``--noise realistic``, chunks of 20 frames) and of
a 6-frame video interpolated by flow over as many spike frames, each from this tree and from a reference checkout
(``git worktree``, default the commit before the simulate job became a front door), in a fresh interpreter per run
on a fresh local cluster of 2 worker processes. Measured: the wall time of the job, and the high-water resident
memory (``VmHWM``) of each worker and of the process that runs the job (client and scheduler). Every run's spikes
and truth must equal the reference's, byte for byte.

Goals: wall time <= 1.05x the reference's; the largest worker peak of the long run <= 1.25x the short run's (memory
bounded by the chunks in flight, not by the recording's length).

``python benchmarks/simulate_memory.py [--reference REV] [--repeats R] [--frames N]``
"""

import argparse
from pathlib import Path

from _common import HIGH_WATER, load_average, markdown_table, median, reference_checkout, save_results, side_by_side

ROOT = Path(__file__).resolve().parent.parent
REFERENCE = "9b4a252"  # the last commit before the simulate job became a front door to the lazy stages
GOAL_TIME, GOAL_MEMORY = 1.05, 1.25
RUN = f"""
import json, os, sys, time
sys.path.insert(0, os.getcwd())
from distributed import Client, LocalCluster
from pipeline.jobs.simulate import SimulateOptions, simulate
{HIGH_WATER}
src, frames, motion, dest = sys.argv[1], int(sys.argv[2]), sys.argv[3] or None, sys.argv[4]
options = SimulateOptions(scale=4, frames=frames, motion=motion, noise="realistic", chunk_frames=20, truth_every=200)
with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0") as cluster, Client(cluster) as client:
    client.run(lambda: None)
    start = time.perf_counter()
    simulate(src, dest, options, scheduler=cluster.scheduler_address, progress=False)
    seconds = time.perf_counter() - start
    workers = sorted(client.run(high_water).values())
print(json.dumps({{"seconds": seconds, "workers": workers, "client": high_water()}}))
"""


def sources(work: Path) -> dict[str, tuple[str, str]]:
    """name -> (source, --motion): a 512x512 picture moved by the camera, a 6-frame 512x512 video."""
    import cv2
    import imageio.v3 as iio
    import numpy as np
    from skimage import data

    picture = cv2.resize(data.astronaut(), (512, 512), interpolation=cv2.INTER_AREA)
    iio.imwrite(work / "picture.png", picture)
    folder = work / "video"
    folder.mkdir()
    for i in range(6):
        iio.imwrite(folder / f"{i:02d}.png", np.roll(picture, (3 * i, 8 * i), axis=(0, 1)))
    return {"picture, random motion": (str(work / "picture.png"), "random"), "6-frame video, flow": (str(folder), "")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default=REFERENCE)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=400, help="the short run's spike frames (the long run: 10x)")
    args = parser.parse_args()
    with reference_checkout(args.reference, "cscsr-simulate-memory-") as (work, reference):
        trees = {"this tree": ROOT, "reference": reference}
        results = {}
        scenes = sources(work)
        for scene, (source, motion) in scenes.items():
            for frames in (args.frames, 10 * args.frames):
                runs = side_by_side(trees, args.repeats, work, f"{scene}, {frames} frames", RUN, source, frames, motion)
                results |= {(scene, frames, name): value for name, value in runs.items()}
        rows, figures = [], {}
        for scene in scenes:
            for frames in (args.frames, 10 * args.frames):
                mine, ref = results[(scene, frames, "this tree")], results[(scene, frames, "reference")]
                ratio = median([a["seconds"] / b["seconds"] for a, b in zip(mine, ref)])
                peak = {name: median([max(r["workers"]) for r in runs]) / 2**20 for name, runs in
                        (("this tree", mine), ("reference", ref))}
                client = {name: median([r["client"] for r in runs]) / 2**20 for name, runs in
                          (("this tree", mine), ("reference", ref))}
                figures[f"{scene}, {frames}"] = {"time_ratio": ratio, "worker_peak_mib": peak,
                                                  "client_peak_mib": client, "seconds": median([r["seconds"] for r in mine]),
                                                  "reference_seconds": median([r["seconds"] for r in ref])}
                rows.append([scene, frames, f"{median([r['seconds'] for r in mine]):.1f}",
                             f"{median([r['seconds'] for r in ref]):.1f}", f"{ratio:.3f}",
                             f"{peak['this tree']:.0f} / {peak['reference']:.0f}",
                             f"{client['this tree']:.0f} / {client['reference']:.0f}"])
        print(f"\n## simulate, 2 workers, median of {args.repeats} (reference {args.reference}); bytes identical\n")
        print(markdown_table(["scene", "spike frames", "s", "reference s", "time ratio",
                              "largest worker peak MiB (this / ref)", "client peak MiB (this / ref)"], rows))
        for scene in scenes:
            short, long = figures[f"{scene}, {args.frames}"], figures[f"{scene}, {10 * args.frames}"]
            growth = long["worker_peak_mib"]["this tree"] / short["worker_peak_mib"]["this tree"]
            figures[scene] = {"worker_peak_growth_10x": growth}
            print(f"{scene}: worker peak x{growth:.2f} for 10x the frames (goal <= {GOAL_MEMORY})")
        print(f"\nLoad average {load_average()}.")
        save_results("simulate_memory", {"reference": args.reference, "repeats": args.repeats, "figures": figures,
                                         "runs": {" / ".join(map(str, key)): value for key, value in results.items()}})


if __name__ == "__main__":
    main()
