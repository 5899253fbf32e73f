"""Overhead of the distributed reconstruction against a plain loop doing the same work.

What: TFP reconstruction of a 1000-frame 512x512 RGGB recording (scale 4: 2048x2048 HR
output frames), window 41, an output frame every ``--every`` spike frames (default 10: 96
frames, centres 20, 30, ..., 970; ``--every 41`` gives 24), three ways and a context run,
all with the same fixed gain:

(a) the reference, a plain loop in this process: for each centre c, ``open_spike_store(...)
    .read(c - 20, c + 21)``, ``stages.reconstruction.tfp.tfp_image(window, width=512, cfa="rggb", gain=g,
    scale=4)``, and a write of that frame into the ``video`` array of an output store made by
    the pipeline's own ``create_video_store`` (same shape, one 2048x2048x3 chunk per frame,
    same codec), frame by frame, every chunk written without an emptiness scan (the array is
    declared ``write_empty_chunks``);
(b) ``pipeline.jobs.reconstruct.reconstruct(..., workers=1)`` with ``tile=512`` (one tile, so one
    task, per frame: the same work as the loop), timed whole: local cluster start-up and
    shut-down included;
(c) the same on a one-worker cluster started (and warmed: the worker imports the pipeline
    and OpenCV) before the clock starts, passed as ``client=``;
(d) context, no goal: the plain loop (a) submitted as one task to (c)'s worker, right after
    (c): the cost of the worker process's environment alone, without the pipeline's tasks.

Goal: (c) <= 1.10 x (a). (b) is reported too. The outputs of (b), (c) and (d) must equal (a)'s
array, frame by frame (checked every repetition).

The recording is an integrate-and-fire simulation of a smooth, slowly drifting colour scene
seen through an RGGB mosaic (rates 0.05-0.3 spikes/pixel/frame), generated once with numpy
in bounded memory, cached as a raw ``.dat`` under /tmp/cscsr_bench and ingested into a
temporary spike store. The gain is the automatic exposure of the middle window, computed
once and passed to every variant. Each repetition runs (a), (b) and (c) in a rotating order
((d) always right after (c)), each after its output is removed and ``sync``; the ratios are
medians of the ratios within each repetition (robust to load that drifts between
repetitions). Outputs are deleted.

This file also holds the recording helpers that ``reconstruct_scaling.py`` and
``reconstruct_memory.py`` import.

Run: ``python benchmarks/reconstruct_overhead.py [--frames N] [--every K] [--repeats R]``.
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import load_average, markdown_table, median, save_results, write_integrate_and_fire

CACHE = Path("/tmp/cscsr_bench")
BLOCK = 200  # frames generated per block; the rate map drifts block to block
WINDOW = 41
SCALE = 4
GOAL = 1.10


# --- the recording (shared with reconstruct_scaling.py and reconstruct_memory.py) ---

def rate_map(height: int, width: int, t: float) -> np.ndarray:
    """Firing rate per pixel in [0.05, 0.3]: a smooth colour scene through RGGB, drifting 0.01 px/frame."""
    from stages.reconstruction.cfa import colour_index

    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    x = x - 0.01 * t
    channels = np.stack([  # each in [0, 1]
        0.5 + 0.3 * np.sin(x / 37) * np.cos(y / 53) + 0.2 * np.sin((x + 0.6 * y) / 23),
        0.5 + 0.3 * np.sin(y / 41 + 1) * np.cos(x / 29) + 0.2 * np.sin((0.7 * x - y) / 19),
        0.5 + 0.3 * np.cos(x / 31 + 2) * np.sin(y / 47) + 0.2 * np.cos((x + y) / 27),
    ])
    site = colour_index("rggb", height, width)
    s = np.take_along_axis(channels, site[None].astype(np.intp), axis=0)[0]
    return (0.05 + 0.25 * s).astype(np.float32)


def cached_capture(frames: int, height: int, width: int) -> Path:
    """The raw ``.dat`` recording, generated once and kept under /tmp/cscsr_bench."""
    path = CACHE / f"if_rggb_{height}x{width}_{frames}.dat"
    if path.exists() and path.stat().st_size == frames * height * width // 8:
        print(f"using cached capture {path}", file=sys.stderr)
        return path
    CACHE.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    write_integrate_and_fire(path, frames, lambda start: rate_map(height, width, start), block=BLOCK)
    print(f"generated {path} ({path.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return path


def spike_store(frames: int, height: int, width: int, dest: Path) -> str:
    """Ingest the cached recording (cfa rggb) into a spike store at ``dest``; its URL."""
    from pipeline.jobs.ingest import IngestOptions, ingest

    ingest(str(cached_capture(frames, height, width)), str(dest),
           IngestOptions(height=height, width=width, cfa="rggb", overwrite=True), progress=False)
    return str(dest)


def middle_gain(store_url: str, window: int, every: int) -> float:
    """The automatic exposure of the middle output window (what ``reconstruct`` would pick)."""
    from stages.reconstruction.methods import output_centres
    from pipeline.stores.spike_store import open_spike_store
    from stages.reconstruction.colour import auto_gain
    from stages.reconstruction.tfp import tfp_rate

    store = open_spike_store(store_url)
    centres = output_centres(store.n_frames, window, every)
    centre, half = centres[len(centres) // 2], window // 2
    return auto_gain(tfp_rate(store.read(centre - half, centre + half + 1), store.meta.width))


def fresh(path: Path) -> None:
    """Remove an output and flush dirty pages, so no run pays for the previous one's writeback."""
    shutil.rmtree(path, ignore_errors=True)
    subprocess.run(["sync"], check=True)


