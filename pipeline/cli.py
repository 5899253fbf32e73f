"""The ``cscsr`` command line (Typer): thin wrappers that parse, call the pipeline, report.

Every failure is one line on standard error and a non-zero exit; set ``CSCSR_DEBUG=1`` for
the full traceback.
"""

from pipeline import stopping  # first of all: in a worker process of the command, Ctrl-C is ignored from here on

import contextlib
import functools
import json
import logging
import os
import signal
import sys
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from stages.cfa import PATTERNS
from stages.methods import METHODS, WINDOW
from stages.sps100 import LAYOUTS

# Click's usage error (Typer >= 0.17 vendors Click; older Typers use Click itself): found the same way in both
USAGE_ERROR = next(kind for kind in typer.BadParameter.__mro__ if kind.__name__ == "UsageError")


@contextlib.contextmanager
def usage_in_one_line(group: typer.Context | None = None):
    """A usage error (an unknown option or command, a value of the wrong type, a missing or extra argument)
    answered as every other bad input: ``error: <one line>`` on standard error and exit status 1, rather than
    Click's usage block with status 2. ``cscsr`` alone still prints the help."""
    try:
        yield
    except USAGE_ERROR as error:
        if type(error).__name__ == "NoArgsIsHelpError":
            raise
        err.print(f"error: {usage_message(error, group)}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(1) from None


def usage_message(error, group: typer.Context | None = None) -> str:
    """``cscsr reconstruct: invalid value for '--every': ..., got 'abc' (see cscsr reconstruct --help)``; the
    command is the error's own, else the one ``group`` was invoking (Click leaves some errors without one)."""
    from stages.errors import describe

    message = describe(error.format_message()).rstrip(".")
    with contextlib.suppress(Exception):  # Typer's conversion keeps the value in pydantic's error, its cause
        message += f", got {error.__cause__.errors()[0]['input']!r}"
    context = getattr(error, "ctx", None)
    if (context is None or context is group) and group is not None and group.invoked_subcommand:
        where = f"{group.command_path} {group.invoked_subcommand}"
    else:
        where = context.command_path if context is not None else "cscsr"
    return f"{where}: {message[:1].lower()}{message[1:]} (see {where} --help)"


class OneLineUsageErrors(typer.core.TyperGroup):
    """The ``cscsr`` group: usage errors in parsing its own options and every command's are one line
    (:func:`usage_in_one_line`)."""

    def make_context(self, *args, **kwargs):
        with usage_in_one_line():
            return super().make_context(*args, **kwargs)

    def invoke(self, ctx):
        with usage_in_one_line(ctx):  # resolving the command, and parsing its arguments and options
            return super().invoke(ctx)


app = typer.Typer(cls=OneLineUsageErrors, no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  help="Reconstruction pipeline for colour spike cameras: ingest, inspect, export, reconstruct.")
# soft_wrap: a printed line is never broken at the terminal's width (a path in a result stays one line that
# a script can read, whatever the width or the path's length); tables still fit the width
err = Console(stderr=True, soft_wrap=True)
stdout = Console(soft_wrap=True)


def choices(names) -> str:
    """How ``--help`` shows an option's choices; the command checks the value itself, so that a bad one
    is the usual one-line error rather than Click's usage block."""
    return "[" + "|".join(names) + "]"


METHOD_CHOICES, CFA_CHOICES = choices(METHODS), choices(PATTERNS)
LAYOUT_CHOICES = choices(LAYOUTS)


def show_version(value: bool) -> None:
    if value:
        from cscsr import __version__

        print(f"cscsr {__version__}")
        raise typer.Exit()


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_TIME = "%Y-%m-%dT%H:%M:%S%z"  # ISO 8601, local time with its offset
log_level = logging.INFO  # set by --quiet / --verbose for the command that runs


@app.callback()
def options(context: typer.Context,
            version: Annotated[bool, typer.Option("--version", callback=show_version, is_eager=True,
                                                  help="Print the version and exit.")] = False,
            quiet: Annotated[bool, typer.Option("-q", "--quiet", help="No progress bars or log lines below "
                                                "warnings: results and errors only.")] = False,
            verbose: Annotated[bool, typer.Option("-v", "--verbose", help="Debug log lines, and Dask's own "
                                                  "warnings.")] = False) -> None:
    """Reconstruction pipeline for colour spike cameras: ingest, inspect, export, reconstruct."""
    global log_level
    from pipeline.progress import set_quiet

    if quiet and verbose:
        err.print("error: -q/--quiet and -v/--verbose exclude each other: give one", markup=False, highlight=False)
        raise typer.Exit(1)
    log_level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    set_quiet(quiet)
    context.call_on_close(lambda: set_quiet(False))  # in-process callers (tests, the Python API) get them back
    send_logs(context)


def send_logs(context: typer.Context, path: str | None = None) -> None:
    """Our log records, timestamped one line each, to standard error or to the file ``path`` (appended), at the
    level --quiet / --verbose chose, until the command ends. Only the command line configures logging."""
    handler = logging.FileHandler(path, encoding="utf-8") if path else logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(LOG_FORMAT, LOG_TIME))
    handler.set_name("cscsr")
    logger = logging.getLogger("cscsr")
    for old in [h for h in logger.handlers if h.get_name() == "cscsr"]:  # --log-file replaces standard error
        logger.removeHandler(old)
        old.close()
    logger.addHandler(handler)
    logger.setLevel(log_level)

    def restore() -> None:
        logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
        handler.close()

    context.call_on_close(restore)


