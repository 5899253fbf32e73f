"""fsspec URLs -> filesystems and Zarr stores; an output kept apart from its inputs; removing a store.

Any location is a URL: a plain path, ``file://``, ``memory://`` (shared within one process),
``s3://`` (s3fs; endpoint and credentials from the usual AWS variables or fsspec's
``FSSPEC_S3_*`` settings; timeouts and retries bounded by :data:`S3_TIMEOUTS`, and an endpoint
that never answers refused in one line). Local paths map to Zarr's ``LocalStore`` (which creates
directories as needed), everything else to ``FsspecStore``.
"""

import atexit
import itertools
import math
import os
import posixpath
import re
import stat
import warnings
from collections.abc import Iterator
from dataclasses import dataclass

import fsspec
import zarr
from fsspec.implementations.local import LocalFileSystem

from stages.errors import InputError, describe


# S3's timeouts and retries (botocore ``Config`` keys), for every S3 filesystem this project opens. botocore's
# own (60 s to connect, 60 s to read, 5 attempts), under s3fs's 5 tries of its own, kept a command silent for
# 411 s on an endpoint that accepts connections and never answers. A key the user sets wins, in fsspec's
# configuration (FSSPEC_S3_CONFIG_KWARGS='{"read_timeout": 60}', or a file in ~/.config/fsspec/).
S3_TIMEOUTS = {"connect_timeout": 5, "read_timeout": 10, "retries": {"mode": "standard", "total_max_attempts": 3}}
S3_PROTOCOLS = ("s3", "s3a")
_ANSWERED: set = set()  # the S3 filesystems (fsspec tokens) whose endpoint has answered in this process


def storage_options(url: str) -> dict:
    """The fsspec options this project adds for ``url``: S3's timeouts (:data:`S3_TIMEOUTS`) under the
    user's own ``config_kwargs``; nothing for other filesystems."""
    if fsspec.core.split_protocol(str(url))[0] not in S3_PROTOCOLS:
        return {}
    theirs = fsspec.config.conf.get("s3", {}).get("config_kwargs")
    return {"config_kwargs": {**S3_TIMEOUTS, **(theirs if isinstance(theirs, dict) else {})}}


def resolve(url: str) -> tuple[fsspec.AbstractFileSystem, str]:
    """(filesystem, path inside it) for a URL or plain path; an S3 endpoint that does not answer is refused
    in one line (:func:`check_answers`)."""
    fs, path = _filesystem(url)
    check_answers(fs, url, path)
    return fs, path


class Unreachable(InputError):
    """Remote storage that cannot be reached (no such host, no answer, no credentials): said in one line, as any
    bad input, and never taken for a place that holds nothing."""


def check_not_empty(url: str) -> None:
    """Refuse an empty path or URL in one line: fsspec takes it for the current folder (a ``simulate ""`` read
    whatever picture it found there)."""
    if not str(url).strip():
        raise InputError(f"a path is empty ({str(url)!r}): give a path or URL (an empty one is not the current "
                         f"folder)")


def _filesystem(url: str) -> tuple[fsspec.AbstractFileSystem, str]:
    """:func:`resolve` without a request: for what only compares or parses locations."""
    check_not_empty(url)
    try:
        return fsspec.core.url_to_fs(str(url), **storage_options(url))
    except (ValueError, ImportError) as error:
        raise InputError(f"cannot use URL {url!r}: {error}") from None
    except OSError as error:  # a filesystem that connects on creation (ftp://): no such host, refused, ...
        raise Unreachable(f"cannot reach {url}: {describe(error)}") from None


