"""The watcher's ledger: one row per (recording, parameters), in SQLite inside OUTBOX.

A row's key is a hash of the recording's fingerprint and the reconstruction parameters,
so the same bytes dropped twice are done once, and new parameters mean new work. States:

    queued -> running -> done
                      -> failed (retried after a back-off, up to a bound) -> quarantined
                      -> failed, final (bad input: retrying cannot help)
    queued, running, failed (to be retried) -> superseded (new bytes of the same recording landed)
    duplicate (the same bytes and parameters as another recording, under another name: done once, as that one)

A row left ``running`` by a watcher that died is taken up again (its outputs resumed) by
the next one, unless the recording's bytes changed meanwhile: then it is superseded by the new
bytes' row, which owns the recording's outputs. Every change is one SQLite transaction, so a
kill at any moment leaves the ledger consistent.

A ledger is opened only if it is ours: a file that is not an SQLite database, or a database
without the marker (``PRAGMA application_id``) and without our ``recordings`` table, is refused
with one line and never changed; ``cscsr status`` opens the ledger read-only (``mode=ro``).
"""

import json
import sqlite3
import time
from contextlib import closing
from dataclasses import dataclass, replace
from pathlib import Path

from stages.errors import InputError, describe

STATES = ("queued", "running", "done", "failed", "quarantined", "superseded", "duplicate")
FILENAME = "ledger.sqlite"
APPLICATION_ID = 0x63736372  # "cscr" in the SQLite header: this database is a cscsr ledger

_SCHEMA = """
CREATE TABLE IF NOT EXISTS recordings (
    key TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    source TEXT NOT NULL,
    fingerprint TEXT NOT NULL,
    params TEXT NOT NULL,
    state TEXT NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0,
    final INTEGER NOT NULL DEFAULT 0,
    error TEXT,
    queued_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    seconds REAL,
    next_try REAL,
    output TEXT
)
"""


@dataclass(frozen=True)
class Row:
    key: str
    name: str
    source: str
    fingerprint: str
    params: str
    state: str
    attempts: int
    final: int
    error: str | None
    queued_at: float
    started_at: float | None
    finished_at: float | None
    seconds: float | None
    next_try: float | None
    output: str | None


