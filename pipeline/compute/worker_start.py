"""How a local cluster's worker processes start: the environment they start in, and for CPU workers, forked from one
server process that imported Dask's distributed, NumPy and Zarr once (Python's ``forkserver``) rather than each
spawned afresh."""

import os
import signal
import sys
import tempfile
import threading

import dask

from pipeline.compute.stopping import COMMAND_LINE


# Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which pins glibc's mmap
# threshold at 128 KiB: every large temporary array (an HR frame is tens of MB) is then a
# fresh mmap with page faults on every touch, 1.44x the time of a reconstruction task.
# Fixed thresholds of 64 MiB keep such arrays on the reused heap. glibc reads them only at
# process start, so they go in the nanny's pre-spawn environment, not in ``env``.
PRE_SPAWN = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": str(256 * 2**20),
             "distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": str(64 * 2**20)}


# A local cluster's CPU workers are forks of one server process (Python's "forkserver", Dask's
# distributed.worker.multiprocessing-method) that has imported distributed, NumPy and Zarr once. Spawned, every worker
# imported them for itself at every cluster start: a job's segments, a nanny's restart of a lost worker and every
# local cluster of a process after the first waited on it. What a job's workers never import is not preloaded, since
# every command that starts a cluster waits on its server: not dask.array (the jobs' tasks are futures; it imports
# xarray, pandas and SciPy: docs/performance.md, "Cluster start-up", for what leaving it out saves), and torch only
# for a job that runs the network (:data:`NETWORK_PRELOAD`; a TFP job never imports it). A forked worker's NumPy
# keeps the server's BLAS threads (Dask's pre-spawn default, 1), and its torch the server's thread count: the network
# runs on one thread whatever it is (``cscsr.inference.reconstructor.one_thread_on_cpu``). GPU workers are still
# spawned (a fork must never carry CUDA state, and they start once per job). Python skips a preload that fails to
# import.
START_METHOD = "distributed.worker.multiprocessing-method"
FORKSERVER_PRELOAD = ("distributed", "numpy", "numcodecs", "zarr",
                      "pipeline.compute.stopping")  # stopping: a command's workers ignore Ctrl-C, as spawned ones do
# What a network job's workers import (2.5 core-s each on a 2-core AMD EPYC): once in the server instead, so that
# neither its workers nor a nanny's restart of one, nor every local cluster of the process after the first, waits on it
NETWORK_PRELOAD = ("torch", "cscsr.inference.reconstructor")


_server_of: list[int] = []  # the process that started its fork server (a process forked from it has none yet)


def forked_workers(preload: tuple[str, ...] = ()) -> dict:
    """Dask's configuration for local workers forked from one server process, which the first call of a process
    starts with :data:`FORKSERVER_PRELOAD` and ``preload`` (:data:`NETWORK_PRELOAD` for a job that runs the network)
    imported, and the environment a spawned worker starts with (the nanny's pre-spawn variables: malloc settings, one
    BLAS thread, Dask's hash seed). The server is the process's: a later call's ``preload`` is not imported there,
    and its workers import what they need themselves, as spawned ones do."""
    if _server_of != [os.getpid()]:
        _start_server(preload)
        _server_of[:] = [os.getpid()]
    return {START_METHOD: "forkserver"}


def _start_server(preload: tuple[str, ...]) -> None:
    import multiprocessing
    from multiprocessing import forkserver

    import distributed.utils

    # Dask's first get_mp_context() under "forkserver" (the nanny's, in this process) imports every package
    # distributed knows of to choose the server's preload list, which ours replaces: pandas among them, 1.2 core-s of
    # every command that starts a cluster. Marked chosen, it imports none of them
    distributed.utils._forkserver_preload_set = True
    context = multiprocessing.get_context("forkserver")
    with dask.config.set(PRE_SPAWN):
        environment = {name: str(value) for name, value in
                       dask.config.get("distributed.nanny.pre-spawn-environ").items() if value is not None}
    environment.setdefault("PYTHONHASHSEED", "6640")  # what a nanny gives a spawned worker
    context.set_forkserver_preload([*FORKSERVER_PRELOAD, *preload])
    _short_socket_folder()
    before = dict(os.environ)
    os.environ.update(environment)
    deaf = bool(os.environ.get(COMMAND_LINE)) and threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if deaf else None
    try:  # a command's server is deaf to Ctrl-C from its first instruction, and so is every worker forked from it
        forkserver.ensure_running()
    finally:
        if deaf:
            signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
        os.environ.clear()
        os.environ.update(before)


SOCKET_PATH_MAX = 107  # bytes of a Unix socket's path (Linux's sun_path, less its terminating zero)


def _short_socket_folder() -> None:
    """The server listens on a Unix socket in multiprocessing's temporary folder, ``$TMPDIR/pymp-XXXXXXXX/
    listener-XXXXXXXX``; under a ``TMPDIR`` too long for a socket's path every job failed ("AF_UNIX path too long").
    There, that folder is made in the system's own temporary folder instead, as Python 3.13's multiprocessing does
    itself. (A process whose multiprocessing made its folder already keeps it.)"""
    if sys.version_info >= (3, 13):
        return
    from multiprocessing import util

    if len(os.path.join(tempfile.gettempdir(), "pymp-xxxxxxxx", "listener-xxxxxxxx")) <= SOCKET_PATH_MAX:
        return
    system = next((folder for folder in ("/tmp", "/var/tmp", "/usr/tmp") if os.access(folder, os.W_OK | os.X_OK)), None)
    if system is None:
        return
    previous, tempfile.tempdir = tempfile.tempdir, system
    try:
        util.get_temp_dir()  # made now, and kept for this process
    finally:
        tempfile.tempdir = previous