def check_answers(fs: fsspec.AbstractFileSystem, url: str, path: str) -> None:
    """Refuse an S3 endpoint that accepts connections and never answers, or cannot be reached at all, in one
    line naming ``url``, within its connect and read timeouts: once per filesystem and process, one request
    (HEAD of the bucket) under a deadline. Any answer counts (no such bucket, access denied): the operation
    that follows says what is wrong. Without it, retries of retries of read timeouts stay silent for minutes."""
    protocols = fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,)
    token = getattr(fs, "_fs_token", None)
    if not set(protocols) & set(S3_PROTOCOLS) or token in _ANSWERED or not hasattr(fs, "_call_s3"):
        return
    bucket = fs.split_path(path)[0]
    if not bucket:
        return
    config = {**S3_TIMEOUTS, **(getattr(fs, "config_kwargs", None) or {})}
    try:
        seconds = float(config["connect_timeout"]) + float(config["read_timeout"])
    except (TypeError, ValueError):
        seconds = float(S3_TIMEOUTS["connect_timeout"] + S3_TIMEOUTS["read_timeout"])
    try:
        fsspec.asyn.sync(fs.loop, fs._call_s3, "head_bucket", Bucket=bucket, timeout=seconds)
    except NotImplementedError:  # called on fsspec's own event loop: no waiting there
        return
    except (fsspec.exceptions.FSTimeoutError, TimeoutError):
        endpoint = getattr(getattr(getattr(fs, "_s3", None), "meta", None), "endpoint_url", None)
        raise Unreachable(f"cannot reach {url}: no answer from {endpoint or 'the S3 endpoint'} within {seconds:g} s "
                         "(something accepts connections there but does not answer; check the endpoint: "
                         "AWS_ENDPOINT_URL or FSSPEC_S3_ENDPOINT_URL)") from None
    except Exception as error:  # noqa: BLE001 - an answer (an HTTP status), or a failure to reach it, named below
        answered = any(getattr(e, "response", None) is not None for e in (error, error.__cause__))
        if not answered and (line := unreachable(error, [str(url)])) is not None:
            raise Unreachable(line) from None
    _ANSWERED.add(token)


def unreachable(error: BaseException, urls) -> str | None:
    """A failure to reach remote storage (no such host, a refused connection, no credentials) as one line
    naming the remote URLs among ``urls`` (a command's arguments) and the cause; None for other errors."""
    remote = [str(u) for u in urls if isinstance(u, str) and "://" in u
              and u.split("://", 1)[0] not in ("file", "local", "memory")]
    if not remote:
        return None
    name = type(error).__name__
    if name in ("NoCredentialsError", "PartialCredentialsError"):  # botocore's, raised through s3fs
        cause = ("no S3 credentials found (set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, AWS_PROFILE, or "
                 "fsspec's FSSPEC_S3_KEY and FSSPEC_S3_SECRET)")
    elif isinstance(error, OSError) and not isinstance(error, (FileNotFoundError, FileExistsError, IsADirectoryError,
                                                                NotADirectoryError)) or _botocore_connection(error):
        cause = f"{name}: {describe(error)}"  # a host not found, a connection refused or timed out
    else:
        return None
    return f"cannot reach {' or '.join(remote)}: {cause}"


def _botocore_connection(error: BaseException) -> bool:
    """botocore's failures to connect (``EndpointConnectionError``, ``ConnectTimeoutError``, ...), which are
    not ``OSError`` under aiobotocore."""
    return any(kind.__name__ == "ConnectionError" and kind.__module__.startswith("botocore")
               for kind in type(error).__mro__)


def is_local(url: str) -> bool:
    return isinstance(resolve(url)[0], LocalFileSystem)