class Ledger:
    def __init__(self, folder: str | Path, *, read_only: bool = False):
        """The ledger in ``folder``: created there if absent (unless ``read_only``), else opened only
        if it is a cscsr ledger."""
        self.path = Path(folder) / FILENAME
        self.read_only = read_only
        if read_only and not self.path.exists():
            raise InputError(f"{folder} has no ledger ({FILENAME}): no cscsr watch has run there")
        if read_only or (self.path.exists() and not (self.path.is_file() and self.path.stat().st_size == 0)):
            self._check_ours()  # an empty file is an SQLite database with nothing in it yet
        if not read_only:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with closing(self._connect()) as db:
                db.execute(_SCHEMA)
                db.execute(f"PRAGMA application_id = {APPLICATION_ID}")

    def _check_ours(self) -> None:
        """Refuse, without writing a byte, a file that is not a database or a database that is not ours."""
        if self.path.is_dir():
            raise InputError(f"ledger {self.path} is a folder, not an SQLite database: move it away or choose "
                             f"another OUTBOX")
        try:
            with closing(sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro", uri=True)) as db:
                marker = db.execute("PRAGMA application_id").fetchone()[0]
                columns = [row[1] for row in db.execute("PRAGMA table_info(recordings)")]
                tables = [row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        except sqlite3.Error as error:
            raise InputError(f"ledger {self.path} is not an SQLite database ({describe(error)}): move it away or "
                             f"choose another OUTBOX") from None
        if marker != APPLICATION_ID and columns != list(Row.__dataclass_fields__):  # no marker: ledgers before it
            raise InputError(f"{self.path} is an SQLite database but not a cscsr ledger (tables: "
                             f"{', '.join(tables) or 'none'}): refusing to change it; move it away or choose another "
                             f"OUTBOX")

    def _connect(self) -> sqlite3.Connection:
        target, uri = (f"{self.path.resolve().as_uri()}?mode=ro", True) if self.read_only else (self.path, False)
        db = sqlite3.connect(target, timeout=30, isolation_level=None, uri=uri)  # autocommit; explicit transactions
        db.row_factory = lambda cursor, values: Row(*values)
        return db

    def _write(self, sql: str, args: tuple) -> None:
        with closing(self._connect()) as db:
            db.execute("BEGIN IMMEDIATE")
            db.execute(sql, args)
            db.execute("COMMIT")

    def get(self, key: str) -> Row | None:
        with closing(self._connect()) as db:
            return db.execute("SELECT * FROM recordings WHERE key = ?", (key,)).fetchone()

    def rows(self) -> list[Row]:
        with closing(self._connect()) as db:
            return db.execute("SELECT * FROM recordings ORDER BY queued_at, name").fetchall()

    def recordings(self) -> list[Row]:
        """One row per recording (its source in the inbox), as ``cscsr status`` shows them: its latest row (a
        capture refused for its sidecar, then done once the sidecar was fixed, is done), with the attempts of all
        its rows counted, in the order the recordings were first found."""
        return latest_per_source(self.rows())

    def owner_of(self, output: str, source: str) -> Row | None:
        """The row, done or in progress, that an output name belongs to, for the recording at ``source``: an
        unfinished attempt at ``source``'s own earlier bytes (left ``running`` by a watcher killed, or failed to be
        retried) is no owner, since the new bytes supersede it (:meth:`supersede`)."""
        with closing(self._connect()) as db:
            return db.execute("SELECT * FROM recordings WHERE output = ? AND state NOT IN ('quarantined', "
                              "'superseded', 'duplicate') AND NOT (state = 'failed' AND final = 1) "
                              "AND NOT (source = ? AND state != 'done') ORDER BY queued_at LIMIT 1",
                              (output, source)).fetchone()

    def supersede(self, source: str) -> int:
        """Mark the unfinished rows of ``source`` (queued, running, failed to be retried) ``superseded``: the
        recording there has new bytes, whose row takes its outputs over. Their keys are renamed (the same bytes
        landing again are new work, not a row done with); the number of rows marked."""
        now = time.time()
        with closing(self._connect()) as db:
            db.execute("BEGIN IMMEDIATE")
            marked = db.execute("UPDATE recordings SET state = 'superseded', key = key || ':superseded:' || ?, "
                                "next_try = NULL, error = 'its recording changed before it was done: the new bytes "
                                "have a row of their own' WHERE source = ? AND final = 0 "
                                "AND state IN ('queued', 'running', 'failed')", (repr(now), source)).rowcount
            db.execute("COMMIT")
        return marked

    def queue(self, key: str, name: str, source: str, fingerprint: str, params: dict) -> None:
        self._write("INSERT OR IGNORE INTO recordings (key, name, source, fingerprint, params, state, queued_at) "
                    "VALUES (?, ?, ?, ?, ?, 'queued', ?)", (key, name, source, fingerprint, json.dumps(params), time.time()))

    def start(self, key: str, output: str | None) -> None:
        self._write("UPDATE recordings SET state = 'running', attempts = attempts + 1, started_at = ?, output = ?, "
                    "error = NULL, next_try = NULL WHERE key = ?", (time.time(), output, key))

    def done(self, key: str, seconds: float) -> None:
        self._write("UPDATE recordings SET state = 'done', finished_at = ?, seconds = ?, error = NULL WHERE key = ?",
                    (time.time(), seconds, key))

    def fail(self, key: str, error: str, *, final: bool, retry_in: float | None, quarantine: bool) -> None:
        state = "quarantined" if quarantine else "failed"
        next_try = None if final or quarantine or retry_in is None else time.time() + retry_in
        self._write("UPDATE recordings SET state = ?, error = ?, final = ?, finished_at = ?, next_try = ? WHERE key = ?",
                    (state, error, int(final), time.time(), next_try, key))

    def record_duplicate(self, key: str, name: str, source: str, of: Row) -> bool:
        """Record the recording at ``source``, named ``name``, as a duplicate of the row ``of`` (the same bytes and
        parameters, another name): its own row (the key ``key``, one per source), ``output`` the name whose outputs
        it shares; whether this is news (False: recorded by an earlier pass)."""
        now = time.time()
        with closing(self._connect()) as db:
            db.execute("BEGIN IMMEDIATE")
            added = db.execute("INSERT OR IGNORE INTO recordings (key, name, source, fingerprint, params, state, "
                               "queued_at, finished_at, output) VALUES (?, ?, ?, ?, ?, 'duplicate', ?, ?, ?)",
                               (key, name, source, of.fingerprint, of.params, now, now, of.output or of.name)).rowcount
            db.execute("COMMIT")
        return added == 1

    def record_refusal(self, key: str, name: str, source: str, error: str) -> None:
        """A candidate refused before any work (bad name, unknown kind, bad sidecar, odd entry): failed, final."""
        now = time.time()
        self._write("INSERT OR IGNORE INTO recordings (key, name, source, fingerprint, params, state, attempts, final, "
                    "error, queued_at, finished_at) VALUES (?, ?, ?, '', '{}', 'failed', 1, 1, ?, ?, ?)",
                    (key, name, source, error, now, now))


def latest_per_source(rows: list[Row]) -> list[Row]:
    """``rows`` collapsed to one per ``source``: the one touched last (queued, started or finished; a superseded
    row only if the source has no other), its ``attempts`` the sum over the source's rows; in the order of each
    source's first row."""
    by_source: dict[str, list[Row]] = {}
    for row in rows:
        by_source.setdefault(row.source, []).append(row)
    return [replace(max(group, key=lambda row: (row.state != "superseded", _last_touched(row))),
                    attempts=sum(row.attempts for row in group)) for group in by_source.values()]


def _last_touched(row: Row) -> float:
    """When ``row`` last changed: the latest of its queued, started and finished times."""
    return max(row.queued_at, row.started_at or 0.0, row.finished_at or 0.0)
