"""Commands on recordings and videos: info, ingest, export, preview, simulate, reconstruct (and its plan), evaluate."""

import json
from typing import Annotated, Optional

import typer

from rich.table import Table

from stages.reconstruction.methods import METHODS, WINDOW
from pipeline.cli.core import CFA_CHOICES, LAYOUT_CHOICES, METHOD_CHOICES, Scheduler, Workers, command, counted, show_table, stdout


@command()
def info(store: Annotated[str, typer.Argument(help="Spike store or HR video store URL.")],
         as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False):
    """A spike store's shape, duration, CFA, firing rate, chunks, size on disk and bits per pixel (missing chunks
    named); an HR video store's frames, size, frame rate, method and state."""
    from pipeline.jobs.info import summarize

    summary = summarize(store)
    if as_json:
        print(json.dumps(summary, allow_nan=False))  # strict JSON: never a bare Infinity or NaN
    else:
        show_table(f"{summary.pop('kind')} {store}", summary)


@command()
def ingest(src: Annotated[str, typer.Argument(help="Capture: .dat, .npy or .npz, or a raw capture of --layout "
                                                  "(any URL).")],
           store: Annotated[str, typer.Argument(help="Spike store to create (any URL).")],
           height: Annotated[Optional[int], typer.Option(help="Frame height (required for .dat).")] = None,
           width: Annotated[Optional[int], typer.Option(help="Frame width without header columns (required for .dat).")] = None,
           flip: Annotated[bool, typer.Option("--flip", help="Frames are stored upside down (real cameras).")] = False,
           cfa: Annotated[str, typer.Option(metavar=CFA_CHOICES, help="Sensor CFA as recorded.")] = "mono",
           fps: Annotated[float, typer.Option(help="Spike frames per second.")] = 20000.0,
           head_columns: Annotated[int, typer.Option(help="Header columns at the end of each .dat row, dropped (SPS10: 16 of 416).")] = 0,
           key: Annotated[Optional[str], typer.Option(help="Array name inside a .npz (default: spk).")] = None,
           layout: Annotated[Optional[str], typer.Option(metavar=LAYOUT_CHOICES, help="A raw capture's layout, "
                                                         "whatever its name: dat (frames of --height x --width "
                                                         "bits), sps100 (the 1000x1000 camera's PCIe line packets, "
                                                         "docs/formats.md) (default: by extension).")] = None,
           reset: Annotated[str, typer.Option(help="Integrator reset of the sensor: subtract or zero.")] = "subtract",
           workers: Annotated[Optional[int], typer.Option(help="Ingest in parallel on a local Dask cluster of this many "
                                                               "worker processes (.dat, .npy, sps100; default: in "
                                                               "this process, one stream).")] = None,
           scheduler: Annotated[Optional[str], typer.Option(help="Ingest in parallel on the Dask scheduler at this "
                                                                 "address (.dat, .npy, sps100).")] = None,
           task_frames: Annotated[Optional[int], typer.Option(help="Frames per task, rounded up to whole chunks "
                                                                   "(default: about 64 MiB of spikes).")] = None,
           resume: Annotated[bool, typer.Option("--resume", help="Finish an interrupted ingest into STORE, from the "
                                                "same capture.")] = False,
           dry_run: Annotated[bool, typer.Option("--dry-run", help="Check everything, create nothing, print the plan "
                                                 "(size at rest, hours on 1, 8, 64 workers, measured on one task).")] = False,
           as_json: Annotated[bool, typer.Option("--json", help="With --dry-run: print the plan as JSON.")] = False,
           overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace STORE if it exists.")] = False):
    """Copy a raw capture into a new spike store, streaming in bounded memory, or in parallel on Dask; resumable."""
    from pipeline.jobs.ingest import IngestOptions, plan_ingest, run_ingest

    if as_json and not dry_run:
        raise ValueError("--json is for --dry-run (the plan as JSON): add --dry-run, or leave --json out")
    options = IngestOptions(height, width, cfa, fps, flip, head_columns, key, reset, overwrite, resume, task_frames,
                            layout=layout)
    if dry_run:
        plan = plan_ingest(src, store, options, workers=workers, scheduler=scheduler)
        if as_json:
            print(json.dumps(plan, allow_nan=False))
            return
        hours = plan.pop("hours")
        rows = {k: v for k, v in plan.items() if k not in ("source", "store")}
        rows["seconds_per_task"] = duration(plan["seconds_per_task"])
        rows.update({f"time on {counted(int(n), 'worker')}": duration(h * 3600) for n, h in hours.items()})
        show_table(f"ingest {src} -> {store} (dry run: nothing created)", rows)
        return
    done = run_ingest(src, store, options, workers=workers, scheduler=scheduler)
    attrs = done["attrs"]
    tasks = (f" ({counted(done['tasks_run'], 'task')} run, {done['tasks_skipped']} already committed)"
             if resume or workers is not None or scheduler is not None else "")
    stdout.print(f"{store}: {counted(done['frames'], 'frame')} {attrs['height']}x{attrs['width']}, cfa {attrs['cfa']}, "
                 f"{attrs['spike_count']} spikes{tasks}")


@command()
def export(store: Annotated[str, typer.Argument(help="Spike store or HR video store URL.")],
           dest: Annotated[str, typer.Argument(help="A spike store's destination: a .dat file. A video store's: "
                                                    "a .mp4 file, or a folder for PNG frames (any URL).")],
           overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace DEST if it exists.")] = False):
    """A spike store back to a raw .dat capture (original orientation, byte-identical to what was ingested);
    an HR video store to an H.264 .mp4 (10 fps) or to a folder of PNG frames (frame_<centre>.png)."""
    from pipeline.jobs.export import export as run

    run(store, dest, overwrite=overwrite)
    stdout.print(f"wrote {dest}")


@command()
def preview(store: Annotated[str, typer.Argument(help="Spike store URL.")],
            image: Annotated[str, typer.Argument(help="PNG to write (any URL).")],
            centre: Annotated[Optional[int], typer.Option(help="Centre spike frame (default: the middle).")] = None,
            window: Annotated[int, typer.Option(help="Frames in the window (odd).")] = WINDOW,
            gain: Annotated[Optional[float], typer.Option(help="Rate-to-intensity gain (default: store's, else auto).")] = None,
            scale: Annotated[int, typer.Option(help="Upsampling factor.")] = 1,
            overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace IMAGE if it exists.")] = False):
    """One TFP picture (window mean, demosaicked, upsampled) from a spike store."""
    from pipeline.stores.images import image_suffix, write_image
    from pipeline.jobs.preview import preview as run
    from pipeline.stores.storage import check_apart, source_of

    check_apart(image, store, source_of(store))  # nor the picture or capture the store was made from
    image_suffix(image)  # a picture we cannot write is refused before the work
    shot = run(store, centre=centre, window=window, gain=gain, scale=scale)
    write_image(image, shot.image, overwrite=overwrite)
    stdout.print(f"wrote {image}: frames {shot.centre - window // 2}..{shot.centre + window // 2}, gain {shot.gain:.4g}")



@command()
def simulate(src: Annotated[str, typer.Argument(help="A video, a folder of frames, a Zarr video, or one image.")],
             store: Annotated[str, typer.Argument(help="Spike store to create (any URL).")],
             scale: Annotated[int, typer.Option(help="Super-resolution factor s: LR = HR / s.")] = 4,
             cfa: Annotated[str, typer.Option(metavar=CFA_CHOICES, help="CFA of the simulated sensor.")] = "rggb",
             brightness: Annotated[float, typer.Option(help="Brightness coefficient alpha.")] = 0.6,
             threshold: Annotated[float, typer.Option(help="Firing threshold theta.")] = 1.0,
             frames: Annotated[int, typer.Option(help="Spike frames to simulate (>= 41).")] = WINDOW,
             motion: Annotated[Optional[str], typer.Option(help="For one image, which needs it: static or random "
                                                                    "(known flow); a video brings its own.")] = None,
             seed: Annotated[int, typer.Option(help="Seed of every random choice.")] = 0,
             noise: Annotated[str, typer.Option(help="none or realistic (shot noise, threshold mismatch, dark current).")] = "none",
             reset: Annotated[str, typer.Option(help="zero (the paper) or subtract (real sensors).")] = "zero",
             interp: Annotated[str, typer.Option(help="Frame interpolation: flow or linear.")] = "flow",
             truth_every: Annotated[int, typer.Option(help="Ground truth every K frames from frame 20.")] = WINDOW,
             speed: Annotated[Optional[float], typer.Option(help="--motion random: typical HR pixels per frame "
                                                                 "(default 0.5).")] = None,
             deform: Annotated[Optional[float], typer.Option(help="--motion random: local deformation, HR pixels "
                                                                  "(default 0).")] = None,
             fps: Annotated[float, typer.Option(help="Spike frames per second.")] = 20000.0,
             chunk_frames: Annotated[Optional[int], typer.Option(help="Frames per time chunk (default ~4 MiB).")] = None,
             workers: Workers = None, scheduler: Scheduler = None,
             overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace STORE if it exists.")] = False):
    """Simulate a colour spike recording with HR ground truth (Algorithm 2), on Dask."""
    from pipeline.jobs.simulate import SimulateOptions, simulate as run

    options = SimulateOptions(scale, cfa, brightness, threshold, frames, motion, seed, noise, reset, interp,
                              truth_every, speed, deform, fps, chunk_frames, overwrite)
    attrs = run(src, store, options, workers=workers, scheduler=scheduler)
    stdout.print(f"{store}: {frames} frames {attrs['height']}x{attrs['width']} cfa {attrs['cfa']}, "
              f"{attrs['spike_count']} spikes, gain {attrs['gain']:.4g}")


@command()
def reconstruct(store: Annotated[str, typer.Argument(help="Spike store URL.")],
                out: Annotated[str, typer.Argument(help="HR video store to write (any URL).")],
                method: Annotated[str, typer.Option(metavar=METHOD_CHOICES, help="Reconstruction method.")] = "tfp",
                every: Annotated[int, typer.Option(help="One output frame every K spike frames.")] = WINDOW,
                window: Annotated[int, typer.Option(help="Spike frames per output frame (odd).")] = WINDOW,
                gain: Annotated[Optional[float], typer.Option(help="Rate-to-intensity gain (default: store's, else auto).")] = None,
                scale: Annotated[Optional[int], typer.Option(help="Upsampling factor (default: store's, else 4).")] = None,
                tile: Annotated[Optional[int], typer.Option(help="Tile side in LR pixels (multiple of 8; default 256 "
                                                                 "on CPU workers, on GPU workers the largest the GPU "
                                                                 "holds: the whole frame where it fits).")] = None,
                weights: Annotated[Optional[str], typer.Option(help="Network weights (safetensors) for cscsr "
                                                                    "(default: full on GPU workers, lite on "
                                                                    "CPUs; lite-mono for a mono "
                                                                    "recording).")] = None,
                workers: Workers = None, scheduler: Scheduler = None,
                resume: Annotated[bool, typer.Option("--resume", help="Finish an interrupted run into OUT.")] = False,
                overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace OUT if it exists.")] = False,
                segment_tasks: Annotated[int, typer.Option(help="Tasks per segment: each segment runs in a fresh "
                                                                 "process and cluster, so memory stays bounded.")]
                = 10_000,
                precision: Annotated[str, typer.Option(help="The network's arithmetic: fp32, or bf16 (autocast on "
                                                            "the worker's GPU or CPU); cscsr methods only.")] = "fp32",
                gpu_batch: Annotated[Optional[int], typer.Option(help="Windows per network pass on GPU workers "
                                                                      "(default: as many as the GPU holds, at "
                                                                      "most 16).")] = None,
                fast_gpu: Annotated[bool, typer.Option("--fast-gpu", help="On GPU workers: channels-last, cuDNN "
                                                                          "autotuning and torch.compile (compiled "
                                                                          "once per shape, cached on disk); not "
                                                                          "bit-reproducible across processes. A "
                                                                          "CPU ignores it.")] = False,
                backend: Annotated[str, typer.Option(help="What runs the network: torch, or onnx (ONNX Runtime on "
                                                          "the CPU: ~1.3x faster, ~18 s to export per tile shape "
                                                          "and worker; pip install 'cscsr\\[onnx]').")] = "torch",
                # \[onnx]: --help is rich markup, where a bare [onnx] is a tag and prints nothing
                start: Annotated[Optional[str], typer.Option(help="Only output frames centred at or after this: "
                                                                  "a spike frame (1200) or seconds (2.5s, "
                                                                  "1500ms).")] = None,
                stop: Annotated[Optional[str], typer.Option(help="Only output frames centred before this (spike "
                                                                 "frame or seconds).")] = None,
                region: Annotated[Optional[str], typer.Option(help="Only this region, Y0:Y1,X0:X1 in LR pixels (even "
                                                                   "bounds for a Bayer CFA).")] = None,
                dry_run: Annotated[bool, typer.Option("--dry-run", help="Check everything, create nothing, and "
                                                                        "print the plan, priced by a few of its "
                                                                        "tasks run for real on its workers.")]
                = False,
                as_json: Annotated[bool, typer.Option("--json", help="With --dry-run: the plan as JSON.")] = False):
    """Reconstruct HR colour video from a spike store, over Dask (network tasks on GPU workers if there are any)."""
    from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct as run

    if as_json and not dry_run:
        raise ValueError("--json is for --dry-run (the plan as JSON): add --dry-run, or leave --json out")
    options = ReconstructOptions(method=method, every=every, window=window, gain=gain, scale=scale, tile=tile,
                                 weights=weights, resume=resume, overwrite=overwrite, segment_tasks=segment_tasks,
                                 precision=precision, gpu_batch=gpu_batch, backend=backend, fast_gpu=fast_gpu,
                                 start=start, stop=stop, region=region)
    counts = run(store, out, options, workers=workers, scheduler=scheduler, progress=not dry_run, dry_run=dry_run)
    if dry_run:
        show_plan(counts, as_json)
        return
    stdout.print(f"{out}: {counted(counts['frames'], 'frame')} ({counted(counts['tasks_run'], 'task')} run, "
                 f"{counts['tasks_skipped']} already committed)")


def in_units(size: float) -> str:
    """Bytes as a few digits in binary units: ``1.2 GiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if size < 1024 or unit == "TiB":
            return f"{size:.3g} {unit}"
        size /= 1024


def duration(seconds: float) -> str:
    """Seconds as a few digits in the unit that suits them: ``0.5 s``, ``41 s``, ``12 min``, ``3.2 h`` (never
    ``0.000139`` hours; ``--json`` keeps the exact numbers)."""
    if seconds < 90:
        return f"{seconds:.2g} s"
    return f"{seconds / 60:.3g} min" if seconds < 5400 else f"{seconds / 3600:.3g} h"


def show_plan(plan: dict, as_json: bool) -> None:
    """``reconstruct --dry-run``'s plan: JSON on standard output, or a table and the hours on N workers."""
    if as_json:
        print(json.dumps(plan, allow_nan=False))
        return
    measured = plan["measured"]
    y0, y1, x0, x1 = plan["region"]
    rows = {"output frames": f"{plan['frames']} (centres at spike frames {plan['spike_frames']}, every "
                             f"{plan['every']}; part [{plan['start']}, {plan['stop']}))",
            "region": f"{y0}:{y1},{x0}:{x1} LR -> {plan['hr_height']}x{plan['hr_width']} HR (x{plan['scale']})",
            "method": f"{plan['method']} on {plan['runs_on']}"
                      + (f", weights {plan['weights']}" if plan["weights"] else ""),
            "tile": f"{plan['tile_lr']} LR ({plan['tiles_per_frame']} per frame)",
            "tasks": f"{plan['tasks']} ({plan['tasks_to_run']} to run), {plan['frames_per_task']} frame(s) each",
            "gain": plan["gain"],
            "measured": f"{counted(measured['tasks'], 'task')} run on {plan['measured_on']} at once: "
                        f"{measured['seconds_per_task']:.3g} s each, {in_units(measured['bytes'])} written",
            "output size": f"~{in_units(plan['output_bytes'])} (the measured tasks' bytes per pixel)",
            "this job": f"~{duration(plan['job_seconds'])} on {plan['workers']} worker(s)"
                        + (f" (each segment's local cluster: {plan['segment_start_seconds']:.2g} s to start and stop)"
                           if plan["segment_start_seconds"] else "")}
    show_table(f"plan: {plan['store']} -> {plan['out']}", rows)
    workers = "GPU workers" if plan["runs_on"] == "GPU workers" else "workers"
    table = Table(title="estimated time")
    table.add_column(workers, justify="right")
    table.add_column("time", justify="right")
    for count, hours in plan["hours"].items():
        table.add_row(count, duration(hours * 3600))
    stdout.print(table)
    stdout.print(f"{plan['seconds_per_task']:.3g} s per task, one task at a time per worker", soft_wrap=True)


@command()
def evaluate(store: Annotated[str, typer.Argument(help="Simulated spike store (with truth).")],
             methods: Annotated[str, typer.Option(help=f"Comma-separated methods of {', '.join(METHODS)}.")] = "tfp,tfi",
             out_dir: Annotated[str, typer.Option("--out", help="Folder for reconstructions, CSVs and the picture.")] = "evaluation",
             weights: Annotated[Optional[str], typer.Option(help="Network weights for cscsr.")] = None,
             workers: Workers = None, scheduler: Scheduler = None,
             overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the --out folder if it is an "
                                                     "evaluation.")] = False,
             video: Annotated[Optional[list[str]], typer.Option("--video", help="NAME=URL: a written video store "
                              "(your own method's) scored beside the methods; repeatable.")] = None):
    """PSNR / SSIM of methods against a store's ground truth: a table, CSVs and a side-by-side picture."""
    from pipeline.jobs.evaluate import evaluate as run, parse_videos

    rows = run(store, [m.strip() for m in methods.split(",") if m.strip()], out_dir, weights=weights,
               workers=workers, scheduler=scheduler, overwrite=overwrite, videos=parse_videos(video))
    table = Table(title=f"{store}: against ground truth ({counted(rows[0]['frames'], 'frame')})")
    for column in ("method", "PSNR (dB)", "SSIM", "s / image"):
        table.add_column(column, justify="left" if column == "method" else "right")
    for row in rows:
        seconds = row["seconds_per_image"]
        table.add_row(row["method"], f"{row['psnr']:.2f}", f"{row['ssim']:.4f}",
                      "written" if seconds is None else f"{seconds:.2f}")
    stdout.print(table)
    stdout.print(f"wrote {out_dir}/metrics.csv, {out_dir}/summary.csv, {out_dir}/comparison.png")
