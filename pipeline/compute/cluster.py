"""Where Dask work runs: an in-process ``LocalCluster`` (the default) or an existing scheduler.

Workers are processes with one task thread each; the numerical libraries inside a task
(numba, OpenCV, torch) get ``cores // workers`` threads so that a 2-core laptop with two
workers is not oversubscribed. An address comes from ``--scheduler`` or
``DASK_SCHEDULER_ADDRESS`` or Dask's ``scheduler-address`` setting; an unreachable one is a one-line error within seconds.
Workers started with ``--resources GPU=1`` are GPU workers (``pipeline.jobs.reconstruct.placement`` finds them).

Several GPUs per machine: one worker per GPU, each pinned to its device (``CUDA_VISIBLE_DEVICES``) and advertising
``GPU=1``, with :data:`GPU_TASKS_IN_FLIGHT` threads; the rest are 1-thread CPU workers that see no GPU. This is
dask-cuda's convention (``LocalCUDACluster``, ``dask cuda worker``), implemented here because dask-cuda does not fit
our pins (rapids-dask-dependency pins dask and distributed to another release, plus cuda-core and pandas). A local
cluster follows it where torch sees GPUs (:func:`dask_client`), and ``cscsr worker`` (:func:`serve_workers`) starts
a cluster node's workers by it. Without a GPU nothing changes.

A local cluster listens on loopback only: its scheduler, workers and dashboard (the dashboard
shows task names and file paths, and can run profiling). ``CSCSR_DASHBOARD=HOST:PORT`` (e.g.
``0.0.0.0:8787``) serves the dashboard elsewhere, for a user who asks for it.
"""

import asyncio
import contextlib
import errno
import functools
import importlib.metadata
import logging
import os
import signal
import sys
import threading
import uuid
from collections.abc import Iterable, Iterator, Sequence

import dask
from distributed import Client, LocalCluster, Nanny, WorkerPlugin

from pipeline.compute.stopping import purge_stale_worker_folders, start_resource_tracker
from pipeline.compute.worker_start import PRE_SPAWN, forked_workers
from stages.errors import InputError, describe
from stages.numbers import check_number

CONNECT_TIMEOUT = "5s"
WAIT_SETTING = "cscsr.wait-for-workers"  # Dask configuration: how long a job waits for a named scheduler's first worker
WAIT_DEFAULT = "60s"
QUIET_WAIT = 2.0  # seconds a job waits for a worker before it says that it is waiting
WORKERS_PER_CORE, MOST_WORKERS = 4, 256  # --workers at most 4 per core and 256 in all: beyond that a local
# cluster only multiplies processes (~100 MiB each) and start-up time, with no core left to run them
GPU = "GPU"  # the Dask worker resource a GPU worker advertises; network tasks ask for one
# Threads of a GPU worker. A network task asks for GPU_SHARE = 1 / GPU_TASKS_IN_FLIGHT of the GPU resource (0.25,
# exact in binary), so up to four network tasks are in flight on one GPU worker: one on the device (the reconstructor
# serialises device work with a lock) while the others read and decompress or compress and write.
GPU_TASKS_IN_FLIGHT = 4
GPU_SHARE = 1 / GPU_TASKS_IN_FLIGHT
DEVICES_VARIABLE = "CUDA_VISIBLE_DEVICES"  # the devices a process sees: what pins a worker to its GPU

_log = logging.getLogger("cscsr.worker")
LOOPBACK = "127.0.0.1"
DASHBOARD_VARIABLE = "CSCSR_DASHBOARD"  # HOST:PORT of a local cluster's dashboard; default loopback, any free port


