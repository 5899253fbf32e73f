"""``cscsr watch``: reconstruct recordings as they land in an inbox, exactly once each.

Each pass lists INBOX (any fsspec URL): spike stores (``NAME.zarr``) and raw captures
(``NAME.dat``, ``NAME.npz``, ``NAME.npy``) with an optional sidecar ``NAME.json`` (height,
width, cfa, flip, fps, reset, head_columns, key, name; the watcher's defaults fill the
rest). A raw capture's CFA is never guessed: it comes from its sidecar or ``--cfa``, and a capture
with neither is refused (:func:`unstated`): taken as the wrong one, a mono capture would be
demosaicked into colour speckle, or a Bayer one shown grey with its mosaic, and no error said so.
A recording is taken once it has not changed for ``settle`` seconds (a file still
being copied is left for a later pass; ``settle`` must exceed the writer's longest pause), and
one changed within the last second only if a second look a second later finds the same
modification time, files and bytes (:func:`steady`). For each: ingest a raw capture into
``OUTBOX/spikes/NAME.zarr``, reconstruct into ``OUTBOX/NAME.zarr``, export
``OUTBOX/NAME.mp4``; the ledger (:mod:`pipeline.inbox.ledger`) records every step's outcome. No two
recordings share an output path (:func:`spike_store_of`), and OUTBOX may not be, be inside, or
contain INBOX.

Killing the watcher at any moment loses nothing and duplicates nothing: the ledger row it
left ``running`` is taken up by the next pass, whose reconstruction resumes from the
committed tiles, and outputs are named by the recording, so there is never a second copy.
Bad input (unknown extension, unsafe name, nonsense sidecar, truncated capture, a symbolic link
anywhere in a recording or its sidecar whose real path leaves INBOX, an entry that is not what its name
says, such as a folder, named pipe, socket or device where a regular file belongs, :func:`_odd`) is recorded
as failed with its reason and never stops the other recordings; other errors are retried
with exponential back-off, then quarantined. Names are checked so no output can land
outside OUTBOX. One watcher per OUTBOX at a time (a lock file).

Every event is one record of the ``cscsr.watch`` logger, naming the recording: found, claimed,
ingested, reconstructed, exported, done (INFO); will retry (WARNING); failed or quarantined, with
the reason (ERROR); skipped, still settling (DEBUG); one summary per pass (INFO). The library
never configures logging: ``cscsr watch`` sends these to standard error or ``--log-file``.
"""

import fcntl
import hashlib
import json
import logging
import os
import re
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from fsspec.implementations.local import LocalFileSystem

from pipeline.compute.cluster import check_in_memory, dask_client
from pipeline.jobs.export import export_mp4
from pipeline.jobs.ingest import IngestOptions, capture_fields, ingest
from pipeline.inbox.ledger import Ledger
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct, reconstructor
from pipeline.stores.spike_store import check_fps, open_spike_store
from pipeline.stores.storage import check_apart, exists, is_local, local_kind, resolve
from pipeline.stores.video_store import open_video_store
from stages.reconstruction.cfa import check_cfa
from stages.errors import InputError, describe
from stages.reconstruction.methods import NETWORKS, WINDOW
from stages.numbers import check_number
from stages.capture.resets import check_reset

RAW = ("dat", "npz", "npy")
KINDS = ("zarr",) + RAW
SKIPPED_SUFFIXES = ("json", "partial", "tmp", "part", "crdownload")  # sidecars, and uploads still in flight
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
SIDECAR_FIELDS = {"height": int, "width": int, "cfa": str, "flip": bool, "fps": (int, float), "reset": str,
                  "head_columns": int, "key": str, "name": str}
SAMPLE = 1 << 20  # bytes read from each end of a file for its fingerprint
WATCH_DEFAULTS = IngestOptions(cfa=None)  # no CFA guessed: a raw capture's comes from its sidecar or --cfa

log = logging.getLogger("cscsr.watch")  # the package is ``pipeline``; the logger is named for the command


