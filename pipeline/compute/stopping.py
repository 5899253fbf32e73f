"""Stopping when asked: SIGTERM (``docker stop``, systemd, Kubernetes, ``kill``) handled as Ctrl-C is.

Python turns SIGINT into ``KeyboardInterrupt`` in the main thread, and every clean-up of this project runs on it
(unfinished outputs removed or left for ``--resume``, claims released, encoders, segment processes and local
clusters stopped, temporary files removed). SIGTERM's default ends the process at once and runs none of it, so
the command line's process and each segment process raise :class:`Terminated`, a ``KeyboardInterrupt``, instead.
"""

import _thread
import contextlib
import logging
import os
import signal
import sys
import threading
import warnings

_handled: set = set()  # the signals interrupt_on handles in this process
COMMAND_LINE = "CSCSR_COMMAND_LINE"  # set by the command line for the processes it starts: they belong to a command


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C raises ``KeyboardInterrupt``."""


def interrupt_on(*signals: signal.Signals) -> None:
    """Make the first of ``signals`` to arrive raise in the main thread (:class:`Terminated` for SIGTERM,
    ``KeyboardInterrupt`` for SIGINT) and ignore the ones after it, so that the clean-up it starts finishes (SIGKILL
    still ends the process at once). Python's own handler, not ``SIG_IGN``: processes started after it (workers,
    encoders) begin with the signals' defaults. Call it from the main thread."""
    received, redelivered = [], []

    def stop(signum, frame) -> None:
        if received:
            return
        received.append(signum)
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    earlier_hook = sys.unraisablehook

    def lost_in_a_finalizer(unraisable) -> None:
        """The interrupt was raised inside a finalizer (``__del__``: asyncio's ``Future``, CI 2026-11-27), where
        Python prints and drops it, and the job went on to finish: deliver it again to the main thread, from a
        timer's thread, once the finalizer is over (again if it lands in another, a few times at most)."""
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and received and len(redelivered) < 5:
            redelivered.append(received.pop())
            again = threading.Timer(0.05, _thread.interrupt_main, args=(redelivered[-1],))
            again.daemon = True
            again.start()
            return
        earlier_hook(unraisable)

    for signum in signals:
        signal.signal(signum, stop)
        _handled.add(signum)
    sys.unraisablehook = lost_in_a_finalizer
    logging.getLogger("tornado.application").addFilter(_cancel_before_start)


def _cancel_before_start(record: logging.LogRecord) -> bool:
    """Drop Dask's own error when an interrupt cuts a call into the client short before the call began: its clean-up
    (``distributed.utils.sync``'s ``cancel``) reads a future not yet assigned, and Tornado logs the ``NameError``
    with a traceback on the event loop's thread, before the command's one line (CI 2026-11-29, a SIGTERM'd
    simulate). Nothing was started, so nothing is left to cancel; every other error is kept."""
    error = record.exc_info[1] if record.exc_info else None
    return not (isinstance(error, NameError) and "'future'" in str(error)
                and "sync.<locals>.cancel" in record.getMessage())


@contextlib.contextmanager
def interrupts_deferred():
    """Hold a SIGTERM or Ctrl-C that arrives inside the block until the block ends, then raise it as
    :func:`interrupt_on`'s handler would: for a write that must not be cut in two (a frame piped to ffmpeg, which,
    handed half a frame as its input closes, prints "Invalid buffer size" after the command's one line). Only where
    :func:`interrupt_on` set up the signal, from the main thread; elsewhere nothing changes."""
    held = [signum for signum in _handled if threading.current_thread() is threading.main_thread()
            and callable(signal.getsignal(signum))]
    if not held:
        yield
        return
    handlers, arrived = {signum: signal.getsignal(signum) for signum in held}, []
    for signum in held:
        signal.signal(signum, lambda signum, frame: arrived.append((signum, frame)))
    try:
        yield
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        if arrived:
            signum, frame = arrived[0]
            handlers[signum](signum, frame)


def quiet_finalizers() -> None:
    """After an interrupt, in a process that :func:`interrupt_on` set up (the command line's, a segment's: it is about
    to exit), drop the errors of finalizers: an object whose construction the interrupt cut short can fail in its
    ``__del__`` (imageio's ``PillowPlugin``: ``AttributeError``), which Python prints as "Exception ignored in ..."
    with a traceback after the command's one line. Elsewhere (the Python API, tests) nothing changes."""
    if _handled:
        sys.unraisablehook = lambda unraisable: None
        # a read the interrupt cut short leaves zarr's coroutine unstarted, which Python reports at exit as "sys:1:
        # RuntimeWarning: coroutine 'AsyncArray._get_selection' was never awaited" (CI 2026-11-30, a SIGTERM'd export)
        warnings.filterwarnings("ignore", message="coroutine .* was never awaited", category=RuntimeWarning)


def mark_command_line() -> None:
    """Mark this process (the command line's) and every process it starts as belonging to a command."""
    os.environ[COMMAND_LINE] = "1"


def ignore_ctrl_c_while_spawned() -> None:
    """In a process that ``multiprocessing`` spawns for a command (a local cluster's worker, a segment, the server
    that forks workers, whose forks keep this handler), ignore SIGINT
    from its first import of this module on: the terminal's Ctrl-C reaches every process of the job, and a worker
    still importing printed a ``KeyboardInterrupt`` traceback of its own (dozens of lines when a job is stopped as its
    cluster starts), while the command closes its cluster, and with it the worker, anyway. A segment process handles
    SIGINT again once it runs (:func:`interrupt_on`). Python's own handler, not ``SIG_IGN``, so that processes started
    after it begin with the default. Elsewhere (the Python API, its own processes, tests) nothing changes."""
    command = getattr(sys, "orig_argv", ())
    spawned = "--multiprocessing-fork" in command or any("multiprocessing.forkserver" in part for part in command)
    if spawned and os.environ.get(COMMAND_LINE) and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, lambda signum, frame: None)


def start_resource_tracker() -> None:
    """Start ``multiprocessing``'s resource tracker of this process now, deaf to Ctrl-C from its first instruction, so
    that the processes this one spawns (a local cluster's workers) share it rather than each start one of their own,
    which Ctrl-C, reaching every process of the job, could stop while it starts (a ``KeyboardInterrupt`` traceback,
    and semaphores left unaccounted for: "leaked semaphore objects"). Ctrl-C is ignored here only while the tracker
    process is created (a few milliseconds); outside the main thread, or when a tracker runs already, it only makes
    sure one runs."""
    from multiprocessing import resource_tracker

    if threading.current_thread() is not threading.main_thread():
        resource_tracker.ensure_running()
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        resource_tracker.ensure_running()
    finally:
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)  # None: set from C, not Python


ignore_ctrl_c_while_spawned()  # at import: pipeline.cli imports this module first, before anything slow to import


def purge_stale_worker_folders() -> None:
    """Remove what the local cluster's workers left in Dask's scratch space when their nanny had to kill them (a
    task still running when the job was stopped: SIGTERM, Ctrl-C): their ``worker-*.dirlock`` files, which Dask
    itself purges only when a worker next starts there. Dask's own purge: it takes only locks no live process holds."""
    import tempfile

    import dask
    from distributed.diskutils import WorkSpace

    base = dask.config.get("temporary-directory", default=None) or tempfile.gettempdir()
    with contextlib.suppress(Exception):  # best effort, never the job's error
        WorkSpace(os.path.join(base, "dask-scratch-space"))._purge_leftovers()
