"""A lease on an output: two jobs never write the same output at once.

A job writing an output keeps ``lease.json`` inside it (its run id, host, pid) and renews
the heartbeat every few seconds from a background thread. Before replacing or resuming an
output, a job checks the lease: a heartbeat younger than ``STALE`` seconds means another
job is alive and writing, and the new job refuses. A killed job stops renewing, so after
``STALE`` seconds its output can be resumed (at once if it ran on this machine and its
process is gone). Works on any URL (a small JSON object, no file
locks), at the price of a short window when two jobs start within the same instant.
"""

import contextlib
import json
import os
import socket
import threading
import time
import uuid

from pipeline.storage import resolve
from stages.errors import InputError

FILENAME = "lease.json"
HEARTBEAT = 5.0  # seconds between renewals
STALE = 30.0  # a lease not renewed for this long belongs to a dead job


def _path(url: str) -> tuple:
    fs, root = resolve(url)
    return fs, f"{root.rstrip('/')}/{FILENAME}"


def holder(url: str) -> dict | None:
    """The live lease on ``url``, or None if there is none or it is stale."""
    fs, path = _path(url)
    try:
        lease = json.loads(fs.cat_file(path))
    except (FileNotFoundError, ValueError, OSError):
        return None
    age = time.time() - float(lease.get("heartbeat", 0))
    if age >= STALE or (lease.get("host") == socket.gethostname() and not _alive(lease.get("pid"))):
        return None  # its job died (a process of this machine that is gone needs no waiting)
    return {**lease, "age": age}


def _alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, TypeError, ValueError):
        return True
    return True


def check_free(url: str) -> None:
    """Refuse if another live job holds ``url``."""
    lease = holder(url)
    if lease is not None:
        raise InputError(f"{url} is being written by another job (host {lease.get('host')}, pid {lease.get('pid')}, "
                         f"heartbeat {lease['age']:.0f} s ago): wait for it to finish or stop it first")


@contextlib.contextmanager
def held(url: str):
    """Hold the lease on ``url`` (an existing folder or store) while the block runs."""
    fs, path = _path(url)
    run = uuid.uuid4().hex
    stop = threading.Event()

    def write():
        lease = {"run": run, "host": socket.gethostname(), "pid": os.getpid(), "heartbeat": time.time()}
        fs.pipe_file(path, json.dumps(lease).encode())

    def renew():
        while not stop.wait(HEARTBEAT):
            with contextlib.suppress(Exception):
                write()

    write()
    thread = threading.Thread(target=renew, daemon=True)
    thread.start()
    try:
        yield run
    finally:
        stop.set()
        thread.join()
        with contextlib.suppress(Exception):
            fs.rm_file(path)