def _thread_env(workers: int) -> dict:
    threads = str(max(1, (os.cpu_count() or 1) // workers))
    return {name: threads for name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def most_workers() -> int:
    """The most local worker processes ``--workers`` may ask for on this machine."""
    return min(MOST_WORKERS, WORKERS_PER_CORE * (os.cpu_count() or 1))


def check_workers(workers: int | None, scheduler: str | None = None) -> None:
    """Refuse a ``--workers`` outside 1..:func:`most_workers` (None: one per core), and with a scheduler named
    too, by ``--scheduler`` or, as it counts for one, ``DASK_SCHEDULER_ADDRESS`` or Dask's ``scheduler-address``
    (a local cluster of our own, and a running one: the workers were silently ignored); every command that
    takes ``--workers`` calls this before it creates any output."""
    if workers is not None:
        check_number("--workers", workers, at_least=1, at_most=most_workers(), integer=True,
                     why=f"at most {WORKERS_PER_CORE} per core and {MOST_WORKERS} in all")
        if scheduler is not None:
            raise InputError(f"--workers {workers} and --scheduler {scheduler} contradict each other: --workers "
                             f"starts a local cluster of its own, --scheduler runs on the one there: give one")
        if named := scheduler_address(None):
            by = ("DASK_SCHEDULER_ADDRESS" if os.environ.get("DASK_SCHEDULER_ADDRESS")
                  else "Dask's scheduler-address setting")
            raise InputError(f"--workers {workers} and the scheduler {by} names ({named}) contradict each other: "
                             f"--workers starts a local cluster of its own: leave --workers out, or unset {by}")


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


def workers_timeout() -> float | None:
    """Seconds a job waits for the first worker of a named scheduler (:func:`wait_for_workers`): Dask's configuration
    value ``cscsr.wait-for-workers`` (``DASK_CSCSR__WAIT_FOR_WORKERS``, a YAML file, ``dask.config.set``), a
    duration as Dask writes them (``60s``, ``5 minutes``, seconds as a number), default :data:`WAIT_DEFAULT`; None
    (``null``) waits for ever. Anything else is refused in one line."""
    value = dask.config.get(WAIT_SETTING, WAIT_DEFAULT)
    if value is None:
        return None
    try:
        seconds = float(dask.utils.parse_timedelta(value, "s"))
    except (ValueError, TypeError, KeyError):
        seconds = -1.0
    if not seconds > 0:
        raise InputError(f"Dask setting {WAIT_SETTING} must be a duration such as 60s or 5 minutes (or null: wait "
                         f"for ever), got {value!r}")
    return seconds


def wait_for_workers(client: Client, address: str) -> None:
    """Return once the scheduler at ``address`` has a running worker (``client.wait_for_workers(1, timeout)``, Dask's
    way); after :data:`QUIET_WAIT` seconds (half the limit if that is shorter) without one, say so in one warning,
    "waiting for workers (0 connected) ...", and at :func:`workers_timeout` give up in one line (:class:`InputError`).
    A job sent to a scheduler whose workers had all died, or not started yet, waited silently for ever."""
    from distributed.client import WorkerStartTimeoutError

    limit = workers_timeout()
    quiet = QUIET_WAIT if limit is None else min(QUIET_WAIT, limit / 2)
    try:
        client.wait_for_workers(1, timeout=quiet)
        return
    except WorkerStartTimeoutError as waited:
        connected = waited.available_workers
    until = "" if limit is None else f", for up to {limit:g} s (Dask setting {WAIT_SETTING})"
    logging.getLogger("cscsr.cluster").warning("waiting for workers (%d connected) at Dask scheduler %s%s",
                                               connected, address, until)
    try:
        client.wait_for_workers(1, timeout=None if limit is None else limit - quiet)
    except WorkerStartTimeoutError:
        raise _no_workers(address, limit) from None


def _no_workers(address: str, seconds: float) -> InputError:
    return InputError(f"no worker at Dask scheduler {address} within {seconds:g} s: start workers there (cscsr worker "
                      f"{address}, or dask worker), or wait longer with Dask's setting {WAIT_SETTING} "
                      f"(DASK_CSCSR__WAIT_FOR_WORKERS=5m)")


_THIS_PROCESS = uuid.uuid4().hex  # a worker answering with this mark runs in this very process


def _process_mark() -> str:
    return _THIS_PROCESS


def workers_in_this_process(client) -> bool:
    """Whether every worker of ``client`` runs in this process (``LocalCluster(processes=False)``), where a
    ``memory://`` store is theirs too. False for ``None`` (a job without a client starts a local cluster of
    worker processes, or connects to a scheduler), for a cluster of worker processes, and for one with no
    worker yet (whoever joins later is a process of its own)."""
    if client is None:
        return False
    if str(client.scheduler.address).startswith("inproc://"):  # only this process can reach such a scheduler
        return True
    try:
        marks = client.run(_process_mark)
    except Exception:  # noqa: BLE001 - workers that cannot even answer share nothing with us
        return False
    return bool(marks) and all(mark == _THIS_PROCESS for mark in marks.values())


def check_in_memory(urls: Iterable[str | None], *, client=None, instead: str = "") -> None:
    """Refuse, in one line and before any output exists, a ``memory://`` input or output among ``urls`` of a
    job whose tasks read or write it in worker processes (a local cluster's, or a scheduler's: ``client``
    None, or one whose workers are not all in this process). A ``memory://`` store lives in one process's
    memory: each worker would write into its own, and the job would fail only after every task had run,
    advising a ``--resume`` that cannot help. ``instead``: a way out for this command (``, or ...``)."""
    memory = [str(url) for url in urls if url is not None and str(url).startswith("memory://")]
    if not memory or workers_in_this_process(client):
        return
    raise InputError(f"cannot use {memory[0]}: memory:// lives in this process only, and this job's tasks run in "
                     f"worker processes (a local cluster's or a scheduler's) that cannot read or write it: give a "
                     f"path or another URL (file://, s3://){instead}")


def visible_gpus() -> int:
    """How many CUDA devices this process sees: ``torch.cuda.device_count()``, which honours
    ``CUDA_VISIBLE_DEVICES`` and asks NVML, so no CUDA context is made (and nothing is initialised
    that a forked process would inherit); 0 if torch is missing or built without CUDA. A CPU build of
    torch (``+cpu``) is answered from its version without importing it (a second and a half)."""
    if os.environ.get(DEVICES_VARIABLE) is not None and not _listed_devices():
        return 0  # CUDA_VISIBLE_DEVICES="" (or "-1"): every device hidden
    if "torch" not in sys.modules:
        try:
            if importlib.metadata.version("torch").endswith("+cpu"):
                return 0
        except importlib.metadata.PackageNotFoundError:
            return 0
    try:
        import torch

        return int(torch.cuda.device_count())
    except Exception:  # noqa: BLE001 - a broken CUDA install is no GPU
        return 0


def _listed_devices() -> list[str]:
    """The entries of this process's ``CUDA_VISIBLE_DEVICES`` (SLURM and container runtimes set it to the
    GPUs a job was given): indices or UUIDs; CUDA stops at the first invalid one, e.g. ``-1``."""
    listed = []
    for entry in os.environ.get(DEVICES_VARIABLE, "").split(","):
        entry = entry.strip()
        if not entry or entry.startswith("-"):
            break
        listed.append(entry)
    return listed


def _devices(gpus: int) -> list[str]:
    """``CUDA_VISIBLE_DEVICES`` of each of ``gpus`` pinned workers: the i-th device this process sees (its own
    ``CUDA_VISIBLE_DEVICES`` entry when it has one, as dask-cuda does, else ``i``)."""
    listed = _listed_devices()
    if not listed:
        return [str(i) for i in range(gpus)]
    if gpus > len(listed):
        raise InputError(f"--gpus {gpus}: this machine's {DEVICES_VARIABLE}={os.environ[DEVICES_VARIABLE]} "
                         f"shows only {len(listed)} GPU{'s' if len(listed) > 1 else ''}")
    return listed[:gpus]


def gpu_worker_specs(workers: int, gpus: int, devices: Sequence[str] | None = None) -> list[dict]:
    """The options of each of ``workers`` worker processes on a machine with ``gpus`` GPUs, as keyword
    arguments of :class:`distributed.Nanny`: ``{"env": {...}, "resources": {...}, "nthreads": n}``.

    The first ``min(workers, gpus)`` are GPU workers: ``CUDA_VISIBLE_DEVICES`` the i-th device
    (``devices[i]``, default ``str(i)``), ``resources={"GPU": 1}``, :data:`GPU_TASKS_IN_FLIGHT`
    threads. The rest are CPU workers: ``CUDA_VISIBLE_DEVICES=""`` (they never touch a GPU), no
    resources, one thread."""
    pinned = max(0, min(workers, gpus))
    devices = [str(i) for i in range(pinned)] if devices is None else list(devices)
    if len(devices) < pinned:
        raise ValueError(f"{pinned} GPU workers need {pinned} devices, got {devices}")
    return ([{"env": {DEVICES_VARIABLE: devices[i]}, "resources": {GPU: 1}, "nthreads": GPU_TASKS_IN_FLIGHT}
             for i in range(pinned)]
            + [{"env": {DEVICES_VARIABLE: ""}, "resources": {}, "nthreads": 1} for _ in range(workers - pinned)])


@contextlib.contextmanager
def dask_client(*, workers: int | None = None, scheduler: str | None = None,
                gpus: int | None = None, preload: tuple[str, ...] = ()) -> Iterator[Client]:
    """A connected client; a local cluster of ``workers`` processes unless a scheduler is named (its CPU workers
    forked from a server that imported ``preload`` too, if this process starts one: :func:`forked_workers`).

    On a machine with GPUs (``gpus``, default :func:`visible_gpus`) the first ``min(workers, gpus)``
    workers of a local cluster are pinned GPU workers and the rest CPU workers
    (:func:`gpu_worker_specs`); with none, every worker is a 1-thread CPU worker as before."""
    address = scheduler_address(scheduler)
    if address:
        check_scheduler(address)  # a port that accepts and never answers would hang Client() for ever
        try:
            client = Client(address, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as error:
            raise InputError(f"cannot reach Dask scheduler {address}: {describe(error)}") from None
        with client:
            wait_for_workers(client, address)  # a scheduler without workers would run nothing, silently, for ever
            yield client
        return
    check_workers(workers)
    if gpus is not None:
        check_number("--gpus", gpus, at_least=0, integer=True)
    start_resource_tracker()  # one, deaf to Ctrl-C, shared by the workers (pipeline.compute.stopping)
    workers = workers if workers is not None else os.cpu_count() or 1
    gpus = visible_gpus() if gpus is None else gpus
    options = {}
    if gpus:  # LocalCluster's own options for every worker, then each one's threads, resources and device
        specs = gpu_worker_specs(workers, gpus, _devices(min(workers, gpus)))
        options["worker_class"] = functools.partial(_pinned_nanny, specs)
    with contextlib.ExitStack() as stack:
        stack.callback(purge_stale_worker_folders)  # after the cluster closed, however it ended
        with dask.config.set({**PRE_SPAWN, **({} if gpus else forked_workers(preload))}), \
                LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host=LOOPBACK,
                             dashboard_address=os.environ.get(DASHBOARD_VARIABLE) or f"{LOOPBACK}:0",
                             silence_logs=_dask_log_level(), env=_thread_env(workers), **options) as cluster, \
                Client(cluster) as client:
            client.register_plugin(_QuietWorkerLogs())  # our own workers only: a shared cluster's logs are its owner's
            yield client


def _pinned_nanny(specs: list[dict], scheduler: str, *, name, env: dict | None = None, **options) -> Nanny:
    """The local cluster's worker ``name`` (0, 1, ...): a Nanny with LocalCluster's options (loopback, memory
    limit, logs, thread environment) and the threads, resources and device of ``specs[name]``."""
    spec = specs[name] if isinstance(name, int) and 0 <= name < len(specs) else gpu_worker_specs(1, 0)[0]
    nanny = GpuNanny if spec["resources"] else Nanny
    return nanny(scheduler, name=name, **{**options, "nthreads": spec["nthreads"], "resources": spec["resources"]},
                 env={**(env or {}), **spec["env"]})


GPU_WORKER_EXIT_S = 60  # seconds a GPU worker's process is given to exit when its cluster closes (GpuNanny)


class GpuNanny(Nanny):
    """A Nanny whose worker process gets :data:`GPU_WORKER_EXIT_S` to exit when closed, not Dask's 4 s then SIGKILL
    and 1 s more: a --fast-gpu worker (a CUDA context of 40 GiB, inductor's compile workers) took longer on the H200
    (2026-11-27), and the finished job failed closing its cluster."""

    async def close(self, timeout: float = GPU_WORKER_EXIT_S, reason: str = "nanny-close"):
        return await super().close(timeout=max(timeout, GPU_WORKER_EXIT_S), reason=reason)


def serve_workers(scheduler: str, *, memory_limit: str | int | None = "4GiB", gpus: int | None = None,
                  name_prefix: str | None = None, nthreads: int | None = None, death_timeout: float | None = None,
                  interface: str | None = None, stop: threading.Event | None = None) -> None:
    """The workers of one cluster node, as ``dask cuda worker`` starts them (``cscsr worker``): one
    :class:`distributed.Nanny` per GPU (``gpus``, default :func:`visible_gpus`), pinned to it and
    advertising ``GPU=1`` with :data:`GPU_TASKS_IN_FLIGHT` threads; one ordinary 1-thread worker when there is
    no GPU (:func:`gpu_worker_specs`). ``memory_limit`` is each worker's (Dask's forms: ``4GiB``, a fraction
    of the machine's, ``auto``, 0 for none); ``name_prefix`` names them ``NAME`` (one worker) or ``NAME-0``,
    ``NAME-1``, ... (dask-jobqueue expects those); ``nthreads`` replaces every worker's thread count;
    ``death_timeout`` and ``interface`` are ``dask worker``'s. Numerical libraries get ``cores // workers``
    threads unless the environment sets them.

    Blocks until the scheduler goes away, or SIGTERM or SIGINT (in the main thread), or ``stop`` is set;
    then closes the workers (their tasks go back to the scheduler) and returns. Refuses a bad option or an
    unreachable scheduler first, in one line (:class:`InputError`)."""
    if gpus is not None:
        check_number("--gpus", gpus, at_least=0, integer=True)
    if nthreads is not None:
        check_number("--nthreads", nthreads, at_least=1, integer=True)
    if death_timeout is not None:
        check_number("--death-timeout", death_timeout, above=0)
    seen = visible_gpus()
    if gpus is not None and gpus > seen:  # told, not refused: a GPU node's environment may hide them from here
        _log.warning("--gpus %d, but torch sees %d CUDA device%s here: these workers advertise GPUs they do not "
                     "have, and the network's tasks (GPU workers get the full weights by default) will run on "
                     "the CPU", gpus, seen, "" if seen == 1 else "s")
    gpus = seen if gpus is None else gpus
    specs = gpu_worker_specs(max(gpus, 1), gpus, _devices(gpus))
    memory = _memory_limit(memory_limit, len(specs))
    check_scheduler(scheduler)
    env = {name: value for name, value in _thread_env(len(specs)).items() if name not in os.environ}
    names = [name_prefix if not name_prefix or len(specs) == 1 else f"{name_prefix}-{i}" for i in range(len(specs))]
    if gpus:
        devices = ", ".join(spec["env"][DEVICES_VARIABLE] for spec in specs)
        _log.info("%d GPU worker%s (CUDA devices %s) for %s", gpus, "s" if gpus > 1 else "", devices, scheduler)
    else:
        _log.info("one CPU worker for %s (no GPU)", scheduler)
    with dask.config.set(PRE_SPAWN):
        asyncio.run(_serve(scheduler, [dict(name=name, memory_limit=memory, death_timeout=death_timeout,
                                            interface=interface, nthreads=nthreads or spec["nthreads"],
                                            resources=spec["resources"], env={**env, **spec["env"]})
                                       for name, spec in zip(names, specs)], stop))


def _memory_limit(value: str | int | float | None, workers: int) -> int | None:
    """Bytes of the memory limit of each of ``workers`` workers, in Dask's forms (``4GiB``, ``0.5`` of the
    machine's; ``auto``: the machine's shared among them; 0 or None: no limit), or a one-line refusal."""
    from distributed.worker_memory import parse_memory_limit

    try:
        limit = parse_memory_limit(value, 1, workers, logger=logging.getLogger("distributed.worker.memory"))
    except (ValueError, TypeError, OverflowError):
        limit = -1
    if limit is not None and limit <= 0:
        raise InputError(f"--memory-limit must be a size like 4GiB, a fraction of the machine's memory like 0.5, "
                         f"auto, or 0 for no limit, got {value!r}")
    return limit


async def _serve(scheduler: str, options: list[dict], stop: threading.Event | None) -> None:
    """Start a Nanny of each of ``options`` and wait until they all finish (their scheduler went away) or a
    stop is asked (SIGTERM, SIGINT, ``stop``); then close them. ``dask worker``'s loop."""
    loop = asyncio.get_running_loop()
    nannies = [(GpuNanny if each.get("resources") else Nanny)(scheduler, **each)  # made in the loop they run in
               for each in options]
    stopping = asyncio.Event()
    handled = []
    for signum in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(ValueError, RuntimeError, NotImplementedError):  # not the main thread
            loop.add_signal_handler(signum, stopping.set)
            handled.append(signum)

    async def asked() -> None:
        while not (stopping.is_set() or (stop is not None and stop.is_set())):
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stopping.wait(), 0.2)

    async def finished() -> None:
        await asyncio.gather(*nannies)
        await asyncio.gather(*(nanny.finished() for nanny in nannies))

    running, stopper = asyncio.create_task(finished()), asyncio.create_task(asked())
    try:
        done, _ = await asyncio.wait([running, stopper], return_when=asyncio.FIRST_COMPLETED)
        if running in done:
            running.result()  # a worker that could not start
        else:
            await asyncio.gather(*(nanny.close(timeout=10, reason="cscsr-worker-stopped") for nanny in nannies),
                                 return_exceptions=True)
            running.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await running
    finally:
        stopper.cancel()
        for signum in handled:
            loop.remove_signal_handler(signum)


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
    heartbeat is in flight (seen on a busy machine), and ``failed during get data`` (a peer that closed while
    this worker sent it a result: a SIGTERM'd simulate job in CI): the job is over by then, a peer lost mid-job is
    Dask's to recover from, and a scheduler lost mid-job fails the job through the client with its own line."""

    EXPECTED = (f"{InputError.__name__}(",  # how the worker writes the exception: its repr
                f"OSError({errno.ENOSPC}, ", f"OSError({errno.EDQUOT}, ")  # no space left, a full quota
    SHUTDOWN_NOISE = ("Failed to communicate with scheduler during heartbeat", "failed during get data with")

    def filter(self, record: logging.LogRecord) -> bool:
        if str(record.msg).startswith(self.SHUTDOWN_NOISE):
            return False
        if not str(record.msg).startswith("Compute Failed") or not isinstance(record.args, tuple):
            return True
        exception = record.args[3] if len(record.args) > 3 else ""
        return not str(exception).startswith(self.EXPECTED)


class _QuietWorkerLogs(WorkerPlugin):
    """Installs :class:`QuietExpectedErrors` in each worker process of a local cluster, and leaves Ctrl-C to the
    cluster: the terminal sends SIGINT to every process of the job, and a worker that took it printed a traceback of
    its own (``KeyboardInterrupt`` from its event loop) while the job was already closing the cluster, which closes
    the worker too."""

    name = "cscsr-quiet-expected-errors"

    def setup(self, worker) -> None:
        log = logging.getLogger("distributed.worker")
        if not any(isinstance(f, QuietExpectedErrors) for f in log.filters):
            log.addFilter(QuietExpectedErrors())
        if threading.current_thread() is threading.main_thread():  # a worker process's event loop: its main thread
            signal.signal(signal.SIGINT, lambda signum, frame: None)  # Python's: processes it starts get the default


