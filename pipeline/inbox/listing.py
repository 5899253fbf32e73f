"""What a pass of ``cscsr watch`` finds in INBOX: the recordings, each with its sidecar and a reason if it cannot be
taken, whether it has stopped changing, and the fingerprint of its bytes.

A pass lists INBOX (any fsspec URL, one level): spike stores (``NAME.zarr``) and raw captures (``NAME.dat``,
``NAME.npz``, ``NAME.npy``) with an optional sidecar ``NAME.json``, in any case (height, width, cfa, flip, fps,
reset, head_columns, key, name; the watcher's defaults fill the rest). Nothing is read through a symbolic link
whose real path leaves INBOX (:func:`_leaves`), nor opened where an entry is not what its name says (:func:`_odd`:
a named pipe's reader waits forever). A recording is taken once it has not changed for ``settle`` seconds (the watcher
checks), and one changed within the last second only if a second look a second later finds the same modification
time, files and bytes (:func:`steady`).
"""

import hashlib
import json
import logging
import os
import re
import time
from dataclasses import dataclass

from fsspec.implementations.local import LocalFileSystem

from pipeline.jobs.ingest import IngestOptions
from pipeline.stores.storage import local_kind, resolve
from stages.errors import InputError, describe

RAW = ("dat", "npz", "npy")
KINDS = ("zarr",) + RAW
SKIPPED_SUFFIXES = ("json", "partial", "tmp", "part", "crdownload")  # sidecars, and uploads still in flight
LONGEST_NAME = 128  # characters of an output name
SAFE_NAME = re.compile(rf"^[A-Za-z0-9][A-Za-z0-9._-]{{0,{LONGEST_NAME - 1}}}$")
SIDECAR_FIELDS = {"height": int, "width": int, "cfa": str, "flip": bool, "fps": (int, float), "reset": str,
                  "head_columns": int, "key": str, "name": str}
SAMPLE = 1 << 20  # bytes read from each end of a file for its fingerprint

log = logging.getLogger("cscsr.watch")


@dataclass(frozen=True)
class Candidate:
    name: str  # output name: OUTBOX/NAME.zarr
    url: str
    kind: str
    sidecar: dict
    modified: float
    problem: str | None = None
    look: tuple = ()  # ((entry, (modification time, files, bytes)), ...) of the recording and its sidecar as listed:
    # a second look compares


class InboxUnavailable(InputError):
    """INBOX cannot be listed (gone, unmounted, not readable): one line; a watcher started with ``--interval`` logs
    it and tries again at its next pass (a remount), one started with ``--once`` ends with it."""


def discover(inbox: str) -> list[Candidate]:
    """The recordings in INBOX (one level), with a reason for each one that cannot be taken. One that cannot be read
    (no permission) is such a reason, for that recording alone; one gone since the listing is left out."""
    fs, root = check_inbox(inbox)
    base_url = str(inbox).rstrip("/")
    try:
        listed = {_base(entry): entry for entry in fs.ls(root, detail=True)}
    except FileNotFoundError:
        raise InboxUnavailable(f"inbox {inbox} does not exist: give the folder where recordings land") from None
    except OSError as error:
        raise InboxUnavailable(f"cannot list inbox {inbox}: {_reason(error)}") from None
    found = []
    for base, entry in sorted(listed.items()):
        suffix = base.rsplit(".", 1)[-1].lower() if "." in base else ""
        if base.startswith(".") or suffix in SKIPPED_SUFFIXES:
            continue
        stem = base[: -len(suffix) - 1] if suffix else base
        try:
            found.append(_candidate(fs, root, f"{base_url}/{base}", listed, entry, stem, suffix))
        except FileNotFoundError:  # moved or deleted since the listing: nothing to take (or to refuse)
            log.info("%s: skipped: gone from the inbox since the pass listed it (%s/%s)", stem, base_url, base)
        except OSError as error:  # no permission: this recording's problem, said once; the others go on
            found.append(Candidate(stem, f"{base_url}/{base}", suffix, {}, 0.0, unreadable(error, root)))
    return found