def warm_worker() -> int:
    """Run on a worker before timing: import what a reconstruction task imports."""
    import os

    import cv2  # noqa: F401  (stages.reconstruction.colour imports it lazily, in the first task)

    import pipeline.jobs.reconstruct  # noqa: F401

    return os.getpid()


def outputs_equal(url_a: str, url_b: str) -> bool:
    """The ``video`` arrays (or bare arrays) at two URLs hold identical frames (compared one at a time)."""
    import zarr

    def video(url):
        node = zarr.open(url, mode="r")
        return node["video"] if isinstance(node, zarr.Group) else node

    a, b = video(url_a), video(url_b)
    return a.shape == b.shape and a.dtype == b.dtype and all(np.array_equal(a[i], b[i]) for i in range(a.shape[0]))


# --- this benchmark ---

def plain_loop(store_url: str, out: str, every: int, gain: float) -> int:
    """(a): read, tfp_image, write each frame into a Zarr array like the pipeline's output."""
    from stages.reconstruction.methods import output_centres
    from pipeline.stores.spike_store import open_spike_store
    from pipeline.stores.video_store import VIDEO, create_video_store
    from stages.reconstruction.tfp import tfp_image

    store = open_spike_store(store_url)
    meta = store.meta
    centres = output_centres(store.n_frames, WINDOW, every)
    hr = (meta.height * SCALE, meta.width * SCALE)
    # The pipeline's own layout (shape, one chunk per frame here, codec), so both write the same bytes;
    # every chunk is written without an emptiness scan, as the array is declared (``write_empty_chunks``).
    group = create_video_store(out, centres=centres, hr_size=hr, tile_hr=hr, tiles=(1, 1), attrs={})
    video = group[VIDEO].with_config({"write_empty_chunks": True})
    half = WINDOW // 2
    for i, centre in enumerate(centres):
        image, _ = tfp_image(store.read(centre - half, centre + half + 1), width=meta.width, cfa=meta.cfa,
                             gain=gain, scale=SCALE)
        video[i] = image
    return len(centres)