@dataclass(frozen=True)
class WatchOptions:
    method: str = "tfp"
    weights: str | None = None
    every: int = WINDOW
    tile: int = 256
    settle: float = 10.0  # seconds a recording must stay unchanged before it is taken
    max_attempts: int = 3  # tries of a recording that fails for other reasons than its input
    backoff: float = 60.0  # seconds before the first retry, doubling each time
    defaults: IngestOptions = WATCH_DEFAULTS  # what a raw capture without a sidecar (or the field) is taken to be

    def check(self) -> None:
        """Refused before the watcher creates OUTBOX, rather than once per recording."""
        ReconstructOptions(method=self.method, every=self.every, tile=self.tile, weights=self.weights).check()
        if self.method in NETWORKS:  # a missing or damaged weights file stops the watcher, not each recording
            reconstructor(self.method, self.weights)  # loaded and checked (and kept for the jobs of this process)
        check_number("--settle", self.settle, at_least=0)
        check_number("--max-attempts", self.max_attempts, at_least=1, integer=True)
        check_number("--backoff", self.backoff, at_least=0)
        for name in ("height", "width"):
            if getattr(self.defaults, name) is not None:
                check_number(f"--{name}", getattr(self.defaults, name), at_least=1, integer=True)
        check_fps("--fps", self.defaults.fps)
        if self.defaults.cfa is not None:
            check_cfa(self.defaults.cfa)
        check_reset(self.defaults.reset)


@dataclass(frozen=True)
class Candidate:
    name: str  # output name: OUTBOX/NAME.zarr
    url: str
    kind: str
    sidecar: dict
    modified: float
    problem: str | None = None
    look: tuple = ()  # (modification time, files, bytes) of the recording when listed: a second look compares


def discover(inbox: str) -> list[Candidate]:
    """The recordings in INBOX (one level), with a reason for each one that cannot be taken."""
    fs, root = check_inbox(inbox)
    base_url = str(inbox).rstrip("/")
    local = isinstance(fs, LocalFileSystem)  # only local folders have symbolic links
    found = []
    listed = {_base(entry): entry for entry in fs.ls(root, detail=True)}
    for base, entry in sorted(listed.items()):
        suffix = base.rsplit(".", 1)[-1].lower() if "." in base else ""
        if base.startswith(".") or suffix in SKIPPED_SUFFIXES:
            continue
        stem = base[: -len(suffix) - 1] if suffix else base
        url = f"{base_url}/{base}"
        escape = (_leaves(root, entry["name"]) or _leaves(root, f"{root}/{stem}.json")) if local else None
        if escape:  # refused before anything (even a modification time) is read through the link
            found.append(Candidate(stem, url, suffix, {}, 0.0, f"{escape} leads outside the inbox: refused "
                                                               f"(a link out of INBOX is never followed)"))
            continue
        odd = _odd(fs, root, entry, store=suffix == "zarr") or _odd(fs, root, listed.get(f"{stem}.json"), store=False)
        if odd:  # refused before anything is read: a named pipe blocks its reader, a folder fails every read
            found.append(Candidate(stem, url, suffix, {}, 0.0, odd))
            continue
        look = _look(fs, entry)
        modified = look[0]
        if suffix not in KINDS:
            found.append(Candidate(stem, url, suffix, {}, modified,
                                   f"unknown kind of file {base!r}: expected NAME.zarr, .dat, .npz or .npy"))
            continue
        sidecar, problem = _sidecar(fs, f"{root}/{stem}.json")
        if sidecar.get("_modified"):
            modified = max(modified, sidecar.pop("_modified"))
        name = sidecar.get("name", stem)
        if problem is None and (not SAFE_NAME.match(name) or ".." in name):
            problem = f"unsafe name {name!r}: letters, digits, '.', '_' and '-' only, no '..'"
        problem = problem or _misfit_fields(sidecar, stem, base, suffix)
        found.append(Candidate(name, url, suffix, sidecar, modified, problem, look))
    return found


def check_inbox(inbox: str):
    """(filesystem, path) of INBOX; refused in one line unless it is a folder (before OUTBOX is made)."""
    fs, root = resolve(inbox)
    if not fs.isdir(root):
        what = "is a file, not a folder" if fs.exists(root) else "does not exist"
        raise InputError(f"inbox {inbox} {what}: give the folder where recordings land")
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