def _candidate(fs, root: str, url: str, listed: dict, entry: dict, stem: str, suffix: str) -> Candidate:
    """The recording ``entry`` of INBOX as a candidate, with the reason it cannot be taken, if any. Its modification
    time is the latest of the recording's and its sidecar's: a sidecar still being written settles as a capture
    does, and is judged only once settled (the watcher checks ``--settle`` before any problem found in it)."""
    base = _base(entry)
    sidecars = sorted(other for other in listed if other[: len(stem)] == stem and other[len(stem):].lower() == ".json")
    sidecar_base = sidecars[0] if sidecars else f"{stem}.json"  # NAME.json, NAME.JSON, ...: beside NAME.DAT alike
    if isinstance(fs, LocalFileSystem):  # only local folders have symbolic links
        escape = _leaves(root, entry["name"]) or _leaves(root, f"{root}/{sidecar_base}")
        if escape:  # refused before anything (even a modification time) is read through the link
            return Candidate(stem, url, suffix, {}, 0.0, f"{escape} leads outside the inbox: refused (a link out of "
                                                         f"INBOX is never followed)")
    odd = _odd(fs, root, entry, store=suffix == "zarr") or _odd(fs, root, listed.get(sidecar_base), store=False)
    if odd:  # refused before anything is read: a named pipe blocks its reader, a folder fails every read
        return Candidate(stem, url, suffix, {}, 0.0, odd)
    look = ((base, _look(fs, entry)),) + (((sidecar_base, _look(fs, listed[sidecar_base])),) if sidecars else ())
    modified = max(seen[0] for _, seen in look)
    if suffix not in KINDS:
        return Candidate(stem, url, suffix, {}, modified,
                         f"unknown kind of file {base!r}: expected NAME.zarr, .dat, .npz or .npy", look)
    if len(sidecars) > 1:
        return Candidate(stem, url, suffix, {}, modified, f"{len(sidecars)} sidecars for {base}: "
                                                          f"{', '.join(sidecars)}: keep one", look)
    sidecar, problem = _sidecar(fs, f"{root}/{sidecar_base}") if sidecars else ({}, None)
    name = sidecar.get("name", stem)
    if problem is None and (not SAFE_NAME.match(name) or ".." in name):
        problem = f"unsafe name {name!r}: letters, digits, '.', '_' and '-' only, no '..'"
        if len(name) > LONGEST_NAME and SAFE_NAME.match(name[:LONGEST_NAME]) and ".." not in name:
            problem = (f"name {name!r} is {len(name)} characters long: at most {LONGEST_NAME} (rename the recording, "
                       f"or give its sidecar a shorter 'name')")
    problem = problem or _misfit_fields(sidecar, sidecar_base, base, suffix)
    return Candidate(name, url, suffix, sidecar, modified, problem, look)


def unreadable(error: OSError, root: str) -> str:
    """Why a recording (or its sidecar, or a file of its store) cannot be read, in one line naming the file within
    INBOX: ``cannot read a.dat: permission denied``. Recorded as its refusal; a later pass that can read it takes
    it (each pass looks again)."""
    path = str(error.filename or "").rstrip("/")
    inside = root.rstrip("/") + "/"
    shown = path[len(inside):] if path.startswith(inside) else path or "it"
    return f"cannot read {shown}: {_reason(error)} (a later pass takes it once it can be read)"


def _reason(error: OSError) -> str:
    """An OS error's reason alone, lower case: ``permission denied``."""
    reason = error.strerror or describe(error)
    return reason[:1].lower() + reason[1:]


def canonical(inbox: str) -> str:
    """INBOX as the ledger knows it: a local folder by its absolute real path, so that ``in``, ``./in/``,
    ``$PWD/in``, ``file://$PWD/in`` and a link to it are one inbox, whose recordings are done, refused and shown
    once; any other URL as given, less a trailing slash."""
    fs, path = resolve(inbox)
    return os.path.realpath(path) if isinstance(fs, LocalFileSystem) else str(inbox).rstrip("/")


