"""Where Dask work runs: an in-process ``LocalCluster`` (the default) or an existing scheduler.

Workers are processes with one task thread each; the numerical libraries inside a task
(numba, OpenCV, torch) get ``cores // workers`` threads so that a 2-core laptop with two
workers is not oversubscribed. An address comes from ``--scheduler`` or
``DASK_SCHEDULER_ADDRESS`` or Dask's ``scheduler-address`` setting; an unreachable one is a one-line error within seconds.
Workers started with ``--resources GPU=1`` are GPU workers (:func:`gpu_workers`).

A local cluster listens on loopback only: its scheduler, workers and dashboard (the dashboard
shows task names and file paths, and can run profiling). ``CSCSR_DASHBOARD=HOST:PORT`` (e.g.
``0.0.0.0:8787``) serves the dashboard elsewhere, for a user who asks for it.
"""

import asyncio
import contextlib
import errno
import logging
import os
import threading
from collections.abc import Iterator

import dask
from distributed import Client, LocalCluster, WorkerPlugin

from stages.errors import InputError, describe
from stages.numbers import check_number

CONNECT_TIMEOUT = "5s"
WORKERS_PER_CORE, MOST_WORKERS = 4, 256  # --workers at most 4 per core and 256 in all: beyond that a local
# cluster only multiplies processes (~100 MiB each) and start-up time, with no core left to run them
GPU = "GPU"  # the Dask worker resource a GPU worker advertises; network tasks ask for one
LOOPBACK = "127.0.0.1"
DASHBOARD_VARIABLE = "CSCSR_DASHBOARD"  # HOST:PORT of a local cluster's dashboard; default loopback, any free port


# Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which pins glibc's mmap
# threshold at 128 KiB: every large temporary array (an HR frame is tens of MB) is then a
# fresh mmap with page faults on every touch, 1.44x the time of a reconstruction task.
# Fixed thresholds of 64 MiB keep such arrays on the reused heap. glibc reads them only at
# process start, so they go in the nanny's pre-spawn environment, not in ``env``.
_PRE_SPAWN = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": str(256 * 2**20),
              "distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": str(64 * 2**20)}


