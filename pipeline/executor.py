"""Running a job's tasks on Dask; what the tasks are is the job's plan, frozen data made elsewhere.

- **A bounded window.** At most a few tasks per worker are in flight (``in_bounded_window``,
  ``submitted``): a recording of millions of frames never becomes one graph of millions of
  tasks, and tasks are made from the plan only as the window moves.
- **Outcomes as they happen.** ``submitted`` yields each task of the plan with its finished future,
  in the order they finish, for the job to count (progress bars) or to report.
- **Segments.** A job that starts its own local cluster runs its tasks ``size`` at a time in a
  child process that starts the cluster (scheduler and workers), runs them, and exits
  (``in_segments``); the parent keeps only the plan, the progress bar and the lease. Dask keeps
  a little memory per task for good in every process that touches it (measured: ~0.5 KiB per
  task in the client and scheduler, ~0.2-1 KiB in a worker; part of it is
  ``dask.utils.key_split``'s cache of every task key, the rest we could not attribute; it is not
  released by ``malloc_trim`` or by closing the cluster): a million-task job would carry hundreds
  of MB of it. Outcomes stream back over a queue as they happen, so progress and failure reports
  are as live as in one process. The child dies with its parent (``PR_SET_PDEATHSIG``), so a
  killed job leaves no segment writing behind it, and ``--resume`` finds the output as the last
  committed task left it.
"""

import ctypes
import itertools
import multiprocessing
import queue
import signal
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

from distributed import Future, as_completed

from stages.errors import InputError, describe

T = TypeVar("T")


def submitted(client, tasks: Iterable[T], submit: Callable[[T], Future]) -> Iterator[tuple[T, Future]]:
    """``submit(task)`` for each task of a plan, a bounded window at a time; yield (task, future) as
    each finishes (its result or error is the caller's to read)."""
    task_of = {}  # future key -> task

    def futures():
        for task in tasks:
            future = submit(task)
            task_of[future.key] = task
            yield future

    for future in in_bounded_window(futures(), window_size(client)):
        yield task_of.pop(future.key), future


def in_bounded_window(futures: Iterator[Future], limit: int) -> Iterator[Future]:
    """Pull futures from ``futures`` (which submits as it is pulled); yield each once finished."""
    done = as_completed()
    in_flight = 0
    for future in futures:
        done.add(future)
        in_flight += 1
        while in_flight >= limit:
            yield next(done)
            in_flight -= 1
    yield from done


def window_size(client) -> int:
    """A few tasks per worker: enough to keep every worker busy, few enough to stay small."""
    return 4 * max(1, len(client.scheduler_info()["workers"])) + 4


_END, _FAILED, _OUTCOME = "end", "failed", "outcome"


def in_segments(run: Callable[..., Iterator[T]], items: Iterable, size: int, *, workers: int | None,
                show_dashboard: bool) -> Iterator[T]:
    """``run(client, segment)`` for each ``size`` items in turn, each in its own process on its own local
    cluster of ``workers`` (items are drawn one segment at a time; ``run`` must pickle)."""
    context = multiprocessing.get_context("spawn")  # a fresh interpreter: nothing carried over
    items = iter(items)
    for number in itertools.count():
        segment = list(itertools.islice(items, size))
        if not segment:
            return
        messages = context.Queue()
        child = context.Process(target=_segment, name=f"cscsr-segment-{number}",
                                args=(run, segment, workers, show_dashboard and number == 0, messages))
        child.start()
        try:
            yield from _relay(messages, child)
        finally:
            if child.is_alive():  # the parent stops early (an error, Ctrl-C): the segment stops too
                child.terminate()
            child.join()


def _relay(messages, child) -> Iterator:
    while True:
        try:
            message = messages.get(timeout=1.0)
        except queue.Empty:
            if child.is_alive():
                continue
            try:  # it may have finished between the two checks
                message = messages.get(timeout=1.0)
            except queue.Empty:
                raise RuntimeError(f"the segment process stopped (exit code {child.exitcode}) without finishing: "
                                   "its committed tasks are kept; run again with --resume") from None
        if message[0] == _END:
            return
        if message[0] == _FAILED:
            kind, text = message[1], message[2]
            raise (InputError if kind == "InputError" else RuntimeError)(text)
        yield message[1]


def _segment(run, items, workers, show_dashboard, messages) -> None:
    """Child: start a cluster, run the segment, send each outcome, exit (and all its memory with it)."""
    _die_with_parent()
    from pipeline.cluster import dashboard_link, dask_client

    try:
        with dask_client(workers=workers) as client:
            if show_dashboard and (link := dashboard_link(client)):
                print(f"dashboard: {link}", file=sys.stderr)
            for outcome in run(client, items):
                messages.put((_OUTCOME, outcome))
        messages.put((_END,))
    except Exception as error:  # reported by the parent, which owns the user's terminal and exit code
        messages.put((_FAILED, type(error).__name__, describe(error)))
    finally:
        messages.close()
        messages.join_thread()


def _die_with_parent() -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no-op elsewhere)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