def command_line(context: typer.Context) -> str:
    """The running command as one would retype it: its name, arguments, and every option not at its default."""
    words = ["cscsr", context.info_name]
    for param in context.command.params:
        value = context.params.get(param.name)
        if param.param_type_name == "argument":
            words.append(str(value))
        elif value != param.default and value is not None and value not in ((), []):
            if param.is_flag:
                words.append(param.opts[0] if value else param.secondary_opts[0])
            elif isinstance(value, (list, tuple)):  # a repeated option, e.g. --pictures A --pictures B
                for item in value:
                    words += [param.opts[0], str(item)]
            else:
                words += [param.opts[0], str(value)]
    return " ".join(words)


def debugging() -> bool:
    """``CSCSR_DEBUG=1`` (or ``true``, ``yes``) shows the traceback of a failure; unset, empty, ``0``, ``false``,
    ``no`` and anything else do not."""
    return os.environ.get("CSCSR_DEBUG", "").strip().lower() in ("1", "true", "yes")


INTERRUPTED_STATUS, TERMINATED_STATUS = 128 + signal.SIGINT, 128 + signal.SIGTERM  # the shells' convention


def one_line_errors(command):
    """Turn any exception into ``error: <one line>`` and exit status 1; Ctrl-C and SIGTERM (``pipeline.stopping``)
    into ``error: interrupted`` / ``error: terminated (SIGTERM)`` and 130 / 143, once the clean-up has run."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except KeyboardInterrupt as interrupt:
            stopping.quiet_finalizers()
            terminated = isinstance(interrupt, stopping.Terminated)
            err.print(f"error: {'terminated (SIGTERM)' if terminated else 'interrupted'}", markup=False)
            raise typer.Exit(TERMINATED_STATUS if terminated else INTERRUPTED_STATUS) from None
        except Exception as error:
            if debugging():
                raise
            from pipeline.storage import unreachable
            from stages.errors import describe

            message = describe(error)
            if reach := unreachable(error, [*args, *kwargs.values()]):
                message = reach
            elif isinstance(error, FileNotFoundError):
                message = f"cannot read {error.filename or message}: no such file or object"
            elif not isinstance(error, ValueError):
                message = f"{type(error).__name__}: {message}"
            err.print(f"error: {message}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None

    return wrapper


def command(*args, **kwargs):
    return lambda fn: app.command(*args, **kwargs)(one_line_errors(fn))


def counted(number: int, noun: str) -> str:
    """``1 task``, ``0 tasks``, ``2 tasks``: a count with its noun, singular for one."""
    return f"{number} {noun}{'' if number == 1 else 's'}"


def show_table(title: str, rows: dict) -> None:
    table = Table(title=title, show_header=False)
    for key, value in rows.items():
        table.add_row(key, f"{value:.6g}" if isinstance(value, float) else str(value))
    stdout.print(table)


@command()
def info(store: Annotated[str, typer.Argument(help="Spike store or HR video store URL.")],
         as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False):
    """A spike store's shape, duration, CFA, firing rate, chunks, size on disk and bits per pixel (missing chunks
    named); an HR video store's frames, size, frame rate, method and state."""
    from pipeline.info import summarize

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
    from pipeline.ingest import IngestOptions, plan_ingest, run_ingest

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
    from pipeline.export import export as run

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
    from pipeline.images import image_suffix, write_image
    from pipeline.preview import preview as run
    from pipeline.storage import check_apart

    check_apart(image, store)
    image_suffix(image)  # a picture we cannot write is refused before the work
    shot = run(store, centre=centre, window=window, gain=gain, scale=scale)
    write_image(image, shot.image, overwrite=overwrite)
    stdout.print(f"wrote {image}: frames {shot.centre - window // 2}..{shot.centre + window // 2}, gain {shot.gain:.4g}")


