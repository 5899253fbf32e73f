"""fsspec URLs -> filesystems and Zarr stores; an output kept apart from its inputs; removing a store.

Any location is a URL: a plain path, ``file://``, ``memory://`` (shared within one process),
``s3://`` (s3fs; endpoint and credentials from the usual AWS variables or fsspec's
``FSSPEC_S3_*`` settings). Local paths map to Zarr's ``LocalStore`` (which creates
directories as needed), everything else to ``FsspecStore``.
"""

import itertools
import os
import posixpath
import warnings

import fsspec
import zarr
from fsspec.implementations.local import LocalFileSystem

from stages.errors import InputError, describe


def resolve(url: str) -> tuple[fsspec.AbstractFileSystem, str]:
    """(filesystem, path inside it) for a URL or plain path."""
    try:
        return fsspec.core.url_to_fs(str(url))
    except (ValueError, ImportError) as error:
        raise InputError(f"cannot use URL {url!r}: {error}") from None
    except OSError as error:  # a filesystem that connects on creation (ftp://): no such host, refused, ...
        raise InputError(f"cannot reach {url}: {describe(error)}") from None


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
                                                                NotADirectoryError)):
        cause = f"{name}: {describe(error)}"  # a host not found, a connection refused or timed out
    else:
        return None
    return f"cannot reach {' or '.join(remote)}: {cause}"


def is_local(url: str) -> bool:
    return isinstance(resolve(url)[0], LocalFileSystem)


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
    return zarr.storage.FsspecStore.from_url(str(url), read_only=read_only)


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
    """A location as a store records it (``source``): a URL as given, a local path made absolute, so
    that the record still points to the same place when the store is moved or read from elsewhere."""
    text = str(url)
    return text if "://" in text else os.path.abspath(text)


def consolidate(url: str) -> None:
    """Write consolidated metadata (every array's metadata, in the root ``zarr.json``), as xarray and other
    readers expect. Called once a store's arrays are all declared: array metadata never changes after, and
    the group's own attributes (``state``, written last) live beside the consolidated copy, so later
    attribute updates keep it valid. Zarr warns that v3 has no standard for it yet; xarray reads it."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part", category=UserWarning)
        zarr.consolidate_metadata(zarr_store(url, read_only=False))


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


def missing_chunks(array: zarr.Array) -> list[tuple[int, ...]]:
    """The chunks of ``array`` (grid coordinates) that have no object in its store, from one listing of
    the array's keys (no chunk is read). Our writers store every chunk, empty or not, so a chunk that
    is not there is lost data."""
    from zarr.core.sync import sync

    prefix = array.store_path.path
    lead = f"{prefix}/" if prefix else ""

    async def listed() -> set[str]:
        return {key async for key in array.store.list_prefix(lead)}

    present = sync(listed())
    grid = [-(-size // chunk) for size, chunk in zip(array.shape, array.chunks)]
    return [coords for coords in itertools.product(*map(range, grid))
            if lead + array.metadata.encode_chunk_key(coords) not in present]


def size_of(url: str) -> int:
    """Bytes stored under a URL (a file, or every file of a directory tree)."""
    fs, path = resolve(url)
    return int(fs.du(path, total=True)) if fs.isdir(path) else int(fs.size(path))


def _location(url: str) -> tuple[str, str]:
    """Where a URL points, the same for every spelling: (kind of filesystem, absolute normalised path).
    Local paths (plain, ``file://``, ``local://``) are resolved: symbolic links, ``..``, a trailing slash."""
    fs, path = resolve(url)
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


def check_apart(output: str, *inputs: str | None) -> None:
    """Refuse an output that is, is inside, or contains one of a command's inputs (``None``: no such
    input), whatever the spelling (a symbolic link, ``file://``, ``..``, a trailing slash): writing or
    ``--overwrite`` there would destroy the input. Called by every command that writes, before it
    creates or deletes anything."""
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
