"""Outputs claimed before they are written: an existing output is refused unless the user asked to
replace it, never one that another live job is writing (``pipeline.stores.lease``), and an output whose
writing fails is removed, so no half-written output stays to look complete.

Only what cscsr wrote is ever replaced (:func:`not_ours`): a Zarr store of the kind the command
writes that it marked as its own (``cscsr_version``): a spike store for ``ingest`` and ``simulate``,
a video store for ``reconstruct``, never one for the other (a spike store is a recording, perhaps
the only copy); a folder holding its marker file (or only its exported frames); a file of the kind
the command writes whose bytes are of that kind (an MP4, a PNG, ...). A user's folder or file is
refused in one line, ``--overwrite`` or not.

A replaced output is not deleted before its successor exists: on a local filesystem the old one is
renamed to a hidden sibling ``.NAME.old-<id>`` (one atomic rename) and deleted only once the new one
is complete; if the job fails, the new one is removed and the old one renamed back (a warning names
it if that fails). A job killed outright (SIGKILL, power loss) leaves the old one under that name
(the next job that completes an output at NAME removes it). Object stores (``s3://``,
``memory://``) have no rename: there the old output is removed first (a documented limit,
``docs/reliability.md``)."""

import contextlib
import json
import logging
import os
import re
import shutil
import uuid
from collections.abc import Iterator

from cscsr.version import __version__
from pipeline.stores.lease import check_free
from pipeline.stores.spike_store import SPIKES
from pipeline.stores.storage import exists, is_local, open_group, remove, resolve
from pipeline.stores.video_store import is_video_store
from stages.errors import InputError, exists_error, not_ours_error, unfinished_error

log = logging.getLogger("cscsr.outputs")

MARKER = ".cscsr-output"  # inside a folder output of ours: {"kind": ..., "cscsr_version": ...}
ASIDE = ".{name}.old-"  # the old output while its successor is written (local filesystems)

# Kinds of output (what a command writes); a file kind is its suffix.
SPIKE_STORE, VIDEO_STORE = "spike store", "video store"
TESTSET, EVALUATION, FRAME_FOLDER = "testset", "evaluation", "frames"  # as written in MARKER
_WHAT = {SPIKE_STORE: "a spike store written by cscsr ingest or simulate",
         VIDEO_STORE: "a video store written by cscsr reconstruct", TESTSET: "a test set made by cscsr make-testset",
         EVALUATION: "an evaluation written by cscsr evaluate or evaluate-testset",
         FRAME_FOLDER: "a folder of frames exported by cscsr (frame_<centre>.png)", ".dat": "a .dat file",
         ".mp4": "an MP4 video"}
_STORES = {SPIKE_STORE: "a spike store (a recording)", VIDEO_STORE: "a video store"}  # what one is found to be
_TIFF = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # little/big endian, classic/BigTIFF
# The images we read and write, by suffix: a test of a file's first 16 bytes saying it is one
# (what ``--overwrite`` replaces; ``pipeline.stores.images`` reads and writes these).
IMAGE_MAGIC = {".png": lambda b: b.startswith(b"\x89PNG\r\n\x1a\n"), ".jpg": lambda b: b.startswith(b"\xff\xd8\xff"),
               ".jpeg": lambda b: b.startswith(b"\xff\xd8\xff"), ".tif": lambda b: b[:4] in _TIFF,
               ".tiff": lambda b: b[:4] in _TIFF, ".bmp": lambda b: b.startswith(b"BM"),
               ".webp": lambda b: b[:4] == b"RIFF" and b[8:12] == b"WEBP"}
_MAGIC = {**IMAGE_MAGIC, ".mp4": lambda b: b[4:8] == b"ftyp",
          ".dat": lambda b: True}  # raw bits: any bytes are a capture
_FRAME = re.compile(r"frame_\d+\.png")
# Names that say "a file of this format": a Zarr store (a folder) under one was taken for that file
# (``reconstruct rec.zarr out.mp4`` wrote a store named out.mp4, no video).
_FILE_NAMES = {**{suffix: "a picture" for suffix in IMAGE_MAGIC}, ".gif": "a picture",
               **{suffix: "a video file" for suffix in (".mp4", ".avi", ".mov", ".mkv", ".webm")},
               ".dat": "a raw capture", ".npy": "a NumPy array", ".npz": "NumPy arrays", ".bin": "a raw file",
               ".h5": "an HDF5 file", ".hdf5": "an HDF5 file", ".mat": "a MATLAB file", ".json": "a JSON file",
               ".csv": "a CSV table", ".txt": "a text file"}
_EXPORTS = {VIDEO_STORE: "cscsr export {store} VIDEO.mp4 or FOLDER/ makes the video",
            SPIKE_STORE: "cscsr export {store} CAPTURE.dat writes the raw capture"}


