"""Outputs claimed before they are written: an existing output is refused unless the user asked to
replace it, never one that another live job is writing (``pipeline.lease``), and an output whose
writing fails is removed, so no half-written output stays to look complete.

Only what cscsr wrote is ever replaced (:func:`not_ours`): a Zarr store that it marked as its own,
a folder holding its marker file (or only its exported frames), a file of the kind the command
writes whose bytes are of that kind (an MP4, a PNG, ...). A user's folder or file is refused in
one line, ``--overwrite`` or not.

A replaced output is not deleted before its successor exists: on a local filesystem the old one is
renamed to a hidden sibling ``.NAME.old-<id>`` (one atomic rename) and deleted only once the new one
is complete; if the job fails, the new one is removed and the old one renamed back. A job killed
outright (SIGKILL, power loss) leaves the old one under that name (the next complete output at
NAME removes it). Object stores (``s3://``, ``memory://``) have no rename: there the old output is
removed first (a documented limit, ``docs/reliability.md``)."""

import contextlib
import json
import logging
import os
import re
import shutil
import uuid
from collections.abc import Iterator

import cscsr
from pipeline.lease import check_free
from pipeline.storage import exists, is_local, remove, resolve
from stages.errors import InputError

log = logging.getLogger("cscsr.outputs")

MARKER = ".cscsr-output"  # inside a folder output of ours: {"kind": ..., "cscsr_version": ...}
ASIDE = ".{name}.old-"  # the old output while its successor is written (local filesystems)

# Kinds of output (what a command writes); a file kind is its suffix.
STORE, TESTSET, EVALUATION, FRAMES = "store", "testset", "evaluation", "frames"
_WHAT = {STORE: "a Zarr store written by cscsr", TESTSET: "a test set made by cscsr make-testset",
         EVALUATION: "an evaluation written by cscsr evaluate or evaluate-testset",
         FRAMES: "a folder of frames exported by cscsr (frame_<centre>.png)", ".dat": "a .dat file",
         ".mp4": "an MP4 video"}
_MAGIC = {".png": lambda b: b.startswith(b"\x89PNG\r\n\x1a\n"), ".jpg": lambda b: b.startswith(b"\xff\xd8\xff"),
          ".jpeg": lambda b: b.startswith(b"\xff\xd8\xff"), ".bmp": lambda b: b.startswith(b"BM"),
          ".tif": lambda b: b[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),
          ".tiff": lambda b: b[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),
          ".webp": lambda b: b[:4] == b"RIFF" and b[8:12] == b"WEBP", ".mp4": lambda b: b[4:8] == b"ftyp",
          ".dat": lambda b: True}  # raw bits: any bytes are a capture
_FRAME = re.compile(r"frame_\d+\.png")


def kind_of(url: str) -> str:
    """The kind of output a URL names when the command does not say: a file kind by its suffix, else a store."""
    suffix = os.path.splitext(str(url).rstrip("/"))[1].lower()
    return suffix if suffix in _MAGIC else STORE


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
        if kind == STORE:
            root = _json(fs, f"{path}/zarr.json")
            if not isinstance(root, dict):
                return _holding(names)
            attrs = root.get("attributes")
            if root.get("node_type") == "group" and isinstance(attrs, dict) and \
                    ("cscsr_version" in attrs or "format_version" in attrs):
                return None
            return "a Zarr store that cscsr did not write"
        marker = _json(fs, f"{path}/{MARKER}") if MARKER in names else None
        if isinstance(marker, dict) and marker.get("kind") == kind:
            return None
        if kind == FRAMES and all(_FRAME.fullmatch(name) for name in names):
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


def check_ours(url: str, kind: str) -> None:
    """Refuse to replace ``url`` unless it is an output of ``kind`` that cscsr wrote (see :func:`not_ours`)."""
    if (why := not_ours(url, kind)) is not None:
        what = _WHAT.get(kind) or f"a {kind[1:].upper()} image"
        raise InputError(f"output {url} already exists and is not {what} ({why}): cscsr replaces only its own "
                         f"outputs, even with --overwrite; choose another output, or move it away yourself")


def mark_folder(url: str, kind: str) -> None:
    """Create the folder ``url`` (if need be) and mark it as an output of ``kind`` of ours."""
    fs, path = resolve(url)
    path = str(path).rstrip("/")
    fs.makedirs(path, exist_ok=True)
    fs.pipe_file(f"{path}/{MARKER}", json.dumps({"kind": kind, "cscsr_version": cscsr.__version__}).encode())


def _check_existing(url: str, *, overwrite: bool, kind: str | None, flag: str) -> bool:
    """For an output about to be written: True if one exists and may be replaced; refuses otherwise."""
    if not exists(url):
        return False
    check_free(url)
    check_ours(url, kind or kind_of(url))
    if not overwrite:
        raise InputError(f"output {url} already exists (pass {flag} to replace it)")
    return True


def claim_output(url: str, *, overwrite: bool, flag: str = "--overwrite", kind: str | None = None) -> None:
    """Refuse an existing output unless ``overwrite`` and it is ours (of ``kind``; by default, as its name
    says); with it, remove the old output at once (never one that another live job is writing: see
    :mod:`pipeline.lease`). Prefer :func:`new_output`, which keeps the old one until the new one exists."""
    if _check_existing(url, overwrite=overwrite, kind=kind, flag=flag):
        remove(url)


def _asides(url: str) -> tuple[str, list[str]]:
    """(folder, names) of the old outputs set aside beside the local output ``url``."""
    path = os.path.abspath(resolve(url)[1]).rstrip("/")
    folder, name = os.path.split(path)
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
    path = os.path.abspath(resolve(url)[1]).rstrip("/")
    folder, name = os.path.split(path)
    aside = os.path.join(folder, ASIDE.format(name=name) + uuid.uuid4().hex[:12])
    try:
        os.rename(path, aside)
    except OSError as error:
        raise InputError(f"cannot replace output {url}: renaming it aside to {aside} failed "
                         f"({error.strerror or error}); nothing was changed") from None
    return aside


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
def new_output(url: str, *, overwrite: bool, kind: str | None = None, flag: str = "--overwrite",
               resume: bool = False, keep_partial: bool = False) -> Iterator[None]:
    """Claim ``url`` for a new output of ``kind`` (default: as its name says) while the block writes it.

    An existing output is refused unless ``overwrite`` and it is ours. The old output is kept until
    the block has succeeded (see the module docstring); if the block fails, the new output is removed
    and the old one put back. ``keep_partial``: a new output that the block created is kept on
    failure, for ``--resume`` (``reconstruct``); the old one then stays set aside, named in a warning,
    until the output is complete. ``resume``: the output exists and is finished by the block (nothing
    is claimed); once it is complete, old outputs set aside by an earlier run are removed."""
    local = is_local(url)
    aside = None
    if not resume and _check_existing(url, overwrite=overwrite, kind=kind, flag=flag):
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
        with contextlib.suppress(Exception):
            remove(url)
        if aside is not None:
            with contextlib.suppress(OSError):
                os.rename(aside, os.path.abspath(resolve(url)[1]).rstrip("/"))
        raise
    if local and (aside is not None or resume):
        folder, names = _asides(url)
        for name in names:  # this one's, and any that a killed run left
            with contextlib.suppress(OSError):
                _delete(os.path.join(folder, name))
