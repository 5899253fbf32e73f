"""Running a job's tasks on Dask; what the tasks are is the job's plan, frozen data made elsewhere.

- **A bounded window.** At most a few tasks per worker are in flight (``in_bounded_window``, ``submitted``): a
  recording of millions of frames never becomes one graph of millions of tasks; tasks are made as the window moves.
- **Nothing a lost worker takes with it.** Everything a task needs travels in the task itself, never as scattered
  data: a task whose worker dies, even the cluster's only worker, is rerun by Dask on whichever worker is there or
  joins later. A task the cluster drops is submitted again (``idempotent`` tasks), and a failure says whether it was
  the task's own error or a cluster fault (``failure``). ``submitted`` yields each task with its finished future.
- **Segments.** A job that starts its own local cluster and has more than ``size`` tasks runs them ``size`` at a
  time, each segment in a child process that starts the cluster, runs them, streams their outcomes back over a queue
  and exits, dying with its parent (``in_segments``): Dask keeps a little memory per task for good in every process
  that touches it (docs/reliability.md, "Why segments"). A job of one segment runs it in its own process.
- **A graph in rounds.** ``computed`` runs the tasks a graph writes (spike stores', ``to_video``'s) a bounded
  number a round, on a client or on Dask's own scheduler, what later rounds read carried over.
"""

import contextlib
import ctypes
import itertools
import logging
import multiprocessing
import os
import queue
import signal
import sys
import weakref
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

import dask
import dask.threaded
from dask.base import get_scheduler
from dask.callbacks import Callback
from dask.core import get_deps
from dask.highlevelgraph import HighLevelGraph
from distributed import Future, as_completed
from distributed.scheduler import KilledWorker

from pipeline.compute.stopping import interrupt_on, quiet_finalizers
from stages.errors import InputError, describe

T = TypeVar("T")
log = logging.getLogger("cscsr.executor")


def submitted(client, tasks: Iterable[T], submit: Callable[[T], Future], *,
              idempotent: bool = False) -> Iterator[tuple[T, Future]]:
    """``submit(task)`` for each task of a plan, a bounded window at a time; yield (task, future) as
    each finishes (its result or error is the caller's to read: :func:`failure`).

    A task whose worker dies is rerun by Dask itself (its inputs travel in the task, never as scattered
    data, which a lost worker takes with it). ``idempotent`` tasks (whole chunks written, the same bytes
    each time) are also submitted again when the cluster drops them (a future cancelled under the job,
    e.g. by a scheduler restart), up to :data:`ATTEMPTS` submissions in all. A task that finished but
    whose result was lost with its worker before it was read here is waited for again (Dask reruns it)."""
    task_of, attempt_of = {}, {}  # future key -> task, -> how many times it was submitted

    def start(task: T, attempt: int) -> Future:
        future = submit(task)
        task_of[future.key], attempt_of[future.key] = task, attempt
        return future

    def again(future: Future) -> Future | None:
        if still_computing(future):
            return future
        if (not idempotent or future.status != "cancelled" or attempt_of[future.key] >= ATTEMPTS
                or client.status != "running"):
            return None
        return start(task_of.pop(future.key), attempt_of.pop(future.key) + 1)

    futures = (start(task, 1) for task in tasks)
    for future in in_bounded_window(futures, window_size(client), again=again):
        attempt_of.pop(future.key)
        yield task_of.pop(future.key), future


@contextlib.contextmanager
def released(futures: Iterable[Future]) -> Iterator[None]:
    """Release ``futures`` on leaving, whatever happens: an error's traceback holds them, and the cluster kept their
    erred keys for the client's life, giving every later computation of those keys (a resume, once the cause is
    fixed) the stale error."""
    try:
        yield
    finally:
        for future in futures:
            future.release()


def result_of(client, function: Callable, args: tuple, key: str):
    """``function(*args)`` computed on ``client`` under ``key``, its future :func:`released`."""
    future = client.submit(function, *args, key=key)
    with released([future]):
        return future.result()


def still_computing(future: Future) -> Future | None:
    """``future`` if it finished but its result died with a worker before it was read (Dask is computing it again:
    wait for that), else None: an ``again`` for :func:`in_bounded_window`."""
    return future if future.status in ("lost", "pending") else None


ATTEMPTS = 3  # submissions of an idempotent task the cluster keeps dropping, before it is reported failed