def check_inbox(inbox: str):
    """(filesystem, path) of INBOX; refused in one line unless it is a folder (before OUTBOX is made)."""
    fs, root = resolve(inbox)
    if not fs.isdir(root):
        if not fs.exists(root):  # at the start, or at a later pass (unmounted)
            raise InboxUnavailable(f"inbox {inbox} does not exist: give the folder where recordings land")
        raise InputError(f"inbox {inbox} is a file, not a folder: give the folder where recordings land")
    if any(fs.exists(f"{root.rstrip('/')}/{name}") for name in ("zarr.json", ".zgroup", ".zarray")):
        raise InputError(f"inbox {inbox} is a Zarr store, not a folder of recordings: give the folder where "
                         f"recordings land (a NAME.zarr there is taken as one)")
    return fs, root


def _base(entry: dict) -> str:
    """The name of a listed entry within its folder."""
    return entry["name"].rstrip("/").rsplit("/", 1)[-1]


def _odd(fs, root: str, entry: dict | None, *, store: bool) -> str | None:
    """Why an INBOX entry as listed (a recording, or the sidecar beside one) is not what its name says it is, in
    one line; None if it is, or if nothing is there. A ``NAME.zarr`` recording (``store``) is a folder of folders
    and regular files; every other entry read (a raw capture, a sidecar) is a regular file. Told without opening
    anything (``os.stat``, through a link that stays in INBOX: links out are refused before this), since a named
    pipe's reader waits forever for a writer and a folder read as a file fails every pass. An object store holds
    files and folders (prefixes) only, as listed."""
    if entry is None:
        return None
    local = isinstance(fs, LocalFileSystem)
    path = entry["name"].rstrip("/")
    name = os.path.relpath(path, root) if local else path[len(root.rstrip("/")) + 1 :]
    what = local_kind(path) if local else ("a folder" if entry.get("type") == "directory" else "a regular file")
    if what is None:
        return None  # gone since the listing
    if store and what != "a folder":
        return f"{name} is {what}, not a folder: refused (a NAME.zarr recording is the folder of a Zarr store)"
    if not store and what != "a regular file":
        return f"{name} is {what}, not a regular file: refused (only regular files and NAME.zarr folders are read)"
    if store and local:
        for folder, dirs, files in os.walk(path):  # as _leaves walks: a link to a folder is not followed
            for inner in files:
                inside = os.path.join(folder, inner)
                if (what := local_kind(inside)) not in ("a regular file", None):
                    return (f"{os.path.relpath(inside, root)} is {what}, not a regular file: refused (a Zarr "
                            f"store holds folders and regular files only)")
    return None


def _leaves(root: str, path: str) -> str | None:
    """The first symbolic link at or under ``path`` whose real path is outside the local folder
    ``root`` (INBOX), as ``NAME -> TARGET``; None if everything stays inside (or nothing is there)."""
    real_root = os.path.realpath(root).rstrip("/") + "/"

    def outside(entry: str) -> str | None:
        target = os.path.realpath(entry)
        return None if target.startswith(real_root) else f"{os.path.relpath(entry, root)} -> {target}"

    if not os.path.lexists(path):
        return None
    if os.path.islink(path) or not os.path.isdir(path):
        return outside(path)
    for folder, dirs, files in os.walk(path):  # never follows a link to a folder: each is checked instead
        for name in dirs + files:
            entry = os.path.join(folder, name)
            if os.path.islink(entry) and (escape := outside(entry)):
                return escape
    return None


def _look(fs, entry: dict) -> tuple[float, int, int]:
    """(latest modification time, files, bytes) of a file, or of every file under a directory (a Zarr store)."""
    def stamp(info):
        value = info.get("mtime") or info.get("LastModified") or info.get("created") or 0
        return value.timestamp() if hasattr(value, "timestamp") else float(value)

    if entry.get("type") == "directory":
        files = fs.find(entry["name"], detail=True).values()
        return (max([stamp(info) for info in files] + [stamp(entry)]), len(files),
                sum(int(info.get("size") or 0) for info in files))
    return stamp(entry), 1, int(entry.get("size") or 0)


SECOND_LOOK = 1.0  # seconds: a recording changed more recently than this is looked at again before it is taken


