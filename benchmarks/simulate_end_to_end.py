"""Whole ``simulate`` of 1,000 spike frames from a 4000x4000 video (LR 1000x1000), against a
reference version of the code in the same run, and where the time goes.

The run: ``pipeline.jobs.simulate.simulate`` on a local cluster (2 workers by default), scale 4,
RGGB, reset zero, flow interpolation, ground truth every 41 frames, in a fresh process per run.
With ``--reference DIR`` (a checkout of an earlier commit: ``git worktree add DIR COMMIT``) the
same simulation runs with that code too, alternating with this code, and the two outputs are
compared byte for byte (spikes, truth). The breakdown: each stage timed alone in this process
on the same data, times how often the run calls it, as a share of the summed stage time, so the
next bottleneck is named.

    python benchmarks/simulate_end_to_end.py --reference /tmp/ref --repeats 3
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from _common import ROOT, load_average, markdown_table, median, save_results

CHUNK_FRAMES = 32


def make_video(path: str, size: int, n_frames: int) -> None:
    """A textured HR video that pans a few pixels per frame (H.264 via imageio-ffmpeg)."""
    import cv2
    import imageio.v3 as iio
    from skimage import data

    texture = cv2.resize(data.hubble_deep_field(), (size + 64 * n_frames, size), interpolation=cv2.INTER_CUBIC)
    frames = np.stack([texture[:, 16 * i : 16 * i + size] for i in range(n_frames)])
    iio.imwrite(path, frames, fps=10, codec="libx264", quality=8, macro_block_size=16)


def run_once(code: str, video: str, dest: str, frames: int, workers: int) -> float:
    """Seconds of one ``simulate`` with the code at ``code``, in a fresh process (imports included)."""
    program = (
        "import sys, time\n"
        f"sys.path.insert(0, {code!r})\n"
        "start = time.perf_counter()\n"
        "from pipeline.jobs.simulate import SimulateOptions, simulate\n"
        f"options = SimulateOptions(scale=4, cfa='rggb', frames={frames}, reset='zero', interp='flow', chunk_frames={CHUNK_FRAMES})\n"
        f"simulate({video!r}, {dest!r}, options, workers={workers}, progress=False)\n"
        "print(time.perf_counter() - start)\n")
    done = subprocess.run([sys.executable, "-c", program], cwd=code, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"simulate with {code} failed:\n{done.stderr[-2000:]}")
    return float(done.stdout.split()[-1])


def same_bytes(a: str, b: str) -> bool:
    """Whether two simulated stores hold the same spikes and truth."""
    import zarr

    first, second = zarr.open_group(a, mode="r"), zarr.open_group(b, mode="r")
    return all(np.array_equal(first[name][:], second[name][:]) for name in ("spikes", "truth", "truth_frames"))


def timed(fn, *args, repeats: int = 3):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn(*args)
        times.append(time.perf_counter() - start)
    return median(times), result


def stage_breakdown(video: str, frames: int, dest: str) -> list[tuple[str, float, int]]:
    """(stage, seconds per call, calls in the run) for every stage of the graph, this code."""
    from cscsr import lazy
    from pipeline.jobs.simulate import SimulateOptions
    from pipeline.jobs.simulate_plan import intensities
    from pipeline.lazy.frames import made_scene
    from pipeline.jobs.simulate import _made_increments, _write_made_truth, fire_chunk
    from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter
    from stages.simulation import sensor
    from stages.simulation.interpolate import estimate_motion
    from stages.simulation.latent import upscale_motion
    from stages.reconstruction.methods import WINDOW, output_centres

    options = SimulateOptions(scale=4, cfa="rggb", frames=frames, reset="zero", interp="flow",
                              chunk_frames=CHUNK_FRAMES)
    scene = made_scene(lazy.open_frames(video, frames=frames, interp="flow", scale=4, chunk_frames=CHUNK_FRAMES).data)
    source = scene.source
    model = options.sensor_model()
    decode, frame0 = timed(source.read, 0, repeats=1)
    downsample, lr0 = timed(sensor.area_downsample, intensities(source, scene.version, 0), options.scale)
    lr = [lr0] + [scene.lr_frame(i) for i in range(1, source.n_frames)]
    motion_time, motion = timed(estimate_motion, lr0, lr[1])
    chunk = range(0, CHUNK_FRAMES)
    pairs = [[i, lr[i], lr[i + 1], motion if i == 0 else estimate_motion(lr[i], lr[i + 1])] for i in scene.pairs(chunk)]
    height, width = lr0.shape[:2]
    dark = sensor.dark_increments(model, height, width)
    inc_time, increments = timed(_made_increments, scene, pairs, chunk, options, dark)
    state = sensor.initial_state(model, height, width)
    fire_time, fired = timed(fire_chunk, increments, state, options.reset, None)
    meta = SpikeMeta(height=height, width=width, cfa=options.cfa)
    writer = SpikeStoreWriter(dest, meta, CHUNK_FRAMES, chunk_frames=CHUNK_FRAMES)
    write_time, _ = timed(writer.write, 0, fired.packed)
    hr_motion_time, hr_motion = timed(upscale_motion, motion, options.scale, repeats=1)
    truth_at = output_centres(frames, WINDOW, options.truth_every)
    first_pair = [t for t in truth_at if scene.pair(t)[0] == 0]
    writer.add_array("truth", (1, *frame0.shape), (1, *frame0.shape), np.uint8, ("k", "y", "x", "c"))
    truth_time, _ = timed(_write_made_truth, dest, 0, scene, first_pair[-1], options.cfa, hr_motion, repeats=1)
    n_chunks = -(-frames // CHUNK_FRAMES)
    pairs_used = source.n_frames - 1
    return [
        (f"decode a {source.height}x{source.width} source frame", decode, source.n_frames),
        ("area downsample to LR", downsample, source.n_frames),
        ("pair motion at LR (DIS both ways + checks)", motion_time, pairs_used),
        (f"latent LR mosaics + increments ({CHUNK_FRAMES} frames)", inc_time, n_chunks),
        (f"integrate-and-fire ({CHUNK_FRAMES} frames)", fire_time, n_chunks),
        (f"write spikes chunk ({CHUNK_FRAMES} frames)", write_time, n_chunks),
        ("pair motion at HR (flows upscaled, checks)", hr_motion_time, pairs_used),
        ("ground-truth frame (HR interpolation, write)", truth_time, len(truth_at)),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=4000, help="HR frame side (default 4000)")
    parser.add_argument("--frames", type=int, default=1000, help="spike frames (default 1000)")
    parser.add_argument("--source-frames", type=int, default=6, help="frames of the source video")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reference", help="a checkout of the code to compare with (e.g. a git worktree)")
    parser.add_argument("--reference-repeats", type=int, help="runs of the reference (default: --repeats)")
    args = parser.parse_args()

    work = tempfile.mkdtemp(prefix="cscsr-sim-bench-")
    try:
        video = os.path.join(work, "source.mp4")
        start = time.perf_counter()
        make_video(video, args.size, args.source_frames)
        print(f"made {args.source_frames}-frame {args.size}x{args.size} video in {time.perf_counter() - start:.0f} s")
        codes = {"this code": str(ROOT)} | ({"reference": os.path.abspath(args.reference)} if args.reference else {})
        walls = {name: [] for name in codes}
        runs = {"this code": args.repeats, "reference": args.reference_repeats or args.repeats}
        for repeat in range(args.repeats):
            for name, code in codes.items():
                if repeat >= runs[name]:
                    continue
                dest = os.path.join(work, f"{name.replace(' ', '-')}-{repeat}.zarr")
                walls[name].append(run_once(code, video, dest, args.frames, args.workers))
                print(f"{name}, run {repeat + 1}: {walls[name][-1]:.1f} s", flush=True)
                if repeat:  # keep the first runs' outputs for the comparison
                    shutil.rmtree(dest)
        identical = same_bytes(os.path.join(work, "this-code-0.zarr"), os.path.join(work, "reference-0.zarr")) \
            if args.reference else None

        lr = args.size // 4
        wall = median(walls["this code"])
        rows = [["wall time, s (median)", f"{wall:.1f}", "-", "-"],
                ["spike frames per second", f"{args.frames / wall:.2f}", "-", "-"]]
        if args.reference:
            before = median(walls["reference"])
            rows = [["wall time, s (median)", f"{wall:.1f}", f"reference: {before:.1f}", f"{before / wall:.1f}x faster"],
                    ["spike frames per second", f"{args.frames / wall:.2f}", f"{args.frames / before:.2f}", f"{before / wall:.1f}x"],
                    ["output bytes", "identical" if identical else "DIFFERENT", "-", "-"]]
        stages = stage_breakdown(video, args.frames, os.path.join(work, "stage.zarr"))
        total = sum(seconds * calls for _, seconds, calls in stages)
        stage_rows = [[name, f"{seconds * 1000:.0f}", calls, f"{seconds * calls:.1f}", f"{100 * seconds * calls / total:.0f} %"]
                      for name, seconds, calls in stages]
        print(f"\n## simulate: {args.frames} frames, {args.size}x{args.size} video -> LR {lr}x{lr}, "
              f"{args.workers} workers, median of {args.repeats}"
              + (f" (reference: {runs['reference']})" if args.reference else "") + "\n")
        print(markdown_table(["figure", "value", "reference", "ratio"], rows))
        print("\nStage shares (each stage timed alone in one process x its calls in the run):\n")
        print(markdown_table(["stage", "ms per call", "calls", "s in run", "share"], stage_rows))
        print(f"\nLoad average {load_average()}.")
        save_results("simulate_end_to_end", {"walls_s": walls, "frames": args.frames, "size": args.size,
                                             "workers": args.workers, "identical": identical,
                                             "stages": [dict(zip(("stage", "seconds", "calls"), s)) for s in stages]})
        if identical is False:
            raise SystemExit("the outputs differ from the reference's")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