def failure(future: Future) -> str | None:
    """Why a finished future has no result, in one line: the task's own error, or what the cluster did
    to it (a task run on workers that all died, a task the cluster dropped); None if it has one."""
    if future.status == "finished":
        return None
    if future.status == "error":
        error = future.exception()
        if isinstance(error, KilledWorker):  # a cluster fault, not the task's: say so
            return (f"cluster fault: every worker that ran this task died (KilledWorker; Dask gives up after "
                    f"distributed.scheduler.allowed-failures deaths): {describe(error)}")
        return describe(error)
    return (f"cluster fault: the task was {future.status} by the cluster (workers lost or the scheduler "
            f"restarted) and not finished")


def in_bounded_window(futures: Iterator[Future], limit: int, *,
                      again: Callable[[Future], Future | None] = lambda future: None) -> Iterator[Future]:
    """Pull futures from ``futures`` (which submits as it is pulled); yield each once finished, unless
    ``again(future)`` gives a future to wait for instead (a resubmission)."""
    done = as_completed()

    def next_finished() -> Future:
        while True:
            future = next(done)
            if (replacement := again(future)) is None:
                return future
            done.add(replacement)

    in_flight = 0
    for future in futures:
        done.add(future)
        in_flight += 1
        while in_flight >= limit:
            yield next_finished()
            in_flight -= 1
    for _ in range(in_flight):
        yield next_finished()


def window_size(client) -> int:
    """A few tasks per worker: enough to keep every worker busy, few enough to stay small."""
    return 4 * max(1, len(client.scheduler_info()["workers"])) + 4


_END, _FAILED, _OUTCOME = "end", "failed", "outcome"


def in_segments(run: Callable[..., Iterator[T]], items: Iterable, size: int, *, workers: int | None,
                show_dashboard: bool, preload: tuple[str, ...] = ()) -> Iterator[T]:
    """``run(client, segment)`` for each ``size`` items in turn, each in its own process on its own local
    cluster of ``workers``, forked from a server that imported ``preload`` (``cluster.dask_client``; items are
    drawn one segment at a time; ``run`` must pickle); items that fit in one segment run in this process, on a
    local cluster of its own (module docstring). The first segment
    prints the dashboard link if ``show_dashboard``, unless ``cscsr --quiet``; with ``cscsr --verbose`` each
    segment's cluster lets Dask's own warnings through, as a cluster in this process would."""
    from pipeline.compute.progress import is_quiet

    context = multiprocessing.get_context("spawn")  # a fresh interpreter: nothing carried over
    show_dashboard = show_dashboard and not is_quiet()
    verbose = log.isEnabledFor(logging.DEBUG)  # a spawned child starts with logging unset: it is told
    cluster = f"local cluster ({workers} workers)" if workers is not None else "local cluster (a worker per core)"
    items = iter(items)
    first = list(itertools.islice(items, size))
    beyond = list(itertools.islice(items, 1))
    if not beyond:  # one segment (or none)
        if first:
            log.debug("segment 0: %d tasks, the job's only one: in this process on a %s of its own", len(first),
                      cluster)
            yield from _on_a_local_cluster(run, first, workers, show_dashboard, preload)
        return
    items = itertools.chain(first, beyond, items)
    for number in itertools.count():
        segment = list(itertools.islice(items, size))
        if not segment:
            return
        log.debug("segment %d: %d tasks, in a process of its own on a fresh %s", number, len(segment), cluster)
        messages = context.Queue()
        child = context.Process(target=_segment, name=f"cscsr-segment-{number}",
                                args=(run, segment, workers, show_dashboard and number == 0, messages, verbose,
                                      preload, os.getpid()))
        child.start()
        try:
            yield from _relay(messages, child)
        except BaseException:  # the job stops early (an error, Ctrl-C, SIGTERM, its caller stops reading)
            _stop(child)
            raise
        child.join()  # its outcomes are all in: it is exiting on its own


SEGMENT_STOP_SECONDS = 15  # for a segment asked to stop to close its cluster (workers, their folders)