def options(every: int, gain: float, tile: int, method: str = "tfp"):
    from pipeline.jobs.reconstruct import ReconstructOptions

    return ReconstructOptions(method=method, every=every, window=WINDOW, gain=gain, scale=SCALE, tile=tile, overwrite=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000, help="spike frames of the recording (default 1000)")
    parser.add_argument("--size", type=int, default=512, help="LR height = width (default 512)")
    parser.add_argument("--every", type=int, default=10, help="spike frames between output frames (default 10)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions of each variant (default 3)")
    args = parser.parse_args()

    from pipeline.compute.cluster import dask_client
    from pipeline.jobs.reconstruct import reconstruct
    from stages.reconstruction.tfp import tfp_image

    load_start = load_average()
    CACHE.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="reconstruct-overhead-", dir=CACHE))
    runs = []
    try:
        store = spike_store(args.frames, args.size, args.size, work / "spikes.zarr")
        gain = middle_gain(store, WINDOW, args.every)
        tile = args.size  # one tile per frame: one task does exactly what one loop iteration does
        # Warm this process as the worker is warmed: OpenCV loaded, its thread pool started.
        tfp_image(np.zeros((WINDOW, args.size, args.size // 8), np.uint8), width=args.size, cfa="rggb", gain=gain,
                  scale=SCALE)
        out = {name: work / f"{name}.zarr" for name in "abcd"}

        def run_a():
            start = time.perf_counter()
            frames = plain_loop(store, str(out["a"]), args.every, gain)
            return {"seconds": time.perf_counter() - start, "frames": frames}

        def run_b():
            start = time.perf_counter()
            counts = reconstruct(store, str(out["b"]), options(args.every, gain, tile), workers=1, progress=False)
            return {"seconds": time.perf_counter() - start, "frames": counts["frames"], "tasks": counts["tasks_run"]}

        def run_c():
            start = time.perf_counter()
            with dask_client(workers=1) as client:
                client.run(warm_worker)
                startup = time.perf_counter() - start
                start = time.perf_counter()
                counts = reconstruct(store, str(out["c"]), options(args.every, gain, tile), client=client, progress=False)
                seconds = time.perf_counter() - start
                # (d), context: the plain loop as one task on the same worker (the worker's environment alone)
                fresh(out["d"])
                start = time.perf_counter()
                client.submit(plain_loop, store, str(out["d"]), args.every, gain, pure=False).result()
                loop_in_worker = time.perf_counter() - start
            return {"seconds": seconds, "startup_seconds": startup, "frames": counts["frames"], "tasks": counts["tasks_run"],
                    "plain_loop_in_worker_seconds": loop_in_worker}

        variants = {"a": run_a, "b": run_b, "c": run_c}
        for rep in range(args.repeats):
            order = "abc"[rep % 3:] + "abc"[: rep % 3]
            result = {"rep": rep, "order": order, "load_average": load_average()}
            for name in order:
                fresh(out[name])
                result[name] = variants[name]()
                print(f"rep {rep} ({args.every=}) {name}: {result[name]['seconds']:.2f} s", file=sys.stderr)
            result["b_equals_a"] = outputs_equal(str(out["b"]), str(out["a"]))
            result["c_equals_a"] = outputs_equal(str(out["c"]), str(out["a"]))
            result["d_equals_a"] = outputs_equal(str(out["d"]), str(out["a"]))
            runs.append(result)
        frames = runs[0]["a"]["frames"]
    finally:
        shutil.rmtree(work, ignore_errors=True)

    med = {name: median(r[name]["seconds"] for r in runs) for name in "abc"}
    ratio_b = median(r["b"]["seconds"] / r["a"]["seconds"] for r in runs)
    ratio_c = median(r["c"]["seconds"] / r["a"]["seconds"] for r in runs)
    startup = median(r["c"]["startup_seconds"] for r in runs)
    identical = all(r["b_equals_a"] and r["c_equals_a"] and r["d_equals_a"] for r in runs)
    loop_in_worker = median(r["c"]["plain_loop_in_worker_seconds"] for r in runs)
    ratio_d = median(r["c"]["plain_loop_in_worker_seconds"] / r["a"]["seconds"] for r in runs)
    summary = [
        ["(a) plain loop, one process, Zarr chunk write per frame", f"{med['a']:.2f}", f"{1000 * med['a'] / frames:.0f}",
         "1.00", "reference", "-"],
        ["(c) reconstruct(client=...), 1 worker, start-up excluded", f"{med['c']:.2f}", f"{1000 * med['c'] / frames:.0f}",
         f"{ratio_c:.2f}", f"<= {GOAL:.2f}", "PASS" if ratio_c <= GOAL else "FAIL"],
        ["(b) reconstruct(workers=1), cluster start-up + shut-down included", f"{med['b']:.2f}",
         f"{1000 * med['b'] / frames:.0f}", f"{ratio_b:.2f}", "(reported)", "-"],
        ["(d) the plain loop (a) as one task on (c)'s worker", f"{loop_in_worker:.2f}",
         f"{1000 * loop_in_worker / frames:.0f}", f"{ratio_d:.2f}", "(context: the worker process alone)", "-"],
        ["cluster start-up + worker warm-up alone (c's, untimed there)", f"{startup:.2f}", "-", "-", "(context)", "-"],
        ["outputs of (b), (c) and (d) identical to (a)", "yes" if identical else "NO", "-", "-", "identical",
         "PASS" if identical else "FAIL"],
    ]
    per_run = [[r["rep"], r["order"], f"{r['a']['seconds']:.2f}", f"{r['b']['seconds']:.2f}", f"{r['c']['seconds']:.2f}",
                f"{r['c']['plain_loop_in_worker_seconds']:.2f}", f"{r['c']['startup_seconds']:.2f}", f"{r['c']['seconds'] / r['a']['seconds']:.2f}",
                f"{r['b']['seconds'] / r['a']['seconds']:.2f}", r["load_average"].split(" (")[0]] for r in runs]
    print(f"## Reconstruction overhead: TFP of {args.frames} frames of {args.size}x{args.size} RGGB -> {frames} frames of "
          f"{args.size * SCALE}x{args.size * SCALE} (window {WINDOW}, every {args.every}, tile {tile}: one task per frame, "
          f"gain {gain:.3f} fixed)\n")
    print(markdown_table(["variant", "seconds (median)", "ms/frame", "ratio to (a)", "goal", "result"], summary))
    print()
    print(markdown_table(["rep", "order", "(a) s", "(b) s", "(c) s", "(d) s", "(c) start-up s", "(c)/(a)", "(b)/(a)",
                          "load avg 1/5/15 at rep start"], per_run))
    print(f"\nMedians of {args.repeats} repetitions; ratios are medians of per-repetition ratios. Load average at start "
          f"{load_start}, at end {load_average()}: other work on the machine makes timings noisy.")
    path = save_results("reconstruct_overhead", {
        "frames": args.frames, "size": args.size, "scale": SCALE, "window": WINDOW, "every": args.every, "tile": tile,
        "output_frames": frames, "gain": gain, "runs": runs, "median_seconds": med, "ratio_c_over_a": ratio_c,
        "ratio_b_over_a": ratio_b, "ratio_d_over_a": ratio_d, "startup_seconds": startup, "outputs_identical": identical,
        "reference": "plain loop writing each frame into the video array of create_video_store (write_empty_chunks)",
        "load_average_at_start": load_start, "goal_ratio": GOAL, "goal_met": ratio_c <= GOAL,
    })
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