def _thread_env(workers: int) -> dict:
    threads = str(max(1, (os.cpu_count() or 1) // workers))
    return {name: threads for name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def most_workers() -> int:
    """The most local worker processes ``--workers`` may ask for on this machine."""
    return min(MOST_WORKERS, WORKERS_PER_CORE * (os.cpu_count() or 1))


def check_workers(workers: int | None) -> None:
    """Refuse a ``--workers`` outside 1..:func:`most_workers` (None: one per core); every command
    that takes ``--workers`` calls this before it creates any output."""
    if workers is not None:
        check_number("--workers", workers, at_least=1, at_most=most_workers(), integer=True,
                     why=f"at most {WORKERS_PER_CORE} per core and {MOST_WORKERS} in all")


def scheduler_address(scheduler: str | None) -> str | None:
    """The scheduler to use, as Dask users expect: ``--scheduler`` (or ``scheduler=``), else
    ``DASK_SCHEDULER_ADDRESS`` (read now, not only when Dask was imported), else ``scheduler-address`` in
    Dask's configuration (a YAML file in ``~/.config/dask/`` or ``DASK_CONFIG``, or ``dask.config.set``).
    None means a local cluster of our own."""
    return scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS") or dask.config.get("scheduler-address", None)


def check_scheduler(scheduler: str | None) -> None:
    """Refuse, in one line naming the address and within :data:`CONNECT_TIMEOUT` (plus a second), a named
    scheduler (``--scheduler``, ``DASK_SCHEDULER_ADDRESS``, Dask's ``scheduler-address``) that cannot be
    reached or does not answer as a Dask scheduler; nothing when no scheduler is named (a local cluster).

    Distributed retries a refused connection until its timeout, but then waits without limit for the
    handshake: a port that accepts connections and never answers (a stopped process, a firewall, a
    forwarded port with nothing behind it) hangs ``Client()`` for ever. This opens one connection with
    the whole handshake under a deadline, in a thread of its own (the caller may be inside an event
    loop), and closes it. Commands call it before they create any output; :func:`dask_client` too."""
    address = scheduler_address(scheduler)
    if not address:
        return
    seconds = float(dask.utils.parse_timedelta(CONNECT_TIMEOUT, "s"))
    outcome: dict[str, BaseException] = {}

    def handshake() -> None:
        from distributed.comm import connect
        from distributed.security import Security

        async def opened() -> None:
            comm = await connect(address, timeout=seconds, **Security().get_connection_args("client"))
            await comm.close()

        try:
            asyncio.run(asyncio.wait_for(opened(), seconds + 1))  # connect() itself gives up on a refusal
        except BaseException as error:  # noqa: BLE001 - handed to the caller's thread
            outcome["error"] = error

    thread = threading.Thread(target=handshake, name="cscsr-scheduler-check", daemon=True)
    thread.start()
    thread.join(seconds + 5)
    error = outcome.get("error")
    if thread.is_alive() or isinstance(error, (TimeoutError, asyncio.TimeoutError)):
        raise InputError(f"cannot reach Dask scheduler {address}: no answer within {seconds:g} s (something "
                         "accepts connections there but does not answer as a Dask scheduler)")
    if isinstance(error, OSError):
        raise InputError(f"cannot reach Dask scheduler {address}: {describe(error)}")
    if isinstance(error, (ValueError, TypeError)) and "address" in str(error).lower():  # no such scheme, no port
        raise InputError(f"cannot use Dask scheduler address {address!r}: {describe(error)}")
    if error is not None:  # an answer, but not Dask's protocol (a web server, say): undecodable frames
        raise InputError(f"cannot reach Dask scheduler {address}: what answers there does not speak Dask's "
                         f"protocol ({type(error).__name__})")


@contextlib.contextmanager
def dask_client(*, workers: int | None = None, scheduler: str | None = None) -> Iterator[Client]:
    """A connected client; a local cluster of ``workers`` processes unless a scheduler is named."""
    address = scheduler_address(scheduler)
    if address:
        check_scheduler(address)  # a port that accepts and never answers would hang Client() for ever
        try:
            client = Client(address, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as error:
            raise InputError(f"cannot reach Dask scheduler {address}: {describe(error)}") from None
        with client:
            yield client
        return
    check_workers(workers)
    workers = workers if workers is not None else os.cpu_count() or 1
    with dask.config.set(_PRE_SPAWN), \
            LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host=LOOPBACK,
                         dashboard_address=os.environ.get(DASHBOARD_VARIABLE) or f"{LOOPBACK}:0",
                         silence_logs=_dask_log_level(), env=_thread_env(workers)) as cluster, Client(cluster) as client:
        client.register_plugin(_QuietWorkerLogs())  # our own workers only: a shared cluster's logs are its owner's
        yield client


def _dask_log_level() -> int:
    """Dask's own log records shown by a local cluster: errors only, and warnings too when our logger is at
    DEBUG (``cscsr --verbose``)."""
    return logging.WARNING if logging.getLogger("cscsr").isEnabledFor(logging.DEBUG) else logging.ERROR


class QuietExpectedErrors(logging.Filter):
    """Drops a worker's ``Compute Failed`` record (a traceback per task) for a task that raised our own
    :class:`InputError` (a lost or damaged chunk, bad data), or ran out of space for its output (``OSError``
    ENOSPC, or EDQUOT: a full quota; every task after the disk fills fails alike): the job names every
    such failure in its one summary line, and a traceback per task would bury it. Any other exception is
    still logged in full.

    Also drops ``Failed to communicate with scheduler during heartbeat`` (with its traceback), which a
    worker of a local cluster can log when the cluster shuts down at the end of a job or segment while a
    heartbeat is in flight (seen on a busy machine): the job is over by then, and a scheduler lost
    mid-job fails the job through the client with its own one-line error."""

    EXPECTED = (f"{InputError.__name__}(",  # how the worker writes the exception: its repr
                f"OSError({errno.ENOSPC}, ", f"OSError({errno.EDQUOT}, ")  # no space left, a full quota
    SHUTDOWN_NOISE = ("Failed to communicate with scheduler during heartbeat",)

    def filter(self, record: logging.LogRecord) -> bool:
        if str(record.msg).startswith(self.SHUTDOWN_NOISE):
            return False
        if not str(record.msg).startswith("Compute Failed") or not isinstance(record.args, tuple):
            return True
        exception = record.args[3] if len(record.args) > 3 else ""
        return not str(exception).startswith(self.EXPECTED)


class _QuietWorkerLogs(WorkerPlugin):
    """Installs :class:`QuietExpectedErrors` in each worker process of a local cluster."""

    name = "cscsr-quiet-expected-errors"

    def setup(self, worker) -> None:
        log = logging.getLogger("distributed.worker")
        if not any(isinstance(f, QuietExpectedErrors) for f in log.filters):
            log.addFilter(QuietExpectedErrors())


def gpu_workers(client: Client) -> int:
    """How many of the cluster's workers advertise the ``GPU`` resource (``dask worker --resources GPU=1``)."""
    workers = client.scheduler_info()["workers"].values()
    return sum(1 for worker in workers if (worker.get("resources") or {}).get(GPU, 0) >= 1)


def dashboard_link(client: Client) -> str | None:
    """The dashboard URL when the scheduler serves one (it needs bokeh)."""
    with contextlib.suppress(Exception):
        return client.dashboard_link if "dashboard" in client.scheduler_info().get("services", {}) else None
    return None