def _stop(child) -> None:
    """Stop the segment process of a job that stops early: SIGTERM, on which it closes its cluster, then SIGKILL if it
    has not ended within :data:`SEGMENT_STOP_SECONDS`."""
    if child.is_alive():
        child.terminate()
        child.join(SEGMENT_STOP_SECONDS)
        if child.is_alive():
            log.warning("the segment process %s did not stop within %d s of SIGTERM: killed", child.name,
                        SEGMENT_STOP_SECONDS)
            child.kill()
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


def _on_a_local_cluster(run, items: list, workers: int | None, show_dashboard: bool,
                        preload: tuple[str, ...] = ()) -> Iterator:
    """A segment in the process that calls: ``run(client, items)`` on a local cluster of ``workers`` started for it,
    its workers forked from a server that imported ``preload`` (and the dashboard link, if ``show_dashboard``)."""
    from pipeline.compute.cluster import dask_client

    with dask_client(workers=workers, preload=preload) as client:
        if show_dashboard:
            show_dashboard_once(client)
        yield from run(client, items)


_DASHBOARDS_SHOWN: "weakref.WeakSet" = weakref.WeakSet()  # the clients whose dashboard link is printed already


def dashboard_link(client) -> str | None:
    """The dashboard URL when the scheduler serves one (it needs bokeh; ``dask scheduler --no-dashboard`` still
    lists the service, its HTTP server answering 404 there). Asked of its root, which redirects to the dashboard
    without drawing it (a few milliseconds; its page itself takes a quarter of a second, at every job's start),
    ``DASHBOARD_TIMEOUT`` at most; one that does not answer from here is shown all the same, a browser elsewhere
    may reach it."""
    import http.client
    import urllib.parse

    with contextlib.suppress(Exception):
        if "dashboard" not in client.scheduler_info().get("services", {}):
            return None
        link = client.dashboard_link
        where = urllib.parse.urlsplit(link)
        try:
            connection = http.client.HTTPConnection(where.hostname, where.port, timeout=DASHBOARD_TIMEOUT)
            try:
                connection.request("GET", "/")
                served = connection.getresponse().status != 404
            finally:
                connection.close()
        except OSError:
            served = True
        return link if served else None
    return None


DASHBOARD_TIMEOUT = 2.0  # seconds the dashboard's page has to answer before its link is shown unchecked


def show_dashboard_once(client) -> None:
    """Print ``client``'s dashboard link on standard error (never mixed with results on stdout), once per client:
    jobs that share a client (the demo's, evaluate's methods) do not repeat it."""
    if client not in _DASHBOARDS_SHOWN:
        _DASHBOARDS_SHOWN.add(client)
        if link := dashboard_link(client):
            print(f"dashboard: {link}", file=sys.stderr)


def _segment(run, items, workers, show_dashboard, messages, verbose=False, preload=(), parent=None) -> None:
    """Child: start a cluster, run the segment, send each outcome, exit (and all its memory with it). Stopped
    (SIGTERM from its job, Ctrl-C at the terminal), it closes its cluster on the way out and says nothing: the job
    reports. A job gone before it started (``parent``, its process id) is not outlived."""
    _die_with_parent(parent)
    interrupt_on(signal.SIGTERM, signal.SIGINT)
    if verbose:  # what the cluster's log level is chosen by (cluster._dask_log_level)
        logging.getLogger("cscsr").setLevel(logging.DEBUG)

    try:
        try:
            for outcome in _on_a_local_cluster(run, items, workers, show_dashboard, preload):
                messages.put((_OUTCOME, outcome))
            messages.put((_END,))
        except Exception as error:  # reported by the parent, which owns the user's terminal and exit code
            messages.put((_FAILED, type(error).__name__, describe(error)))
        messages.close()
        messages.join_thread()
    except KeyboardInterrupt:  # the job stopped: it reads no more outcomes, so none is waited on to be sent
        quiet_finalizers()
        messages.cancel_join_thread()


def _die_with_parent(parent: int | None = None) -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no-op elsewhere); exit at once if the parent,
    process ``parent``, is already gone: a job killed while its segment's interpreter was still starting (seconds on
    a loaded machine) left it writing OUT with no claim held, a resume beside it."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if parent is not None and os.getppid() != parent:  # asked after the request: no death falls between the two
        os._exit(1)


# ---- a graph in bounded rounds (the spike stores' writes, to_video's rounds) ----