Workers = Annotated[Optional[int], typer.Option(help="Local Dask worker processes (default: one per core; at most "
                                                     "4 per core and 256).")]
Scheduler = Annotated[Optional[str], typer.Option(help="Dask scheduler address (default: DASK_SCHEDULER_ADDRESS, else Dask's "
                                                          "scheduler-address setting).")]


@command()
def simulate(src: Annotated[str, typer.Argument(help="A video, a folder of frames, a Zarr video, or one image.")],
             store: Annotated[str, typer.Argument(help="Spike store to create (any URL).")],
             scale: Annotated[int, typer.Option(help="Super-resolution factor s: LR = HR / s.")] = 4,
             cfa: Annotated[str, typer.Option(metavar=CFA_CHOICES, help="CFA of the simulated sensor.")] = "rggb",
             brightness: Annotated[float, typer.Option(help="Brightness coefficient alpha.")] = 0.6,
             threshold: Annotated[float, typer.Option(help="Firing threshold theta.")] = 1.0,
             frames: Annotated[int, typer.Option(help="Spike frames to simulate (>= 41).")] = WINDOW,
             motion: Annotated[Optional[str], typer.Option(help="For one image: static or random (known flow).")] = None,
             seed: Annotated[int, typer.Option(help="Seed of every random choice.")] = 0,
             noise: Annotated[str, typer.Option(help="none or realistic (shot noise, threshold mismatch, dark current).")] = "none",
             reset: Annotated[str, typer.Option(help="zero (the paper) or subtract (real sensors).")] = "zero",
             interp: Annotated[str, typer.Option(help="Frame interpolation: flow or linear.")] = "flow",
             truth_every: Annotated[int, typer.Option(help="Ground truth every K frames from frame 20.")] = WINDOW,
             speed: Annotated[float, typer.Option(help="Random motion: typical HR pixels per frame.")] = 0.5,
             deform: Annotated[float, typer.Option(help="Random motion: local deformation, HR pixels.")] = 0.0,
             fps: Annotated[float, typer.Option(help="Spike frames per second.")] = 20000.0,
             chunk_frames: Annotated[Optional[int], typer.Option(help="Frames per time chunk (default ~4 MiB).")] = None,
             workers: Workers = None, scheduler: Scheduler = None,
             overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace STORE if it exists.")] = False):
    """Simulate a colour spike recording with HR ground truth (Algorithm 2), on Dask."""
    from pipeline.simulate import SimulateOptions, simulate as run

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
                                                                    "CPUs).")] = None,
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
                region: Annotated[Optional[str], typer.Option(help="Only this region, Y0:Y1,X0:X1 in LR pixels (X0 a "
                                                                   "multiple of 8; even bounds for a Bayer "
                                                                   "CFA).")] = None,
                dry_run: Annotated[bool, typer.Option("--dry-run", help="Check everything, create nothing, and "
                                                                        "print the plan, priced by a few of its "
                                                                        "tasks run for real on its workers.")]
                = False,
                as_json: Annotated[bool, typer.Option("--json", help="With --dry-run: the plan as JSON.")] = False):
    """Reconstruct HR colour video from a spike store, over Dask (network tasks on GPU workers if there are any)."""
    from pipeline.reconstruct import ReconstructOptions, reconstruct as run

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
            "region": f"{y0}:{y1},{x0}:{x1} LR -> {plan['hr_width']}x{plan['hr_height']} HR (x{plan['scale']})",
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
                                                     "evaluation.")] = False):
    """PSNR / SSIM of methods against a store's ground truth: a table, CSVs and a side-by-side picture."""
    from pipeline.evaluate import evaluate as run

    rows = run(store, [m.strip() for m in methods.split(",") if m.strip()], out_dir, weights=weights,
               workers=workers, scheduler=scheduler, overwrite=overwrite)
    table = Table(title=f"{store}: against ground truth ({rows[0]['frames']} frames)")
    for column in ("method", "PSNR (dB)", "SSIM", "s / image"):
        table.add_column(column, justify="left" if column == "method" else "right")
    for row in rows:
        table.add_row(row["method"], f"{row['psnr']:.2f}", f"{row['ssim']:.4f}", f"{row['seconds_per_image']:.2f}")
    stdout.print(table)
    stdout.print(f"wrote {out_dir}/metrics.csv, {out_dir}/summary.csv, {out_dir}/comparison.png")