def _names(fs, path: str) -> list[str]:
    return sorted(str(entry).rstrip("/").rsplit("/", 1)[-1] for entry in fs.ls(path, detail=False))


def _holding(names: list[str]) -> str:
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return f"a folder holding {shown}"


def _json(fs, path: str):
    try:
        return json.loads(fs.cat_file(path))
    except (OSError, ValueError):
        return None


def not_ours(url: str, kind: str) -> str | None:
    """Why the thing at ``url`` is not an output of ``kind`` that cscsr wrote (a few words), or None if it
    is one (or holds nothing to lose: an empty folder or file, or nothing at all)."""
    fs, path = resolve(url)
    path = str(path).rstrip("/") or path
    try:
        is_dir = fs.isdir(path)
        if not is_dir and not fs.exists(path):
            return None
        names = _names(fs, path) if is_dir else []
        if (is_dir and not names) or (not is_dir and fs.size(path) == 0):
            return None  # nothing in it to lose
        if kind.startswith("."):  # a file kind
            if is_dir:
                return _holding(names)
            with fs.open(path, "rb") as handle:
                head = handle.read(16)
            return None if _MAGIC.get(kind, lambda b: False)(head) else f"a file that is not {kind[1:].upper()}"
        if not is_dir:
            return "a regular file"
        if kind in _STORES:
            return _not_our_store(url, fs, path, names, kind)
        marker = _json(fs, f"{path}/{MARKER}") if MARKER in names else None
        if isinstance(marker, dict) and marker.get("kind") == kind:
            return None
        if kind == FRAME_FOLDER and all(_FRAME.fullmatch(name) for name in names):
            return None
        if kind == TESTSET and isinstance(manifest := _json(fs, f"{path}/manifest.json"), dict) \
                and "items" in manifest and "hr_side" in manifest:
            return None  # a test set made before markers
        if kind == EVALUATION and "summary.csv" in names and {"crops.png", "comparison.png"} & set(names) \
                and MARKER not in names:
            return None  # an evaluation written before markers (evaluate-testset's, evaluate's)
        return _holding(names)
    except OSError as error:
        return f"it cannot be read: {error.strerror or error}"


def _not_our_store(url: str, fs, path: str, names: list[str], kind: str) -> str | None:
    """Why the folder at ``url`` is not a Zarr store of ``kind`` that cscsr wrote (one of :data:`_STORES`'s
    words where it is cscsr's store of the other kind), or None. Every spike and video store cscsr has
    written carries ``cscsr_version`` in its group's attributes (spike stores from the first, video
    stores since ``format_version`` 1, which came with it)."""
    root = _json(fs, f"{path}/zarr.json")
    if not isinstance(root, dict):
        return _holding(names)
    attrs = root.get("attributes")
    if root.get("node_type") != "group" or not isinstance(attrs, dict) or "cscsr_version" not in attrs:
        return "a Zarr store that cscsr did not write"
    try:
        group = open_group(url)
        found = VIDEO_STORE if is_video_store(group) else SPIKE_STORE if SPIKES in group else None
    except Exception:  # a damaged store: zarr raises its own error types
        return "a Zarr store of cscsr's that cannot be read"
    if found == kind:
        return None
    return _STORES[found] if found else "a Zarr store of cscsr's that is neither a spike store nor a video store"


def check_ours(url: str, kind: str) -> None:
    """Refuse to replace ``url`` unless it is an output of ``kind`` that cscsr wrote (see :func:`not_ours`)."""
    if (why := not_ours(url, kind)) is None:
        return
    if kind in _STORES and why in _STORES.values():  # ours, but a store of the other kind
        raise InputError(f"output {url} is {why}, not a {kind}: --overwrite replaces only "
                         f"{_WHAT[kind]}; choose another output")
    raise not_ours_error(url, _WHAT.get(kind) or f"a {kind[1:].upper()} image", why)


def mark_folder(url: str, kind: str) -> None:
    """Create the folder ``url`` (if need be) and mark it as an output of ``kind`` of ours."""
    fs, path = resolve(url)
    path = str(path).rstrip("/")
    fs.makedirs(path, exist_ok=True)
    fs.pipe_file(f"{path}/{MARKER}", json.dumps({"kind": kind, "cscsr_version": __version__}).encode())


def check_existing(url: str, *, overwrite: bool, kind: str, flag: str) -> bool:
    """For an output about to be written: True if one exists and may be replaced; refuses otherwise (a new store
    under a file format's name too)."""
    if not exists(url):
        check_store_name(url, kind)
        return False
    check_free(url)
    check_ours(url, kind)
    if not overwrite:
        raise unfinished_error(url, left, flag) if (left := leftover(url, kind)) else exists_error(url, flag)
    return True


