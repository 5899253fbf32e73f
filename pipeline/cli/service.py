"""Commands that serve: the inbox watcher and its status, the demo, a Dask worker."""

import json
import os
from typing import Annotated, Optional

import typer

from rich.table import Table

from stages.reconstruction.methods import WINDOW
from pipeline.cli.core import CFA_CHOICES, METHOD_CHOICES, Scheduler, Workers, command, send_logs, stdout


DEFAULT_INTERVAL = "10m"  # between a watcher's passes


@command()
def watch(context: typer.Context,
          inbox: Annotated[str, typer.Argument(help="Where recordings land (any URL).")],
          outbox: Annotated[str, typer.Argument(help="Local folder for outputs and the ledger.")],
          interval: Annotated[Optional[str], typer.Option(help="Time between passes: 30s, 10m, 1h, at most 168h "
                                                           "(default: 10m).")] = None,
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
    from pipeline.jobs.ingest import IngestOptions
    from pipeline.compute.cluster import check_workers
    from pipeline.inbox.watch import WatchOptions, parse_interval, watch as run

    options = WatchOptions(method, weights, every, tile, settle, max_attempts, backoff,
                           IngestOptions(height, width, cfa, fps, flip, reset=reset))
    check_workers(workers, scheduler)
    options.check()  # before OUTBOX is created
    if once and interval is not None:
        from stages.errors import InputError

        raise InputError(f"--once and --interval {interval} contradict each other: --once makes one pass, --interval "
                         f"passes again and again: give one")
    seconds = parse_interval(interval or DEFAULT_INTERVAL)
    if log_file is not None:
        check_log_file(log_file, inbox, outbox)
        send_logs(context, log_file)
    run(inbox, outbox, options, once=once, interval=seconds, workers=workers, scheduler=scheduler)


def check_log_file(path: str, inbox: str, outbox: str) -> None:
    """A log file the watcher can append to, outside INBOX (else it would be taken as a recording)."""
    from pipeline.stores.storage import check_apart
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

    from pipeline.inbox.ledger import Ledger

    rows = Ledger(outbox, read_only=True).recordings()  # refused unless it is a cscsr ledger; never written
    if as_json:  # one JSON document per command, as info --json and the dry runs print; params an object, in it
        print(json.dumps([{**row.__dict__, "params": json.loads(row.params), "final": bool(row.final)}
                          for row in rows], allow_nan=False))
        return
    table = Table(title=f"{outbox}: {len(rows)} recordings (sources: --json)")
    for column in ("name", "state", "tries", "seconds", "finished", "error / output"):
        table.add_column(column, overflow="fold")
    for r in rows:
        finished = time.strftime("%m-%d %H:%M:%S", time.localtime(r.finished_at)) if r.finished_at else ""
        detail = r.error or (f"{r.output}.zarr" if r.state == "done" else "")
        if r.state == "duplicate":  # the same bytes and parameters as the recording named r.output
            detail = f"same bytes as {r.output}: {r.output}.zarr (see its line)"
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
    from pipeline.compute.cluster import scheduler_address, serve_workers
    from stages.errors import InputError

    address = scheduler_address(scheduler)
    if not address:
        raise InputError("give the Dask scheduler's address (tcp://HOST:8786), or set DASK_SCHEDULER_ADDRESS")
    serve_workers(address, memory_limit=memory_limit, gpus=gpus, name_prefix=name, nthreads=nthreads,
                  death_timeout=death_timeout, interface=interface)  # refuses bad options and a lost scheduler first