@command("model-info")
def model_info(config: Annotated[str, typer.Option(help="Named configuration: lite or full.")] = "lite",
               weights: Annotated[Optional[str], typer.Option(help="Describe this weights file instead.")] = None):
    """Parameter counts and settings of a CSCSR network configuration (or of a weights file)."""
    from cscsr.model_info import model_info as describe

    rows = describe(config, weights)
    show_table(f"CSCSR {rows['configuration']}", rows)


@command()
def train(context: typer.Context,
          out: Annotated[str, typer.Argument(help="Folder for checkpoints, log.jsonl and the final weights.")],
          config: Annotated[str, typer.Option(help="Network configuration: lite or full.")] = "lite",
          steps: Annotated[int, typer.Option(help="Optimiser steps in all (a resumed run continues to this).")] = 20000,
          batch: Annotated[int, typer.Option(help="Clips per step.")] = 8,
          lr_side: Annotated[int, typer.Option(help="LR crop side of a training clip (even).")] = 32,
          learning_rate: Annotated[float, typer.Option(help="Adam learning rate (after the warm-up, x0.9 every "
                                                             "--decay-every steps).")] = 2e-4,
          warmup: Annotated[int, typer.Option(help="Steps of linear learning-rate warm-up.")] = 200,
          decay_every: Annotated[int, typer.Option(help="Steps between x0.9 learning-rate decays; may change on "
                                                        "--resume (the rate drops at once to its new place on the "
                                                        "schedule: an annealing phase).")] = 7500,
          seed: Annotated[int, typer.Option(help="Seed of the clips and the initial weights.")] = 0,
          pool: Annotated[int, typer.Option(help="Clips simulated up front and reused under 8 flips and turns "
                                                 "(0: a fresh clip every time); may grow on --resume.")] = 0,
          init: Annotated[Optional[str], typer.Option(help="Start from the weights in this file instead of random ones "
                                                           "(fine-tuning, e.g. on larger --lr-side crops).")] = None,
          motion: Annotated[str, typer.Option(help="Ablation: joint or assembled motion estimation.")] = "joint",
          flow_guidance: Annotated[bool, typer.Option("--flow-guidance/--no-flow-guidance",
                                                      help="Ablation: fuse time points aligned by flow, or not.")] = True,
          checkpoint_every: Annotated[int, typer.Option(help="Steps between checkpoints.")] = 100,
          validate_every: Annotated[int, typer.Option(help="Steps between validation PSNR lines.")] = 250,
          pictures: Annotated[Optional[list[str]], typer.Option(
              help="A folder of training pictures (repeat for more; default: the bundled pictures).")] = None,
          dead_leaves: Annotated[float, typer.Option(help="Share of clips showing dead leaves.")] = 0.4,
          device: Annotated[str, typer.Option(help="cpu or cuda (cuda: clips synthesised on the GPU).")] = "cpu",
          precision: Annotated[str, typer.Option(help="fp32 or bf16 (autocast).")] = "fp32",
          synthesis: Annotated[str, typer.Option(help="Clips by numpy or torch (on the device; the same clips); "
                                                      "auto: torch on a GPU.")] = "auto",
          time_budget: Annotated[float, typer.Option(help="Stop cleanly, checkpointed, before this many seconds "
                                                          "(0: no limit); --resume continues.")] = 0.0,
          threads: Annotated[Optional[int], typer.Option(help="Torch threads (default: every core).")] = None,
          channels_last: Annotated[bool, typer.Option("--channels-last", help="Convolutions on NHWC tensors (the "
                                                      "same training within rounding; may change on --resume).")] = False,
          resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT/checkpoint.safetensors (exact), "
                                                       "or from the parts of a portable checkpoint in OUT.")] = False):
    """Train the CSCSR network on clips simulated on the fly; resumable."""
    import torch

    from cscsr.train import TrainOptions, train as run
    from pipeline.storage import check_apart

    check_apart(out, init, *(pictures or []))
    if threads:
        torch.set_num_threads(threads)
    options = TrainOptions(config=config, steps=steps, batch=batch, lr_side=lr_side, learning_rate=learning_rate,
                           warmup=warmup, decay_every=decay_every, seed=seed, pool=pool, init=init or "",
                           motion=motion, flow_guidance=flow_guidance, pictures=os.pathsep.join(pictures or []),
                           dead_leaves=dead_leaves, device=device, precision=precision, time_budget=time_budget,
                           synthesis=synthesis, channels_last=channels_last,
                           checkpoint_every=checkpoint_every, validate_every=validate_every)
    final = run(options, out, resume=resume, log=lambda line: stdout.print(line, highlight=False),
                command=command_line(context))
    stdout.print(f"weights: {final}")