def check_store_name(url: str, kind: str) -> None:
    """Refuse a new Zarr store of ``kind`` named as a file of another format (``out.mp4``, ``rec.dat``): the user
    asked for that file, and would get a folder of Zarr chunks under its name."""
    suffix = os.path.splitext(str(url).rstrip("/"))[1].lower()
    if kind in _STORES and suffix in _FILE_NAMES:
        store = str(url).rstrip("/")[: -len(suffix)] + ".zarr"
        raise InputError(f"{url} names {_FILE_NAMES[suffix]}, but this writes a {kind} (a Zarr folder): name it "
                         f"{store} ({_EXPORTS[kind].format(store=store)})")


def leftover(url: str, kind: str) -> str | None:
    """What the store of ``kind`` at ``url`` is, in a few words, when its writer did not finish it (its ``state`` is
    not "complete": an interrupted or killed ``simulate``, ``ingest`` or ``reconstruct``); None for a finished store,
    any other output, or one that cannot be read."""
    if kind not in _STORES:
        return None
    fs, path = resolve(url)
    root = _json(fs, f"{str(path).rstrip('/')}/zarr.json")
    attrs = root.get("attributes") if isinstance(root, dict) else None
    if not isinstance(attrs, dict) or attrs.get("state", "complete") == "complete":
        return None
    writer = "reconstruct" if kind == VIDEO_STORE else "simulate" if attrs.get("simulated") else "ingest"
    return f"an incomplete {kind} (state {attrs['state']!r}), the leftover of an interrupted {writer}"


def _local_path(url: str) -> str:
    """The absolute path of the local output ``url``, without a trailing slash."""
    return os.path.abspath(resolve(url)[1]).rstrip("/")


def _asides(url: str) -> tuple[str, list[str]]:
    """(folder, names) of the old outputs set aside beside the local output ``url``."""
    folder, name = os.path.split(_local_path(url))
    prefix = ASIDE.format(name=name)
    try:
        return folder, [entry for entry in os.listdir(folder or ".") if entry.startswith(prefix)]
    except OSError:
        return folder, []


def _delete(path: str) -> None:
    if os.path.islink(path) or not os.path.isdir(path):
        os.unlink(path)  # a link to an output: the link is what was replaced
    else:
        shutil.rmtree(path)


def _set_aside(url: str) -> str:
    """Rename the local output ``url`` to a hidden sibling; -> its new path."""
    path = _local_path(url)
    folder, name = os.path.split(path)
    aside = os.path.join(folder, ASIDE.format(name=name) + uuid.uuid4().hex[:12])
    try:
        os.rename(path, aside)
    except OSError as error:
        raise InputError(f"cannot replace output {url}: renaming it aside to {aside} failed "
                         f"({error.strerror or error}); nothing was changed") from None
    return aside


@contextlib.contextmanager
def new_output(url: str, *, overwrite: bool, kind: str, flag: str = "--overwrite",
               resume: bool = False, keep_partial: bool = False) -> Iterator[None]:
    """Claim ``url`` for a new output of ``kind`` (:data:`SPIKE_STORE`, ..., or a file's suffix) while the block
    writes it.

    An existing output is refused unless ``overwrite`` and it is ours. The old output is kept until
    the block has succeeded (see the module docstring); if the block fails, the new output is removed
    and the old one put back. ``keep_partial``: a new output that the block created is kept on
    failure, for ``--resume`` (``reconstruct``); the old one then stays set aside, named in a warning,
    until the output is complete. ``resume``: the output exists and is finished by the block (nothing
    is claimed). Once the output is complete, every old output set aside at ``url`` (this run's, and any
    that a killed or failed run left) is removed."""
    local = is_local(url)
    aside = None
    if not resume and check_existing(url, overwrite=overwrite, kind=kind, flag=flag):
        if local:
            aside = _set_aside(url)
        else:
            remove(url)  # object stores: no rename (docs/reliability.md, "Known gaps")
    try:
        yield
    except BaseException:
        if resume:
            raise
        if keep_partial and exists(url):
            if aside is not None:
                log.warning("the old %s is kept as %s until the new one is complete (rename it back to keep it)",
                            url, aside)
            raise
        unremoved = ""
        try:
            remove(url)
        except Exception as error:
            unremoved = f"the new, unfinished {url} could not be removed ({getattr(error, 'strerror', None) or error})"
        if aside is not None:
            try:
                os.rename(aside, _local_path(url))
            except OSError as error:
                log.warning("the old %s could not be put back (%s%s): it is kept as %s (rename it back to keep it)",
                            url, error.strerror or error, f"; {unremoved}" if unremoved else "", aside)
        elif unremoved:
            log.warning("%s: remove it before using it", unremoved)
        raise
    if local:
        folder, names = _asides(url)
        for name in names:  # this one's, and any that a killed run left
            with contextlib.suppress(OSError):
                _delete(os.path.join(folder, name))