FILE_TYPES = ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
              (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def local_kind(path: str) -> str | None:
    """What a local path is (:data:`FILE_TYPES`; a link is what it leads to), in words; None if nothing is there."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a link to nothing" if os.path.lexists(path) else None
    except OSError as error:  # a loop of links, a path too long, ...
        return f"unreadable ({describe(error)})"
    return next((what for is_type, what in FILE_TYPES if is_type(mode)), "neither a file nor a folder")


def check_regular_file(url: str, what: str) -> None:
    """Refuse, in one line, a local ``url`` that is there but is no regular file (a folder, a named pipe, whose
    reader would wait for a writer, a device), without opening it; nothing for other places, or nothing there."""
    if is_local(url) and (kind := local_kind(resolve(url)[1])) not in (None, "a regular file"):
        raise InputError(f"{what} {url} is {kind}, not a regular file: give the file itself")


def exists(url: str) -> bool:
    fs, path = resolve(url)
    return fs.exists(path)


def remove(url: str) -> None:
    """Delete a file or directory tree if it exists."""
    fs, path = resolve(url)
    if fs.exists(path):
        fs.rm(path, recursive=True)


def zarr_store(url: str, *, read_only: bool) -> zarr.abc.store.Store:
    """A Zarr v3 store for the URL."""
    fs, path = resolve(url)
    if isinstance(fs, LocalFileSystem):
        return zarr.storage.LocalStore(path, read_only=read_only)
    return zarr.storage.FsspecStore.from_url(str(url), read_only=read_only,
                                             storage_options=storage_options(url) or None)


def remove_partial_writes(url: str) -> list[str]:
    """Remove the temporary files of chunk writes that never finished from the store at ``url``.

    Zarr's ``LocalStore`` writes a chunk to ``KEY.<uuid>.partial`` and renames it; a worker killed
    between the two leaves the temporary file behind (the task reruns elsewhere and writes the chunk).
    Called by a job when every task has finished, before it marks the store complete, so a complete
    store holds its chunks and nothing else. Other filesystems write in one step: nothing to do."""
    if not is_local(url):
        return []
    fs, root = resolve(url)
    partial = [name for name in fs.find(root) if name.endswith(".partial")]
    for name in partial:
        fs.rm_file(name)
    return partial


def recorded(url: str) -> str:
    """A location as a store records it (``source``) and as a job's tasks open it: a URL as given, a local path
    made absolute, so that the record still points to the same place when the store is moved or read from
    elsewhere, and a worker started in another folder (``dask worker`` on a cluster) reads and writes where the
    user meant."""
    text = str(url)
    return text if "://" in text else os.path.abspath(text)


def consolidate(url: str) -> None:
    """Write consolidated metadata (every array's metadata, in the root ``zarr.json``), as xarray and other
    readers expect. Called once a store's arrays are all declared: array metadata never changes after, and
    the group's own attributes (``state``, written last) live beside the consolidated copy, so later
    attribute updates keep it valid. Zarr warns that v3 has no standard for it yet; xarray reads it."""
    zarr.consolidate_metadata(zarr_store(url, read_only=False))


# Zarr's warning that v3 has no standard for consolidated metadata (we write it for xarray, on purpose): ignored for the
# whole process, not inside a ``catch_warnings`` block around the call, because Zarr may issue it on its own I/O thread
# after a Ctrl-C has already left such a block (the job's one-line "interrupted" then came after the warning's lines)
warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part", category=UserWarning)


def open_group(url: str, what: str = "store") -> zarr.Group:
    """The Zarr group at ``url``, read-only; a one-line error if it is missing, an array, or damaged.

    Read from the arrays' own metadata, not the consolidated copy (that is for xarray): an array added
    to a store after it was consolidated is still seen."""
    try:
        return zarr.open_group(zarr_store(url, read_only=True), mode="r", use_consolidated=False)
    except InputError:
        raise
    except FileNotFoundError:
        raise InputError(f"cannot read {what} {url}: no Zarr group there") from None
    except zarr.errors.ContainsArrayError:
        raise InputError(f"cannot read {what} {url}: it holds a Zarr array, not a group") from None
    except (ValueError, TypeError, KeyError, AttributeError, zarr.errors.BaseZarrError) as error:
        raise InputError(f"cannot read {what} {url}: its Zarr metadata is damaged ({describe(error)})") from None


@dataclass(frozen=True)
class ChunkListing:
    """Which chunks of an array have an object in its store, from one listing of its keys (no chunk read), kept as
    what is stored: the grid's size is arithmetic and its missing chunks runs between stored ones, so a shape that
    claims 10⁹ frames costs what the store holds, never a list of the whole grid. Chunks are numbered in the grid's
    C order (:meth:`coordinates`)."""

    grid: tuple[int, ...]  # chunks along each dimension
    stored: tuple[int, ...]  # the numbers of the chunks that have an object, ascending

    @property
    def total(self) -> int:
        return math.prod(self.grid)

    @property
    def missing(self) -> int:
        return self.total - len(self.stored)

    def missing_runs(self) -> Iterator[range]:
        """The runs of consecutive missing chunks (chunk numbers), in order: at most one more than the stored chunks."""
        previous = -1
        for number in (*self.stored, self.total):
            if number > previous + 1:
                yield range(previous + 1, number)
            previous = number

    def first_missing(self, count: int) -> list[tuple[int, ...]]:
        """The grid coordinates of the first ``count`` missing chunks (fewer if fewer are missing)."""
        numbers = itertools.islice(itertools.chain.from_iterable(self.missing_runs()), count)
        return [self.coordinates(number) for number in numbers]

    def coordinates(self, number: int) -> tuple[int, ...]:
        """The grid coordinates of chunk ``number``."""
        coords = []
        for size in reversed(self.grid):
            number, index = divmod(number, size)
            coords.append(index)
        return tuple(reversed(coords))

    def number(self, coords: tuple[int, ...]) -> int | None:
        """The number of the chunk at grid coordinates ``coords``; None outside the grid."""
        if len(coords) != len(self.grid) or not all(0 <= index < size for index, size in zip(coords, self.grid)):
            return None
        number = 0
        for index, size in zip(coords, self.grid):
            number = number * size + index
        return number


def list_chunks(array: zarr.Array) -> ChunkListing:
    """The chunks of ``array`` that have an object in its store (:class:`ChunkListing`), from one listing of the
    array's keys, no chunk read. Our writers store every chunk, empty or not, so a chunk that is not there is lost
    data. Keys that are not chunks of the grid (metadata, temporary files of writes, chunks beyond the shape) are
    not counted."""
    from zarr.core.sync import sync

    prefix = array.store_path.path
    lead = f"{prefix}/" if prefix else ""

    async def listed() -> list[str]:
        return [key async for key in array.store.list_prefix(lead)]

    grid = tuple(-(-size // chunk) for size, chunk in zip(array.shape, array.chunks))
    numbering = ChunkListing(grid, ())
    stored = {numbering.number(coords) for key in sync(listed())
              if (coords := _chunk_coordinates(array, key[len(lead):])) is not None}
    return ChunkListing(grid, tuple(sorted(stored - {None})))


def _chunk_coordinates(array: zarr.Array, key: str) -> tuple[int, ...] | None:
    """The grid coordinates that ``key`` (relative to the array) names as a chunk of ``array``, or None: its parts
    as integers (Zarr's ``c/0/1`` or ``0.1``), kept when the array encodes them back to the same key. Zarr's own
    decoder fails on its default encoding (zarr 3.1)."""
    parts = re.split(r"[./]", key)
    if parts[:1] == ["c"]:
        parts = parts[1:]
    if not parts or not all(part.isascii() and part.isdigit() for part in parts):
        return None
    coords = tuple(int(part) for part in parts)
    return coords if array.metadata.encode_chunk_key(coords) == key else None


def size_of(url: str) -> int:
    """Bytes stored under a URL (a file, or every file of a directory tree)."""
    fs, path = resolve(url)
    return int(fs.du(path, total=True)) if fs.isdir(path) else int(fs.size(path))


def _location(url: str) -> tuple[str, str]:
    """Where a URL points, the same for every spelling: (kind of filesystem, absolute normalised path).
    Local paths (plain, ``file://``, ``local://``) are resolved: symbolic links, ``..``, a trailing slash."""
    fs, path = _filesystem(url)
    if isinstance(fs, LocalFileSystem):
        return "file", os.path.realpath(path)
    protocol = fs.protocol[0] if isinstance(fs.protocol, (tuple, list)) else fs.protocol
    return str(protocol), posixpath.normpath("/" + str(path).strip("/"))


def _inside(path: str, folder: str) -> bool:
    return path.startswith(folder.rstrip("/") + "/")


def _same_local_file(a: str, b: str) -> bool:
    """One file or folder under two real paths (a hard link, a bind mount)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return False


UNWRITABLE = "is not writable (no permission, or a read-only file system)"


class Unwritable(InputError):
    """An output place this process may not write (no permission, a read-only file system): one line, as any bad
    input, for a command; for the watcher a problem of OUTBOX, not of the recording, retried as a full disk is."""


def check_place(output: str) -> None:
    """Refuse, in one line naming the path, a local output that cannot be written where it is asked for: one
    under a regular file (``file.txt/out.zarr``: "is a file, not a folder"), or in a folder this process may
    not write (the nearest folder that exists, or the output itself when it is an existing folder that
    the command writes into). Object stores are not checked (no folders; their permissions show on write)."""
    fs, path = _filesystem(output)
    if not isinstance(fs, LocalFileSystem):
        return
    shown = str(output) if "://" not in str(output) else path  # the user's own spelling where it is a path
    here, name = os.path.normpath(path), os.path.normpath(shown)
    if os.path.isfile(here) and os.access(here, os.W_OK):  # e.g. a log file appended to
        return
    if os.path.isdir(here):
        if not os.access(here, os.W_OK | os.X_OK):
            raise Unwritable(f"cannot write {output}: the folder {name} {UNWRITABLE}")
        return
    while True:
        here, name = os.path.dirname(here), os.path.dirname(name)
        if os.path.exists(here) or here == os.path.dirname(here):
            break
    if not os.path.isdir(here):
        raise InputError(f"cannot write {output}: {name or here} is a file, not a folder")
    if not os.access(here, os.W_OK | os.X_OK):
        raise Unwritable(f"cannot write {output}: the folder {name or here} {UNWRITABLE}")


def source_of(url: str) -> str | None:
    """What the store at ``url`` records it was made from (its ``source``: a capture, a picture, a spike store), or
    None: an output of a store must not replace that either (``export --overwrite`` onto the capture it was
    ingested from)."""
    try:
        source = open_group(url).attrs.get("source")
    except Unreachable:  # said once, now, not after a second wait for the same answer
        raise
    except Exception:  # noqa: BLE001 - not a store: the command refuses it in its own words
        return None
    if not isinstance(source, str) or not source.strip():
        return None
    try:
        _filesystem(source)  # a place this machine cannot name (gs:// without gcsfs) is no output of ours either
    except InputError:
        return None
    return source


def check_apart(output: str, *inputs: str | None) -> None:
    """Refuse an output that is, is inside, or contains one of a command's inputs (``None``: no such
    input), whatever the spelling (a symbolic link, ``file://``, ``..``, a trailing slash): writing or
    ``--overwrite`` there would destroy the input. Called by every command that writes, before it
    creates or deletes anything; a local output must also have a place to go (:func:`check_place`)."""
    check_place(output)
    kind, out_path = _location(output)
    for source in inputs:
        if source is None or str(source) == "":
            continue
        source_kind, in_path = _location(source)
        if source_kind != kind:
            continue
        if out_path == in_path or (kind == "file" and _same_local_file(out_path, in_path)):
            relation = "is the same as"
        elif _inside(out_path, in_path):
            relation = "is inside"
        elif _inside(in_path, out_path):
            relation = "contains"
        else:
            continue
        real = f" (both are {in_path})" if relation == "is the same as" and str(output) != str(source) else ""
        raise InputError(f"output {output} {relation} input {source}{real}: writing there would destroy or "
                         f"corrupt the input; choose another output")


PENDING_IO_SECONDS = 2.0  # at exit, how long the requests still in flight get to end once cancelled


def cancel_pending_io() -> None:
    """Cancel the requests still in flight on zarr's and fsspec's event loops, each in its own task, and
    give them :data:`PENDING_IO_SECONDS` to end. Registered to run at exit, before zarr stops its loop.

    When one request of a batch fails (zarr reads a group's four metadata objects at once), the others
    go on retrying on the loop's thread; stopped with the interpreter, each is closed outside the task
    and context it ran in, and aiobotocore's clean-up there raises ``ValueError: <Token ...> was created
    in a different Context``, which Python prints as "Exception ignored in: <coroutine ...>" with a
    traceback, tens of lines after the command's one-line error. Cancelled in their own tasks instead,
    they end cleanly and print nothing."""
    import asyncio
    import contextlib

    loops = []
    with contextlib.suppress(Exception):
        from zarr.core import sync as zarr_sync

        loops.append(zarr_sync.loop[0])
    with contextlib.suppress(Exception):
        loops.append(fsspec.asyn.loop[0])

    async def cancel_all() -> None:
        tasks = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=PENDING_IO_SECONDS)

    for loop in loops:
        if loop is None or loop.is_closed() or not loop.is_running():
            continue
        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(cancel_all(), loop).result(PENDING_IO_SECONDS + 1)


atexit.register(cancel_pending_io)  # after zarr's own (imported above): so it runs first
