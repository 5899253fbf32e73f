"""A lease on an output: two jobs never write the same output at once.

A job writing an output keeps ``lease.json`` inside it (its run id, host, pid) and renews
the heartbeat every few seconds from a background thread. Before replacing or resuming an
output, a job checks the lease: a heartbeat younger than ``STALE`` seconds means another
job is alive and writing, and the new job refuses. A killed job stops renewing, so after
``STALE`` seconds its output can be resumed (at once if it ran on this machine and its
process is gone). Works on any URL (a small JSON object, no file locks).

Two jobs starting within the same instant could both find no live lease, so a job first takes
the output's *claim* (:func:`claimed`), atomically, before it touches the output at all, and
holds it to the end. On a local path the claim is an exclusive kernel lock (``flock``) on a file
beside the output, ``.NAME.claim``: of two jobs that try at once exactly one gets it, and a job
that dies, however it dies, lets go of it (no stale claim to break, which an ``O_EXCL`` file left
by a killed job would need). On an object store the claim is an object beside the output created
with a conditional write (``If-None-Match: *`` on AWS S3, atomic; an existence check then a write
on stores without one) and renewed like a lease. Limits there: a claim left by a killed job is
taken over after ``STALE`` seconds by a check-then-replace that two jobs starting in the same
instant could both pass; and S3-compatible servers that ignore ``If-None-Match`` make even the
first claim a check-then-write.
"""

import contextlib
import fcntl
import json
import os
import socket
import threading
import time
import uuid

from fsspec.implementations.local import LocalFileSystem

from pipeline.stores.storage import check_place, resolve
from stages.errors import InputError, describe

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
    return _live(lease)


def _live(lease) -> dict | None:
    """A lease record with its age if its job is alive, else None."""
    if not isinstance(lease, dict):
        return None
    try:
        age = time.time() - float(lease.get("heartbeat", 0))
    except (TypeError, ValueError):
        return None
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


CLAIM_FORMAT = ".{name}.claim"  # beside the output, hidden (the watcher's inbox listing skips dot files)
_remote_claims = threading.Lock()  # memory:// lives in this process: claims of its threads take turns


def claim_path(url: str) -> tuple:
    """(filesystem, path) of the claim file of the output at ``url``: beside it, not inside it, since
    ``--overwrite`` removes the output itself."""
    fs, path = resolve(url)
    if isinstance(fs, LocalFileSystem):  # one claim for every spelling: a symbolic link, file://, ..
        path = os.path.realpath(path)
    path = str(path).rstrip("/")
    parent, _, name = path.rpartition("/")
    return fs, f"{parent}/{CLAIM_FORMAT.format(name=name or 'root')}"


def _busy(url: str, other: dict | None) -> InputError:
    who = f" (host {other.get('host')}, pid {other.get('pid')})" if isinstance(other, dict) else ""
    return InputError(f"{url} is being written by another job{who}: wait for it to finish or stop it first")


@contextlib.contextmanager
def claimed(url: str):
    """Own the output at ``url`` while the block runs: of jobs that claim one output at once, exactly
    one gets in, the others are refused with one line (see the module docstring). Take it before
    touching the output (removing an old one included)."""
    check_place(url)  # under a regular file, or in a folder we may not write: one line, not a failed claim
    fs, path = claim_path(url)
    record = {"run": uuid.uuid4().hex, "host": socket.gethostname(), "pid": os.getpid(), "since": time.time()}
    if isinstance(fs, LocalFileSystem):
        with _locked(url, path, record):
            yield
    else:
        with _claimed_remote(url, fs, path, record):
            yield


@contextlib.contextmanager
def _locked(url: str, path: str, record: dict):
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                other = _read_record(fd)
                for _ in range(40):  # the holder writes who it is just after it took the lock
                    if other is not None:
                        break
                    time.sleep(0.005)
                    other = _read_record(fd)
                os.close(fd)
                raise _busy(url, other) from None
            try:  # the holder before us removes the file as it lets go: then ours is a lock on nothing
                current = os.stat(path)
                mine = os.fstat(fd)
                if (current.st_dev, current.st_ino) == (mine.st_dev, mine.st_ino):
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
    except OSError as error:
        raise InputError(f"cannot claim output {url}: {error.strerror or error} ({path})") from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # still holding the lock: a job that opened the old file sees it is gone
        os.close(fd)


def _read_record(fd: int) -> dict | None:
    with contextlib.suppress(OSError, ValueError):
        record = json.loads(os.pread(fd, 4096, 0) or b"null")
        return record if isinstance(record, dict) else None
    return None


@contextlib.contextmanager
def _claimed_remote(url: str, fs, path: str, record: dict):
    def write(mode: str) -> None:
        fs.pipe_file(path, json.dumps({**record, "heartbeat": time.time()}).encode(), mode=mode)

    def read() -> dict | None:
        try:
            return json.loads(fs.cat_file(path))
        except (FileNotFoundError, ValueError, OSError):
            return None

    with _remote_claims:
        try:
            write("create")
        except FileNotFoundError as error:  # no such bucket (or container): said of the output, not of a read
            raise InputError(f"cannot write {url}: {describe(error)}") from None
        except FileExistsError:
            other = read()
            if _live(other) is not None:
                raise _busy(url, other) from None
            with contextlib.suppress(FileNotFoundError):
                fs.rm_file(path)  # the claim of a job that died (not atomic: see the module docstring)
            try:
                write("create")
            except FileExistsError:
                raise _busy(url, read()) from None
    stop = threading.Event()

    def renew():
        while not stop.wait(HEARTBEAT):
            with contextlib.suppress(Exception):
                write("overwrite")

    thread = threading.Thread(target=renew, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        with contextlib.suppress(Exception):
            fs.rm_file(path)