def computed(graph, frames: dict, advance, client, at_once: int | None = None, failed=None) -> list:
    """The results of the tasks ``frames`` names (key -> what it writes) of ``graph``, in that order, computed on
    ``client`` (else dask's own scheduler), ``advance(frames[key])`` as each finishes; the first error raised, but on
    a client with ``failed``: ``failed(frames[key], why)`` and the others go on (results of those that finished). The
    graph is handed over culled to what they need (a resume's tasks), its tasks' names kept (nothing fused);
    ``at_once``: that many of them a round, what a round made that later rounds need (a chain's state, the sensor's
    draws, a video's pair, windows) kept for them, so that memory and the scheduler's graph stay bounded; what a
    scheduler's restart cancelled of it is made again."""
    keys = list(frames)
    if isinstance(graph, HighLevelGraph):
        graph = dict(graph.cull(set(keys)))
    dependencies, dependents = get_deps(graph)
    results, held = [], {}  # held: what earlier rounds made that later ones need (futures on a client, else values)
    try:
        for round_keys, round_graph, earlier, kept, needed_later in _rounds(graph, keys, at_once or len(keys) or 1,
                                                                            dependencies, dependents):
            again = _made_again(dependencies, earlier, held) if client is not None else set()
            reads = earlier | {dep for key in again for dep in dependencies[key]}
            round_graph = round_graph | {key: graph[key] for key in again} | {key: held[key] for key in reads - again}
            if client is not None:
                renewed = kept + [key for key in again if key in held]  # held anew (the cancelled ones released)
                futures = client.get(round_graph, round_keys + renewed, sync=False)
                for key, future in zip(renewed, futures[len(round_keys):]):  # released below, whatever happens
                    if key in held:
                        held[key].release()
                    held[key] = future
                ours = futures[:len(round_keys)]
                with released(ours):  # forgotten by the cluster even while an error holds them: a resume computes
                    for future in in_bounded_window(iter(ours), len(ours), again=still_computing):  # afresh
                        if future.status == "finished":
                            advance(frames[future.key])
                        elif failed is not None:
                            failed(frames[future.key], failure(future))
                    results += client.gather(ours, errors="skip" if failed else "raise")
            else:
                class Advance(Callback):  # dask's local schedulers call it as each task finishes, from their loop
                    def _posttask(self, key, result, dsk, state, worker_id):
                        if key in frames:
                            advance(frames[key])

                with Advance():  # dask's configured scheduler, else its default for arrays and delayed: threads
                    values = (get_scheduler() or dask.threaded.get)(round_graph, round_keys + kept)
                results += values[:len(round_keys)]
                held |= dict(zip(kept, values[len(round_keys):]))
            for key in [key for key in held if key not in needed_later]:
                value = held.pop(key)
                if client is not None:
                    value.release()
    finally:
        if client is not None:
            for future in held.values():
                future.release()
    return results


def _made_again(dependencies: dict, earlier: set, held: dict) -> set:
    """The keys to make again so that a round can read ``earlier``: those whose ``held`` futures a scheduler's restart
    cancelled, and what they need that is not held (any more)."""
    again, stack = set(), [key for key in earlier if held[key].status == "cancelled"]
    while stack:
        if (key := stack.pop()) not in again:
            again.add(key)
            stack.extend(dep for dep in dependencies[key] if dep not in held or held[dep].status == "cancelled")
    return again


def _rounds(graph: dict, keys: list, at_once: int, dependencies: dict, dependents: dict):
    """``keys`` of ``graph`` ``at_once`` a round, in order: per round its keys, its graph (what they need that no
    earlier round made), the keys of earlier rounds it reads, the keys it makes that a later round reads, and every
    key made so far that a later round reads."""
    unread = {key: len(readers) for key, readers in dependents.items()}  # readers not yet made
    made, open_keys = set(), set()
    for start in range(0, len(keys), at_once):
        round_keys = keys[start:start + at_once]
        needed, stack = set(), list(round_keys)
        while stack:
            if (key := stack.pop()) not in needed and key not in made:
                needed.add(key)
                stack.extend(dependencies[key])
        earlier = {dep for key in needed for dep in dependencies[key]} - needed
        made |= needed
        for key in needed:
            for dep in dependencies[key]:
                unread[dep] -= 1
        open_keys = {key for key in open_keys | needed if unread[key]}
        yield round_keys, {key: graph[key] for key in needed}, earlier, sorted(open_keys & needed, key=str), \
            set(open_keys)
