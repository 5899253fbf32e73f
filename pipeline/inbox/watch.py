"""``cscsr watch``: reconstruct recordings as they land in an inbox, exactly once each.

Each pass lists INBOX (:mod:`pipeline.inbox.listing`: the recordings, their sidecars, whether they have settled).
A raw capture's CFA is never guessed: it comes from its sidecar or ``--cfa``, and a capture with neither is
refused (:func:`unstated`): taken as the wrong one, a mono capture would be demosaicked into colour speckle, or a
Bayer one shown grey with its mosaic, and no error said so. A recording is taken once it has not changed for
``settle`` seconds (``settle`` must exceed the writer's longest pause). For each: ingest a raw capture into
``OUTBOX/spikes/NAME.zarr``, reconstruct into ``OUTBOX/NAME.zarr``, export ``OUTBOX/NAME.mp4``; the ledger
(:mod:`pipeline.inbox.ledger`) records every step's outcome. No two recordings share an output path
(:func:`spike_store_of`), and OUTBOX may not be, be inside, or contain INBOX.

Killing the watcher at any moment loses nothing and duplicates nothing: the ledger row it
left ``running`` is taken up by the next pass, whose reconstruction resumes from the
committed tiles, and outputs are named by the recording, so there is never a second copy.
Bad input (unknown extension, unsafe name, nonsense sidecar, truncated capture, a symbolic link
anywhere in a recording or its sidecar whose real path leaves INBOX, an entry that is not what its name
says, such as a folder, named pipe, socket or device where a regular file belongs, :func:`_odd`) is recorded
as failed with its reason and never stops the other recordings; other errors (an OUTBOX folder not writable
included) are retried with exponential back-off, then quarantined. A recording that cannot be read is refused
alone, one gone mid-pass skipped; new bytes of a recording supersede an unfinished attempt at its old ones, and
the same bytes under another name are a duplicate, done once. Names are checked so no output can land
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

from pipeline.compute.cluster import check_in_memory, dask_client
from pipeline.jobs.export import export_mp4
from pipeline.jobs.ingest import IngestOptions, capture_fields, ingest
from pipeline.inbox.ledger import Ledger, Row
from pipeline.inbox.listing import (RAW, Candidate, InboxUnavailable, canonical, check_inbox, discover,
                                    fingerprint, steady, unreadable)
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct, reconstructor
from pipeline.stores.spike_store import check_fps, open_spike_store
from pipeline.stores.storage import Unreachable, Unwritable, check_apart, exists, is_local, resolve
from pipeline.stores.video_store import open_video_store
from stages.reconstruction.cfa import check_cfa
from stages.errors import InputError, describe
from stages.reconstruction.methods import NETWORKS, WINDOW
from stages.numbers import check_number
from stages.capture.resets import check_reset

ENVIRONMENT = (Unwritable, Unreachable)  # refusals that say what is wrong around a recording, not in it: retried
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
            client) -> str:
    """Ingest (raw captures), reconstruct, export; record the outcome and return it: ``done``, ``refused`` (bad
    input found on the way, a truncated capture: final) or ``retry`` (anything else, an output folder not writable
    or storage out of reach included: :data:`ENVIRONMENT`; retried with back-off, or quarantined). Never raises for
    one recording."""
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
        if isinstance(error, ENVIRONMENT):
            return _retry_later(candidate, key, ledger, options, describe(error))
        ledger.fail(key, str(error), final=True, retry_in=None, quarantine=False)
        log.error("%s: failed: %s", candidate.name, describe(error))
        return "refused"
    except Exception as error:  # anything else may pass: retry later, up to a bound
        return _retry_later(candidate, key, ledger, options, f"{type(error).__name__}: {describe(error)}")
    ledger.done(key, time.perf_counter() - started)
    log.info("%s: done in %.1f s -> %s", candidate.name, time.perf_counter() - started, video)
    return "done"


def _retry_later(candidate: Candidate, key: str, ledger: Ledger, options: WatchOptions, message: str) -> str:
    """Record a failure that may pass (a lost worker, a full disk, an output folder not writable for now): retried
    after the back-off, doubling, then quarantined after ``max_attempts``; ``retry``."""
    attempts = ledger.get(key).attempts
    quarantine = attempts >= options.max_attempts
    ledger.fail(key, message, final=False, retry_in=options.backoff * 2 ** (attempts - 1), quarantine=quarantine)
    if quarantine:
        log.error("%s: quarantined after %d attempts: %s", candidate.name, attempts, message)
    else:
        log.warning("%s: failed, will retry in %.0f s (attempt %d of %d): %s", candidate.name,
                    options.backoff * 2 ** (attempts - 1), attempts, options.max_attempts, message)
    return "retry"


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
    """One pass over INBOX; returns how many recordings were processed (done, or failed to be retried), waited for,
    skipped (handled before) and refused (bad input, whether found before any work or on the way: a truncated
    capture is refused as a nonsense sidecar is). What goes wrong with one recording is that recording's alone: one
    that cannot be read is refused (and taken by a later pass that can read it), one gone since the listing is
    skipped, and the pass goes on. An INBOX that cannot be listed is :class:`InboxUnavailable`."""
    ledger = Ledger(outbox)
    counts = {"processed": 0, "waiting": 0, "skipped": 0, "refused": 0}
    now = time.time()
    inbox = canonical(inbox)  # however INBOX is spelt, its recordings have one source each in the ledger
    root = resolve(inbox)[1]
    for candidate in discover(inbox):
        try:
            outcome = _take(candidate, outbox, ledger, options, client, now)
        except FileNotFoundError:  # moved or deleted (or a file of its store) since the listing: nothing to take
            log.info("%s: skipped: gone from the inbox since the pass listed it (%s)", candidate.name, candidate.url)
            continue
        except OSError as error:  # no permission to read it: its own problem, said once; the others go on
            outcome = _refuse(candidate, unreadable(error, root), ledger)
        counts[outcome] += 1
    return counts


def _refuse(candidate: Candidate, problem: str, ledger: Ledger) -> str:
    """Record ``candidate`` as refused for ``problem``, once per problem (a later pass finding the same problem
    skips it, as a recording done is: a --once pass of nothing new is no failure); the count it adds to."""
    refusal = _refusal_key(candidate, problem)
    if ledger.get(refusal) is None:
        ledger.record_refusal(refusal, candidate.name, candidate.url, problem)
        log.error("%s: failed: %s (%s)", candidate.name, problem, candidate.url)
        return "refused"
    log.debug("%s: skipped: refused before (%s)", candidate.name, candidate.url)
    return "skipped"


def _refusal_key(candidate: Candidate, problem: str) -> str:
    """The ledger key of a refusal: one per recording and problem."""
    return hashlib.sha256(f"{candidate.url}|{problem}".encode()).hexdigest()[:24]


def _duplicate(candidate: Candidate, key: str, row: Row, ledger: Ledger) -> str:
    """A recording whose bytes and parameters are those of the ledger's ``row``, under another name: done once,
    as that one (its outputs are that name's), and recorded as a ``duplicate`` of it, so ``cscsr status`` shows a
    line for it; said once at INFO. Counted as handled."""
    if ledger.record_duplicate(_refusal_key(candidate, key), candidate.name, candidate.url, row):
        log.info("%s: same bytes and parameters as %s (%s): not done again, its outputs are %s's", candidate.name,
                 row.name, row.source, row.output or row.name)
    else:
        log.debug("%s: skipped: same bytes and parameters as %s (%s)", candidate.name, row.name, row.source)
    return "skipped"


def _take(candidate: Candidate, outbox: str, ledger: Ledger, options: WatchOptions, client, now: float) -> str:
    """Refuse, leave for later, skip or process one recording of a pass; which of the pass's counts it adds to. A
    recording (with its sidecar) is judged once it has settled: a sidecar still being written is no bad JSON yet.
    Problems found without reading anything (a link out of INBOX, an odd entry) have no time: refused at once."""
    if now - candidate.modified < options.settle:
        log.debug("%s: skipped for now: changed %.1f s ago, still settling", candidate.name, now - candidate.modified)
        return "waiting"  # still being written, or just landed: next pass
    if candidate.problem:
        if ledger.get(_refusal_key(candidate, candidate.problem)) is None and not steady(candidate):
            log.debug("%s: skipped for now: changed between two looks a second apart, still being written",
                      candidate.name)
            return "waiting"
        return _refuse(candidate, candidate.problem, ledger)
    params = parameters(candidate, options)
    bytes_hash = fingerprint(candidate)
    key = key_of(bytes_hash, params)
    row = ledger.get(key)
    handled = row is not None and (row.state in ("done", "quarantined") or (
        row.state == "failed" and (row.final or (row.next_try or 0) > now)))
    if not handled and not steady(candidate):  # the bytes just fingerprinted may be half a recording
        log.debug("%s: skipped for now: changed between two looks a second apart, still being written",
                  candidate.name)
        return "waiting"
    if problem := unstated(candidate, params):  # once settled: a sidecar may land after its capture
        return _refuse(candidate, problem, ledger)
    if row is not None and row.source != candidate.url and row.name != candidate.name:  # sent under another name
        if row.state == "failed" and row.final:  # its bytes were refused: these are too, in its words
            return _refuse(candidate, f"the same bytes and parameters as {row.name}, refused: {row.error}", ledger)
        return _duplicate(candidate, key, row, ledger)
    if row is None:
        if (owner := ledger.owner_of(candidate.name, candidate.url)) is not None:
            # the name's fault, not the bytes': refused under its own key, so the same bytes under a free name are done
            whose = (f"{owner.source} as it was done earlier" if owner.source == candidate.url else owner.source)
            return _refuse(candidate, f"output name {candidate.name!r} already belongs to {whose} (other bytes or "
                           f"parameters): rename the recording or give its sidecar a 'name'", ledger)
        if ledger.supersede(candidate.url):  # before the new row is queued: the new row is the one touched last
            log.info("%s: changed before an earlier attempt at it was done: that attempt is superseded",
                     candidate.name)
        ledger.queue(key, candidate.name, candidate.url, bytes_hash, params)
        log.info("%s: found %s (%s)", candidate.name, candidate.url, candidate.kind)
        row = ledger.get(key)
    waiting = row.state == "failed" and not row.final and (row.next_try or 0) > now
    if row.state in ("done", "quarantined") or (row.state == "failed" and row.final) or waiting:
        log.debug("%s: skipped: %s", candidate.name, "waiting to retry" if waiting else
                  f"already {row.state}{' (final)' if row.final else ''}")
        return "skipped"
    outcome = process(candidate, key, params, outbox, ledger, options, client)
    return "refused" if outcome == "refused" else "processed"  # bad input found on the way is refused


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
    """Passes over INBOX every ``interval`` seconds (or one, ``once``), on one Dask client. An INBOX that cannot be
    listed at a pass (unmounted for a while) is an ERROR line and the next pass looks again; with ``once``, the one
    line that ends the command."""
    if not is_local(outbox):
        raise InputError(f"OUTBOX must be a local folder (the ledger is SQLite), got {outbox}")
    check_apart(outbox, inbox, options.weights)  # else the watcher would take its own outputs as recordings
    options.check()
    if os.path.exists(outbox) and not os.path.isdir(outbox):
        raise InputError(f"OUTBOX {outbox} is a file, not a folder: give a folder for the outputs and the ledger")
    check_in_memory((inbox,))  # its spike stores are read by the reconstructions' worker processes
    check_inbox(inbox)  # a missing INBOX is refused before OUTBOX is made
    inbox = canonical(inbox)  # as the ledger knows it (and each pass's line says it)
    os.makedirs(outbox, exist_ok=True)
    Ledger(outbox)  # someone else's file named like the ledger is refused before the lock file or a cluster
    with outbox_lock(outbox), dask_client(workers=workers, scheduler=scheduler) as client:
        while True:
            try:
                counts = watch_once(inbox, outbox, options, client)
            except (InboxUnavailable, Unreachable) as error:  # unmounted, offline: a service says so, looks again
                if once:
                    raise
                log.error("pass over %s: %s; trying again in %s", inbox, describe(error), _duration(interval))
            else:
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


def _duration(seconds: float) -> str:
    """``90 s``, ``10 min``, ``2 h``: an interval as a log line says it."""
    for unit, size in (("h", 3600), ("min", 60)):
        if seconds >= size and seconds % size == 0:
            return f"{seconds / size:g} {unit}"
    return f"{seconds:g} s"


LONGEST_INTERVAL = 7 * 24 * 3600  # seconds between passes, at most: rarer passes are cron's work (--once)


def parse_interval(text: str) -> float:
    """'90', '90s', '10m', '1h' -> seconds; at most a week (:data:`LONGEST_INTERVAL`), refused before the first
    pass (a huge one failed after it, as more than the system's sleep can wait)."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([smh]?)\s*", str(text))
    if not match or float(match.group(1)) <= 0:
        raise InputError(f"--interval must look like 30s, 10m or 1h, got {text!r}")
    seconds = float(match.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[match.group(2)]
    if seconds > LONGEST_INTERVAL:
        raise InputError(f"--interval must be at most 168h (a week), got {text!r}: for rarer passes, run cscsr watch "
                         f"--once from cron")
    return seconds