@command("export-weights")
def export_weights(folder: Annotated[str, typer.Argument(help="A cscsr train folder.")],
                   dest: Annotated[str, typer.Argument(help="Weights file to write (.safetensors).")],
                   half: Annotated[bool, typer.Option("--half", help="Store float16 (half the size).")] = False,
                   portable: Annotated[bool, typer.Option(
                       "--portable", help="Write DEST as a folder holding the whole checkpoint in parts of at most "
                                          "16 MiB (bf16 Adam moments; fp16 weights with --half), which train "
                                          "--resume continues on another machine (close, not bit-exact).")] = False,
                   overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace DEST if it is a weights file "
                                                           "(--portable: the parts in DEST).")] = False):
    """The latest checkpoint of a training run as a weights file for --weights (or, --portable, as a
    checkpoint small enough to carry to another machine)."""
    from cscsr.train import export_portable, export_weights as run
    from pipeline.storage import check_apart

    check_apart(dest, os.path.join(folder, "checkpoint.safetensors"))  # the file it reads (DEST may sit beside it)
    if portable:
        step, parts = export_portable(folder, dest, weights="float16" if half else "float32", overwrite=overwrite)
        stdout.print(f"{dest}: the checkpoint after {step} steps in {len(parts)} parts")
        return
    step = run(folder, dest, storage="float16" if half else "float32", overwrite=overwrite)
    stdout.print(f"{dest}: weights after {step} steps")


@command("make-testset")
def make_testset(out: Annotated[str, typer.Argument(help="Folder for the test set (sources, stores, manifest).")],
                 workers: Workers = None,
                 overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace OUT if it exists.")] = False):
    """Simulate the held-out test set (3 pictures x alpha 0.6/0.8/1.0), bit-identically every time."""
    from pipeline.testset import make_testset as run

    stores = run(out, workers=workers, overwrite=overwrite)
    stdout.print(f"{out}: {len(stores)} spike stores with ground truth")


@command("evaluate-testset")
def evaluate_testset(testset: Annotated[str, typer.Argument(help="A folder made by cscsr make-testset.")],
                     methods: Annotated[str, typer.Option(help="Comma-separated methods.")] = "tfp,tfi",
                     weights: Annotated[Optional[str], typer.Option(help="Network weights for cscsr.")] = None,
                     out: Annotated[str, typer.Option(help="Folder for results.")] = "evaluation-testset",
                     workers: Workers = None, scheduler: Scheduler = None,
                     overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the --out folder if it is an "
                                                             "evaluation.")] = False):
    """PSNR / SSIM per method and alpha on the test set: table, summary.csv, crops.png."""
    from pipeline.testset import evaluate_testset as run

    rows = run(testset, [m.strip() for m in methods.split(",") if m.strip()], out, weights=weights, workers=workers,
               scheduler=scheduler, overwrite=overwrite)
    table = Table(title=f"{testset}: x4, mean over pictures and truth frames")
    for column in ("method", "alpha", "PSNR dB", "SSIM", "s / image"):
        table.add_column(column)
    for r in rows:
        table.add_row(r["method"], str(r["alpha"]), f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['seconds_per_image']:.3f}")
    stdout.print(table)