def steady(candidate: Candidate) -> bool:
    """Whether a recording has stopped changing. One unchanged for a second or more is taken as it is (the
    ``--settle`` check before this has already waited as long as the user asked); one changed within the
    last second (``--settle`` under 1) is looked at again a second after that change, and taken only if its
    modification time, files and bytes (and its sidecar's) are the same as when it was listed. A writer that
    pauses longer than ``--settle`` (and than a second) between writes is not seen: ``--settle`` must exceed its
    pauses."""
    quiet = time.time() - candidate.modified
    if quiet >= SECOND_LOOK or not candidate.look:
        return True
    time.sleep(min(SECOND_LOOK, SECOND_LOOK - quiet))  # a clock ahead of ours (a remote store's) waits a second
    fs, path = resolve(candidate.url)
    parent = str(path).rstrip("/").rsplit("/", 1)[0]
    fs.invalidate_cache()  # an object store's listing cache would show the first look again
    names = dict(candidate.look)
    again = {_base(entry): _look(fs, entry) for entry in fs.ls(parent, detail=True) if _base(entry) in names}
    return again == names  # as the first look saw them (a link's own time, not its target's); one moved away: no


def _sidecar(fs, path: str) -> tuple[dict, str | None]:
    if not fs.exists(path):
        return {}, None
    name = path.rsplit("/", 1)[-1]
    try:
        values = json.loads(fs.cat_file(path))
    except (ValueError, UnicodeDecodeError) as error:
        return {}, f"sidecar {name} is not JSON ({error})"
    if not isinstance(values, dict):
        return {}, f"sidecar {name} must be a JSON object, got {type(values).__name__}"
    for key, value in values.items():
        kind = SIDECAR_FIELDS.get(key)
        if kind is None:
            return {}, f"sidecar {name}: unknown field {key!r} (known: {', '.join(SIDECAR_FIELDS)})"
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            return {}, f"sidecar {name}: {key} must be {getattr(kind, '__name__', 'a number')}, got {value!r}"
    try:  # its values as ingest checks them, said as the sidecar's fields, not as options nobody gave
        IngestOptions(**{k: v for k, v in values.items() if k != "name"}).check()
    except InputError as error:
        return {}, f"sidecar {name}: " + re.sub(r"--([a-z][a-z-]*)", lambda m: m[1].replace("-", "_"), str(error))
    return values, None


def _misfit_fields(sidecar: dict, sidecar_base: str, base: str, suffix: str) -> str | None:
    """Why a sidecar's fields do not fit the recording ``base`` beside it, in one line, or None: beside a spike
    store (``NAME.zarr``, which records its own size, CFA and rate) only ``name`` applies; ``key`` names an array
    inside a ``.npz``, and other captures have none. Refused rather than ignored: the sender meant something by
    them."""
    if suffix == "zarr":
        fields = sorted(field for field in sidecar if field != "name")
        if fields:
            one = len(fields) == 1
            return (f"sidecar {sidecar_base}: {', '.join(fields)} describe{'s' if one else ''} a raw capture, and "
                    f"{base} is a spike store, which records its own: remove {'it' if one else 'them'} (only 'name' "
                    f"applies to a store)")
    elif "key" in sidecar and suffix != "npz":
        return f"sidecar {sidecar_base}: key names an array inside a .npz, and {base} has none: remove it"
    return None


def fingerprint(candidate: Candidate) -> str:
    """A hash of the recording's bytes: size and both ends of a file; every file's size and the
    metadata of a Zarr store. Renaming a recording does not change it; changing it does."""
    fs, path = resolve(candidate.url)
    digest = hashlib.sha256()
    if candidate.kind == "zarr":
        for name, info in sorted(fs.find(path, detail=True).items()):
            relative = name[len(path.rstrip("/")) :]
            digest.update(f"{relative}:{info['size']};".encode())
            if relative.endswith("zarr.json"):
                digest.update(fs.cat_file(name))
    else:
        size = fs.size(path)
        digest.update(f"{candidate.kind}:{size};".encode())
        with fs.open(path, "rb") as f:
            digest.update(f.read(SAMPLE))
            if size > SAMPLE:
                f.seek(max(size - SAMPLE, SAMPLE))
                digest.update(f.read())
    return digest.hexdigest()
