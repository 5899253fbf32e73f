"""Whole ``simulate`` of 1,000 spike frames from a 4000x4000 video (LR 1000x1000), and where
the time goes.

The run: ``pipeline.simulate.simulate`` on a local 2-worker cluster, scale 4, RGGB, reset
zero, flow interpolation, ground truth every 41 frames. The breakdown: each stage timed
alone in this process on the same data, times how often the run calls it, as a share of the
summed stage time; so the next bottleneck is named. Reference for the wall time: reading
the source video once (decode only).
"""

import argparse
import os
import shutil
import tempfile
import time

import numpy as np

from _common import load_average, markdown_table, median, save_results


def make_video(path: str, size: int, n_frames: int) -> None:
    """A textured HR video that pans a few pixels per frame (H.264 via imageio-ffmpeg)."""
    import cv2
    import imageio.v3 as iio
    from skimage import data

    texture = cv2.resize(data.hubble_deep_field(), (size + 64 * n_frames, size), interpolation=cv2.INTER_CUBIC)
    frames = np.stack([texture[:, 16 * i : 16 * i + size] for i in range(n_frames)])
    iio.imwrite(path, frames, fps=10, codec="libx264", quality=8, macro_block_size=16)


def timed(fn, *args, repeats: int = 3):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn(*args)
        times.append(time.perf_counter() - start)
    return median(times), result


def stage_breakdown(video: str, options, n_chunks: int, n_truth: int, dest: str) -> list[tuple[str, float, int]]:
    """(stage, seconds per call, calls in the run) for every stage of the graph."""
    from pipeline.frame_sources import open_frame_source
    from pipeline.simulate import _lr_frame, _hr_frame, _increments, _fire, Scene, _write_truth
    from stages.methods import WINDOW, output_centres
    from pipeline.spike_store import SpikeMeta, SpikeStoreWriter
    from stages import sensor
    from stages.interpolate import estimate_flows

    source = open_frame_source(video)
    model = options.sensor_model()
    read_hr, frame0 = timed(_hr_frame, source, 0, repeats=1)
    lr_time, lr0 = timed(_lr_frame, source, 0, options.scale, repeats=1)
    lr1 = _lr_frame(source, 1, options.scale)
    flow_time, flows = timed(estimate_flows, lr0, lr1)
    chunk = options.chunk_frames
    frames = range(0, chunk)
    scene = Scene(source, None)
    pairs = {0: (lr0, lr1, flows)}
    height, width = lr0.shape[:2]
    dark = sensor.dark_increments(model, height, width)
    inc_time, increments = timed(_increments, scene, pairs, frames, options, dark)
    state = sensor.initial_state(model, height, width)
    fire_time, fired = timed(_fire, increments, state, options.reset, None)
    meta = SpikeMeta(height=height, width=width, cfa=options.cfa)
    writer = SpikeStoreWriter(dest, meta, chunk, chunk_frames=chunk)
    write_time, _ = timed(writer.write, 0, fired.packed)
    writer.add_array("truth", (1, *frame0.shape), (1, *frame0.shape), np.uint8, ("k", "y", "x", "c"))
    truth_time, _ = timed(_write_truth, dest, 0, scene, output_centres(options.frames, WINDOW, WINDOW)[0], options, flows, repeats=1)
    return [
        ("decode HR source frame + area downsample", read_hr + lr_time, source.n_frames),
        ("optical flow (DIS, LR, both directions)", flow_time, source.n_frames - 1),
        (f"latent LR mosaics + increments ({chunk} frames)", inc_time, n_chunks),
        (f"integrate-and-fire ({chunk} frames)", fire_time, n_chunks),
        (f"write spikes chunk ({chunk} frames)", write_time, n_chunks),
        ("ground-truth frame (2 HR decodes, HR flow interpolation, write)", truth_time, n_truth),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=4000, help="HR frame side (default 4000)")
    parser.add_argument("--frames", type=int, default=1000, help="spike frames (default 1000)")
    parser.add_argument("--source-frames", type=int, default=6, help="frames of the source video")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()

    from pipeline.frame_sources import open_frame_source
    from pipeline.simulate import SimulateOptions, simulate
    from stages.methods import WINDOW, output_centres

    work = tempfile.mkdtemp(prefix="cscsr-sim-bench-")
    try:
        video = os.path.join(work, "source.mp4")
        start = time.perf_counter()
        make_video(video, args.size, args.source_frames)
        print(f"made {args.source_frames}-frame {args.size}x{args.size} video in {time.perf_counter() - start:.0f} s")
        source = open_frame_source(video)
        decode_time, _ = timed(lambda: [source.read(i) for i in range(source.n_frames)], repeats=1)

        options = SimulateOptions(scale=4, cfa="rggb", frames=args.frames, reset="zero", interp="flow", chunk_frames=32)
        start = time.perf_counter()
        simulate(video, os.path.join(work, "run.zarr"), options, workers=args.workers, progress=False)
        wall = time.perf_counter() - start

        n_chunks = -(-args.frames // options.chunk_frames)
        n_truth = len(output_centres(args.frames, WINDOW, options.truth_every))
        stages = stage_breakdown(video, options, n_chunks, n_truth, os.path.join(work, "stage.zarr"))
        total = sum(seconds * calls for _, seconds, calls in stages)
        lr = args.size // 4
        rows = [[name, f"{seconds * 1000:.0f}", calls, f"{seconds * calls:.1f}", f"{100 * seconds * calls / total:.0f} %"]
                for name, seconds, calls in stages]
        print(f"\n## simulate: {args.frames} frames, {args.size}x{args.size} video -> LR {lr}x{lr}, "
              f"{args.workers} workers\n")
        print(markdown_table(["figure", "value", "reference", "ratio"], [
            ["wall time, s", f"{wall:.1f}", f"decode the whole source once: {decode_time:.1f} s", f"{wall / decode_time:.1f}"],
            ["spike frames per second", f"{args.frames / wall:.1f}", "-", "-"],
            ["LR Gpixel-frames/s", f"{args.frames * lr * lr / wall / 1e9:.3f}", "-", "-"],
        ]))
        print("\nStage shares (each stage timed alone in one process x its calls in the run):\n")
        print(markdown_table(["stage", "ms per call", "calls", "s in run", "share"], rows))
        print(f"\nLoad average {load_average()}.")
        save_results("simulate_end_to_end", {"wall_s": wall, "frames": args.frames, "size": args.size,
                                             "decode_s": decode_time, "workers": args.workers,
                                             "stages": [dict(zip(("stage", "seconds", "calls"), s)) for s in stages]})
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