@command()
def watch(context: typer.Context,
          inbox: Annotated[str, typer.Argument(help="Where recordings land (any URL).")],
          outbox: Annotated[str, typer.Argument(help="Local folder for outputs and the ledger.")],
          interval: Annotated[str, typer.Option(help="Time between passes: 30s, 10m, 1h.")] = "10m",
          once: Annotated[bool, typer.Option("--once", help="One pass, then exit (for cron).")] = False,
          method: Annotated[str, typer.Option(metavar=METHOD_CHOICES, help="Reconstruction method.")] = "tfp",
          weights: Annotated[Optional[str], typer.Option(help="Network weights for cscsr.")] = None,
          every: Annotated[int, typer.Option(help="One output frame every K spike frames.")] = WINDOW,
          tile: Annotated[int, typer.Option(help="Tile side in LR pixels.")] = 256,
          settle: Annotated[float, typer.Option(help="Seconds a recording must be unchanged before it is taken: "
                                                  "more than the longest pause of what writes into INBOX.")] = 10.0,
          max_attempts: Annotated[int, typer.Option(help="Tries before a failing recording is quarantined.")] = 3,
          backoff: Annotated[float, typer.Option(help="Seconds before the first retry (doubles each time).")] = 60.0,
          height: Annotated[Optional[int], typer.Option(help="Default frame height of raw captures.")] = None,
          width: Annotated[Optional[int], typer.Option(help="Default frame width of raw captures.")] = None,
          cfa: Annotated[Optional[str], typer.Option(metavar=CFA_CHOICES, help="CFA of raw captures whose sidecar "
                                                     "names none (default: none, such a capture is refused: "
                                                     "never guessed).")] = None,
          flip: Annotated[bool, typer.Option("--flip", help="Raw captures are upside down by default.")] = False,
          fps: Annotated[float, typer.Option(help="Default spike frames per second of raw captures.")] = 20000.0,
          reset: Annotated[str, typer.Option(help="Default sensor reset of raw captures.")] = "subtract",
          log_file: Annotated[Optional[str], typer.Option(help="Append the log lines to this file instead of "
                                                               "standard error.")] = None,
          workers: Workers = None, scheduler: Scheduler = None):
    """Reconstruct recordings as they land in INBOX, once each, with a ledger in OUTBOX; one timestamped log
    line per event (found, claimed, ingested, reconstructed, exported, done, failed, skipped with -v)."""
    from pipeline.ingest import IngestOptions
    from pipeline.cluster import check_workers
    from pipeline.watch import WatchOptions, parse_interval, watch as run

    options = WatchOptions(method, weights, every, tile, settle, max_attempts, backoff,
                           IngestOptions(height, width, cfa, fps, flip, reset=reset))
    check_workers(workers)
    options.check()  # before OUTBOX is created
    seconds = parse_interval(interval)
    if log_file is not None:
        check_log_file(log_file, inbox, outbox)
        send_logs(context, log_file)
    run(inbox, outbox, options, once=once, interval=seconds, workers=workers, scheduler=scheduler)


def check_log_file(path: str, inbox: str, outbox: str) -> None:
    """A log file the watcher can append to, outside INBOX (else it would be taken as a recording)."""
    from pipeline.storage import check_apart
    from stages.errors import InputError

    if os.path.isdir(path):
        raise InputError(f"--log-file {path} is a folder: give a file to append the log lines to")
    if not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        raise InputError(f"--log-file {path}: its folder does not exist")
    check_apart(path, inbox)


