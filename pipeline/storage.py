"""fsspec URLs -> filesystems and Zarr stores, and removal of outputs that did not finish.

Any location is a URL: a plain path, ``file://``, ``memory://`` (shared within one process),
``s3://`` (s3fs; endpoint and credentials from the usual AWS variables or fsspec's
``FSSPEC_S3_*`` settings). Local paths map to Zarr's ``LocalStore`` (which creates
directories as needed), everything else to ``FsspecStore``.
"""

import contextlib
from collections.abc import Iterator

import fsspec
import zarr
from fsspec.implementations.local import LocalFileSystem

from stages.errors import InputError


def resolve(url: str) -> tuple[fsspec.AbstractFileSystem, str]:
    """(filesystem, path inside it) for a URL or plain path."""
    try:
        return fsspec.core.url_to_fs(str(url))
    except (ValueError, ImportError) as error:
        raise InputError(f"cannot use URL {url!r}: {error}") from None


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


def open_group(url: str, what: str = "store") -> zarr.Group:
    """The Zarr group at ``url``, read-only; a one-line error if it is missing, an array, or damaged."""
    try:
        return zarr.open_group(zarr_store(url, read_only=True), mode="r")
    except FileNotFoundError:
        raise InputError(f"cannot read {what} {url}: no Zarr group there") from None
    except zarr.errors.ContainsArrayError:
        raise InputError(f"cannot read {what} {url}: it holds a Zarr array, not a group") from None
    except (ValueError, TypeError, KeyError, AttributeError, zarr.errors.BaseZarrError) as error:
        raise InputError(f"cannot read {what} {url}: its Zarr metadata is damaged ({describe(error)})") from None


def describe(error: BaseException) -> str:
    """An exception as one line of text."""
    return " ".join(str(error).split()) or type(error).__name__


def size_of(url: str) -> int:
    """Bytes stored under a URL (a file, or every file of a directory tree)."""
    fs, path = resolve(url)
    return int(fs.du(path, total=True)) if fs.isdir(path) else int(fs.size(path))


def claim_output(url: str, *, overwrite: bool, flag: str = "--overwrite") -> None:
    """Refuse an existing output unless ``overwrite``; with it, clear the old output (never one that
    another live job is writing: see :mod:`pipeline.lease`)."""
    if exists(url):
        from pipeline.lease import check_free

        check_free(url)
        if not overwrite:
            raise InputError(f"output {url} already exists (pass {flag} to replace it)")
        remove(url)


@contextlib.contextmanager
def removed_on_failure(url: str) -> Iterator[None]:
    """Delete ``url`` if the block raises (or is interrupted): no half-written output stays."""
    try:
        yield
    except BaseException:
        with contextlib.suppress(Exception):
            remove(url)
        raise


@contextlib.contextmanager
def new_output(url: str, *, overwrite: bool, flag: str = "--overwrite") -> Iterator[None]:
    """Claim ``url`` for a new output (refusing an existing one first), removed if the block fails."""
    claim_output(url, overwrite=overwrite, flag=flag)
    with removed_on_failure(url):
        yield