def _modified(fs, entry: dict) -> float:
    """Latest modification time of a file, or of any file under a directory (a Zarr store)."""
    return _look(fs, entry)[0]


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
    modification time, files and bytes are the same as when it was listed. A writer that pauses longer
    than ``--settle`` (and than a second) between writes is not seen: ``--settle`` must exceed its pauses."""
    quiet = time.time() - candidate.modified
    if quiet >= SECOND_LOOK or not candidate.look:
        return True
    time.sleep(min(SECOND_LOOK, SECOND_LOOK - quiet))  # a clock ahead of ours (a remote store's) waits a second
    fs, path = resolve(candidate.url)
    parent, base = str(path).rstrip("/").rsplit("/", 1)
    fs.invalidate_cache()  # an object store's listing cache would show the first look again
    for entry in fs.ls(parent, detail=True):  # as the first look saw it (a link's own time, not its target's)
        if _base(entry) == base:
            return _look(fs, entry) == candidate.look
    return False  # moved away between the two looks


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
    return {**values, "_modified": _modified(fs, fs.info(path))}, None


def _misfit_fields(sidecar: dict, stem: str, base: str, suffix: str) -> str | None:
    """Why a sidecar's fields do not fit the recording ``base`` beside it, in one line, or None: beside a spike
    store (``NAME.zarr``, which records its own size, CFA and rate) only ``name`` applies; ``key`` names an array
    inside a ``.npz``, and other captures have none. Refused rather than ignored: the sender meant something by
    them."""
    if suffix == "zarr":
        fields = sorted(field for field in sidecar if field not in ("name", "_modified"))
        if fields:
            return (f"sidecar {stem}.json: {', '.join(fields)} describe{'s' if len(fields) == 1 else ''} a raw capture, "
                    f"and {base} is a spike store, which records its own: remove {'it' if len(fields) == 1 else 'them'} "
                    f"(only 'name' applies to a store)")
    elif "key" in sidecar and suffix != "npz":
        return f"sidecar {stem}.json: key names an array inside a .npz, and {base} has none: remove it"
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


def parameters(candidate: Candidate, options: WatchOptions) -> dict:
    params = {"method": options.method, "weights": options.weights, "every": options.every, "tile": options.tile}
    if candidate.kind in RAW:
        capture = capture_fields(options.defaults)
        capture.update({k: v for k, v in candidate.sidecar.items() if k != "name"})
        params["capture"] = capture
    return params


def unstated(candidate: Candidate, params: dict) -> str | None:
    """Why a raw capture cannot be taken as it is: its CFA given neither by its sidecar nor by ``--cfa``
    (none is guessed: the wrong one is reconstructed without any error, into colour speckle or a grey
    mosaic); None if it can."""
    if candidate.kind not in RAW or params["capture"].get("cfa") is not None:
        return None
    base = str(candidate.url).rstrip("/").rsplit("/", 1)[-1]
    return (f"no CFA for {base}: give its sidecar {base[: -len(candidate.kind) - 1]}.json a \"cfa\" (mono, rggb, "
            f"bggr, grbg, gbrg), or start the watcher with --cfa; none is guessed")


def key_of(fingerprint_: str, params: dict) -> str:
    return hashlib.sha256((fingerprint_ + json.dumps(params, sort_keys=True)).encode()).hexdigest()[:24]


def process(candidate: Candidate, key: str, params: dict, outbox: str, ledger: Ledger, options: WatchOptions,
            client) -> None:
    """Ingest (raw captures), reconstruct, export; record the outcome. Never raises for one recording."""
    row = ledger.get(key)
    out = str(outbox).rstrip("/")
    video, preview = f"{out}/{candidate.name}.zarr", f"{out}/{candidate.name}.mp4"
    taken_up = row.state in ("running", "failed")  # a previous attempt may have left outputs to reuse or resume
    ledger.start(key, candidate.name)
    log.info("%s: claimed (attempt %d%s)", candidate.name, ledger.get(key).attempts,
             ", taking up an earlier one" if taken_up else "")
    started = time.perf_counter()
    try:
        spikes = candidate.url
        if candidate.kind in RAW:
            spikes = spike_store_of(out, candidate.name)
            if not (taken_up and _complete_spikes(spikes)):
                attrs = ingest(candidate.url, spikes, IngestOptions(**params["capture"], overwrite=True), progress=False)
                log.info("%s: ingested %s -> %s (%d spikes)", candidate.name, candidate.url, spikes,
                         attrs["spike_count"])
            else:
                log.info("%s: ingested already (%s)", candidate.name, spikes)
        resume = taken_up and exists(video)  # the same capture ingested again has the same identity
        if not (resume and open_video_store(video).attrs.get("state") == "complete"):
            counts = reconstruct(spikes, video, ReconstructOptions(method=options.method, every=options.every,
                                                                   tile=options.tile, weights=options.weights,
                                                                   resume=resume, overwrite=not resume),
                                 client=client, progress=False)
            log.info("%s: reconstructed %s%s -> %s (%d frames)", candidate.name, options.method,
                     " (resumed)" if resume else "", video, counts["frames"])
        else:
            log.info("%s: reconstructed already (%s)", candidate.name, video)
        export_mp4(video, preview, overwrite=True, progress=False)
        log.info("%s: exported %s", candidate.name, preview)
    except InputError as error:
        ledger.fail(key, str(error), final=True, retry_in=None, quarantine=False)
        log.error("%s: failed: %s", candidate.name, describe(error))
        return
    except Exception as error:  # anything else may pass: retry later, up to a bound
        attempts = ledger.get(key).attempts
        quarantine = attempts >= options.max_attempts
        message = f"{type(error).__name__}: {describe(error)}"
        ledger.fail(key, message, final=False, retry_in=options.backoff * 2 ** (attempts - 1), quarantine=quarantine)
        if quarantine:
            log.error("%s: quarantined after %d attempts: %s", candidate.name, attempts, message)
        else:
            log.warning("%s: failed, will retry in %.0f s (attempt %d of %d): %s", candidate.name,
                        options.backoff * 2 ** (attempts - 1), attempts, options.max_attempts, message)
        return
    ledger.done(key, time.perf_counter() - started)
    log.info("%s: done in %.1f s -> %s", candidate.name, time.perf_counter() - started, video)


def spike_store_of(outbox: str, name: str) -> str:
    """Where a raw capture's spike store goes: ``OUTBOX/spikes/NAME.zarr``. Every other output of a
    recording is ``OUTBOX/NAME.zarr`` or ``.mp4``, with a different NAME for each recording (the
    ledger refuses a second owner), so no output of one recording can be another's: a folder named
    ``spikes`` is never ``SOMETHING.zarr`` or ``.mp4`` (a spike store at ``OUTBOX/NAME.spikes.zarr``
    was the video of a recording named ``NAME.spikes``)."""
    return f"{str(outbox).rstrip('/')}/spikes/{name}.zarr"


def _complete_spikes(url: str) -> bool:
    try:
        open_spike_store(url)
        return True
    except InputError:
        return False


def watch_once(inbox: str, outbox: str, options: WatchOptions, client) -> dict:
    """One pass over INBOX; returns how many recordings were processed, waited for and skipped."""
    ledger = Ledger(outbox)
    counts = {"processed": 0, "waiting": 0, "skipped": 0, "refused": 0}
    now = time.time()

    def refuse(candidate: Candidate, problem: str) -> None:
        refusal = hashlib.sha256(f"{candidate.url}|{problem}".encode()).hexdigest()[:24]  # once per problem
        if ledger.get(refusal) is None:
            ledger.record_refusal(refusal, candidate.name, candidate.url, problem)
            log.error("%s: failed: %s (%s)", candidate.name, problem, candidate.url)
            counts["refused"] += 1
        else:  # handled before, as a recording done is: a --once pass of nothing new is no failure
            log.debug("%s: skipped: refused before (%s)", candidate.name, candidate.url)
            counts["skipped"] += 1

    for candidate in discover(inbox):
        if candidate.problem:
            refuse(candidate, candidate.problem)
            continue
        if now - candidate.modified < options.settle:
            log.debug("%s: skipped for now: changed %.1f s ago, still settling", candidate.name, now - candidate.modified)
            counts["waiting"] += 1  # still being written, or just landed: next pass
            continue
        params = parameters(candidate, options)
        bytes_hash = fingerprint(candidate)
        key = key_of(bytes_hash, params)
        row = ledger.get(key)
        handled = row is not None and (row.state in ("done", "quarantined") or (
            row.state == "failed" and (row.final or (row.next_try or 0) > now)))
        if not handled and not steady(candidate):  # the bytes just fingerprinted may be half a recording
            log.debug("%s: skipped for now: changed between two looks a second apart, still being written",
                      candidate.name)
            counts["waiting"] += 1
            continue
        if problem := unstated(candidate, params):  # once settled: a sidecar may land after its capture
            refuse(candidate, problem)
            continue
        if row is None:
            owner = ledger.owner_of(candidate.name)
            ledger.queue(key, candidate.name, candidate.url, bytes_hash, params)
            log.info("%s: found %s (%s)", candidate.name, candidate.url, candidate.kind)
            if owner is not None:
                ledger.start(key, None)
                reason = (f"output name {candidate.name!r} already belongs to {owner.source} (other bytes or "
                          f"parameters): rename the recording or give its sidecar a 'name'")
                ledger.fail(key, reason, final=True, retry_in=None, quarantine=False)
                log.error("%s: failed: %s", candidate.name, reason)
                counts["refused"] += 1
                continue
            row = ledger.get(key)
        waiting = row.state == "failed" and not row.final and (row.next_try or 0) > now
        if row.state in ("done", "quarantined") or (row.state == "failed" and row.final) or waiting:
            log.debug("%s: skipped: %s", candidate.name, "waiting to retry" if waiting else
                      f"already {row.state}{' (final)' if row.final else ''}")
            counts["skipped"] += 1
            continue
        process(candidate, key, params, outbox, ledger, options, client)
        counts["processed"] += 1
    return counts


@contextmanager
def outbox_lock(outbox: str):
    """Hold OUTBOX/.watch.lock for the watcher's life: a second watcher is refused."""
    path = Path(outbox) / ".watch.lock"
    with open(path, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(f"another cscsr watch is already working on {outbox}") from None
        yield


def watch(inbox: str, outbox: str, options: WatchOptions, *, once: bool, interval: float, workers: int | None = None,
          scheduler: str | None = None) -> None:
    """Passes over INBOX every ``interval`` seconds (or one, ``once``), on one Dask client."""
    if not is_local(outbox):
        raise InputError(f"OUTBOX must be a local folder (the ledger is SQLite), got {outbox}")
    check_apart(outbox, inbox, options.weights)  # else the watcher would take its own outputs as recordings
    options.check()
    if os.path.exists(outbox) and not os.path.isdir(outbox):
        raise InputError(f"OUTBOX {outbox} is a file, not a folder: give a folder for the outputs and the ledger")
    check_in_memory((inbox,))  # its spike stores are read by the reconstructions' worker processes
    check_inbox(inbox)  # a missing INBOX is refused before OUTBOX is made
    os.makedirs(outbox, exist_ok=True)
    Ledger(outbox)  # someone else's file named like the ledger is refused before the lock file or a cluster
    with outbox_lock(outbox), dask_client(workers=workers, scheduler=scheduler) as client:
        while True:
            counts = watch_once(inbox, outbox, options, client)
            log.info("pass over %s: %d processed, %d still settling, %d already handled, %d refused", inbox,
                     counts["processed"], counts["waiting"], counts["skipped"], counts["refused"])
            if once:
                check_not_all_refused(counts, inbox, outbox)
                return
            time.sleep(interval)


def check_not_all_refused(counts: dict, inbox: str, outbox: str) -> None:
    """End a ``--once`` pass that refused every recording new to it (none processed or settling; those handled by
    earlier passes, refusals included, are not new) with one line and exit status 1, so that cron or a scheduler
    sees it, once; one that refused some and took others ends as usual (the ledger and the log name the refused
    ones)."""
    if counts["refused"] and not (counts["processed"] or counts["waiting"]):
        raise InputError(f"every recording in {inbox} was refused ({counts['refused']}): see the lines above, or "
                         f"cscsr status {outbox}")


def parse_interval(text: str) -> float:
    """'90', '90s', '10m', '1h' -> seconds."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([smh]?)\s*", str(text))
    if not match or float(match.group(1)) <= 0:
        raise InputError(f"--interval must look like 30s, 10m or 1h, got {text!r}")
    return float(match.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[match.group(2)]