@command()
def status(outbox: Annotated[str, typer.Argument(help="A watcher's OUTBOX.")],
           as_json: Annotated[bool, typer.Option("--json", help="Print one JSON list of the recordings instead of a "
                                                 "table.")] = False):
    """The watcher's ledger: every recording once (its latest state), its attempts, timings and errors."""
    import time

    from pipeline.ledger import Ledger

    rows = Ledger(outbox, read_only=True).recordings()  # refused unless it is a cscsr ledger; never written
    if as_json:  # one JSON document per command, as info --json and the dry runs print
        print(json.dumps([row.__dict__ for row in rows], allow_nan=False))
        return
    table = Table(title=f"{outbox}: {len(rows)} recordings (sources: --json)")
    for column in ("name", "state", "tries", "seconds", "finished", "error / output"):
        table.add_column(column, overflow="fold")
    for r in rows:
        finished = time.strftime("%m-%d %H:%M:%S", time.localtime(r.finished_at)) if r.finished_at else ""
        detail = r.error or (f"{r.output}.zarr" if r.state == "done" else "")
        if r.state == "failed" and not r.final and r.next_try:
            detail += f" (retry after {time.strftime('%H:%M:%S', time.localtime(r.next_try))})"
        table.add_row(r.name, r.state + (" (final)" if r.final else ""), str(r.attempts),
                      f"{r.seconds:.1f}" if r.seconds else "", finished, detail)
    stdout.print(table)


@command()
def demo(out_dir: Annotated[str, typer.Option("--out", help="Folder for the demo's outputs.")] = "demo-output"):
    """The main job on the bundled samples, start to finish, with a results table."""
    from pipeline.demo import run

    run(out_dir, console=stdout)


@command()
def worker(scheduler: Annotated[Optional[str], typer.Argument(
               help="Dask scheduler address (default: DASK_SCHEDULER_ADDRESS, else Dask's scheduler-address "
                    "setting).")] = None,
           memory_limit: Annotated[str, typer.Option(help="Memory of each worker: 4GiB, a fraction of the machine's "
                                                         "(0.5), auto (the machine's, shared), or 0 for no limit.")]
           = "4GiB",
           gpus: Annotated[Optional[int], typer.Option(help="GPUs to serve, one pinned worker each (default: every GPU "
                                                            "torch sees here; 0: one CPU worker).")] = None,
           name: Annotated[Optional[str], typer.Option(help="Worker name; NAME-0, NAME-1, ... for several.")] = None,
           nthreads: Annotated[Optional[int], typer.Option(help="Threads of each worker (default: 4 on a GPU worker, "
                                                                "1 on a CPU worker).")] = None,
           death_timeout: Annotated[Optional[float], typer.Option(help="Seconds to wait for a scheduler before "
                                                                       "closing (default: for ever).")] = None,
           interface: Annotated[Optional[str], typer.Option(help="Network interface to listen on (e.g. ib0).")]
           = None):
    """This machine's Dask workers for a cluster, as `dask cuda worker` starts them: one per GPU, pinned to it
    (CUDA_VISIBLE_DEVICES) and advertising GPU=1, with 4 threads; one 1-thread CPU worker without a GPU. Runs
    until the scheduler closes, or SIGTERM or Ctrl-C."""
    from pipeline.cluster import scheduler_address, serve_workers
    from stages.errors import InputError

    address = scheduler_address(scheduler)
    if not address:
        raise InputError("give the Dask scheduler's address (tcp://HOST:8786), or set DASK_SCHEDULER_ADDRESS")
    serve_workers(address, memory_limit=memory_limit, gpus=gpus, name_prefix=name, nthreads=nthreads,
                  death_timeout=death_timeout, interface=interface)  # refuses bad options and a lost scheduler first


def main() -> None:
    stopping.interrupt_on(signal.SIGTERM)  # this process only: the Python API leaves its caller's signals alone
    stopping.mark_command_line()
    app(prog_name="cscsr")


if __name__ == "__main__":
    sys.exit(main())
