"""``cscsr watch`` when something goes wrong with one recording or with the places around it: a recording that
cannot be read, one gone mid-pass, an inbox gone for a while. What goes wrong with one recording is that
recording's alone; the others are taken, and a service keeps running."""

import logging
import os
import shutil
import sqlite3
import subprocess

import pytest

from pipeline.inbox.ledger import Ledger
from pipeline.inbox.listing import InboxUnavailable
from pipeline.inbox.watch import WatchOptions
from pipeline.jobs.ingest import IngestOptions, ingest
from tests.test_watch import drop, settled
from tests.test_watch_log import tiny_capture
from tests.test_watch_odd_entries import watch_once_process

SIDECAR = {"height": 16, "width": 16, "cfa": "rggb"}
QUICK = WatchOptions(tile=16, every=5, settle=0)


def as_a_user() -> list[str]:
    """The prefix that runs a command without root's right to read and write whatever it likes: none for a user;
    for root, ``setpriv`` dropping that right (DAC override) from what the command may have; skipped without it."""
    if os.geteuid() != 0:
        return []
    prefix = ["setpriv", "--bounding-set=-dac_override,-dac_read_search"]
    if shutil.which("setpriv") is None or subprocess.run([*prefix, "true"], capture_output=True,
                                                         check=False).returncode:
        pytest.skip("running as root, and setpriv cannot drop root's right to read any file here")
    return prefix


def rows(outbox) -> dict:
    return {row.name: row for row in Ledger(outbox).recordings()}


def test_a_recording_that_cannot_be_read_is_refused_alone_and_taken_once_it_can_be(tmp_path, cli):
    """A capture, a sidecar and a store's metadata that the watcher may not read (chmod 000): each crashed the
    whole pass with a PermissionError, every pass, and the readable recording beside them was never taken. Now
    each is refused in one line naming the file, the others are done, and a pass after the fix takes them."""
    prefix = as_a_user()
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "good.npy", tiny_capture(), SIDECAR)
    drop(inbox, "locked.npy", tiny_capture(1), SIDECAR)
    drop(inbox, "sealed.npy", tiny_capture(2), SIDECAR)
    np_capture = tmp_path / "store.npy"
    np_capture.write_bytes(tiny_capture(3))
    ingest(str(np_capture), str(inbox / "store.zarr"), IngestOptions(cfa="rggb"), progress=False)
    settled(inbox)
    shut = [inbox / "locked.npy", inbox / "sealed.json", inbox / "store.zarr" / "zarr.json"]
    for path in shut:
        path.chmod(0o000)
    try:
        result = watch_once_process(inbox, outbox, prefix)
    finally:
        for path in shut:
            path.chmod(0o644)
    assert result.returncode == 0, result.stderr  # one recording was taken: no failed pass
    got = rows(outbox)
    assert {name: (row.state, row.final) for name, row in got.items()} == {
        "good": ("done", 0), "locked": ("failed", 1), "sealed": ("failed", 1), "store": ("failed", 1)}
    for name, shown in (("locked", "locked.npy"), ("sealed", "sealed.json"), ("store", "store.zarr/zarr.json")):
        assert got[name].error == f"cannot read {shown}: permission denied (a later pass takes it once it can be " \
                                  f"read)", got[name].error
    assert "Traceback" not in result.stderr and "PermissionError" not in result.stderr

    again = cli("watch", inbox, outbox, "--once", "--workers", 1, "--settle", 0, "--tile", 16, "--every", 5)
    assert again.exit_code == 0, again.stderr
    assert {name: row.state for name, row in rows(outbox).items()} == dict.fromkeys(got, "done")


def test_a_service_outlives_a_recording_gone_mid_pass_and_an_inbox_gone_for_a_while(tmp_path, monkeypatch, caplog):
    """A watcher with --interval: a recording listed, then moved away before its turn, ended the service
    (``error: cannot read .../b.npy: no such file or object``), the rest of the pass never looked at; so did an
    INBOX unmounted for a pass. Now the first is an INFO line and the pass goes on; the second an ERROR line, and
    the next pass looks again. With --once, an INBOX gone is still the one line that ends the command."""
    import pipeline.inbox.watch as watcher

    inbox, outbox, away = tmp_path / "inbox", tmp_path / "outbox", tmp_path / "unmounted"
    inbox.mkdir()
    for seed, name in enumerate(("a", "b", "c")):
        drop(inbox, f"{name}.npy", tiny_capture(seed), SIDECAR)
    settled(inbox)
    real_discover, real_pass, passes = watcher.discover, watcher.watch_once, []

    class Enough(Exception):
        pass

    def listing(path):
        found = real_discover(path)
        if len(passes) == 1:
            os.remove(inbox / "b.npy")  # listed, and moved away while a.npy is reconstructed
        return found

    def one_pass(*args):
        passes.append(args)
        if len(passes) == 2:
            inbox.rename(away)  # unmounted
        elif len(passes) == 3:
            away.rename(inbox)  # mounted again, with a new recording
            drop(inbox, "d.npy", tiny_capture(4), SIDECAR)
            settled(inbox)
        elif len(passes) == 4:
            raise Enough
        return real_pass(*args)

    monkeypatch.setattr(watcher, "discover", listing)
    monkeypatch.setattr(watcher, "watch_once", one_pass)
    with caplog.at_level(logging.DEBUG, logger="cscsr.watch"), pytest.raises(Enough):
        watcher.watch(str(inbox), str(outbox), QUICK, once=False, interval=0.01, workers=1)
    logged = [(record.levelname, record.getMessage()) for record in caplog.records]
    assert ("INFO", f"b: skipped: gone from the inbox since the pass listed it ({inbox / 'b.npy'})") in logged
    assert ("ERROR", (f"pass over {inbox}: inbox {inbox} does not exist: give the folder where recordings land; "
                      f"trying again in 0.01 s")) in logged
    assert {name: row.state for name, row in rows(outbox).items()} == {"a": "done", "c": "done", "d": "done"}

    monkeypatch.setattr(watcher, "watch_once", real_pass)
    monkeypatch.setattr(watcher, "discover", lambda path: (inbox.rename(away), real_discover(path))[1])
    with pytest.raises(InboxUnavailable, match=f"^inbox {inbox} does not exist"):
        watcher.watch(str(inbox), str(outbox), QUICK, once=True, interval=1, workers=1)


def test_new_bytes_of_a_recording_supersede_an_attempt_left_unfinished(tmp_path, client, monkeypatch):
    """A capture re-sent with new bytes after a watcher was killed mid-reconstruction of the old ones (its row left
    ``running``), or after the old ones failed to be retried (a store copied half, then whole): the new bytes were
    refused as ``output name 'r' already belongs to .../r.npy``, their own path, and the old row stayed running
    for ever. Now the new bytes are done under the name, and the unfinished row is superseded."""
    import pipeline.inbox.watch as watcher

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "flaky.npy", tiny_capture(1), SIDECAR)
    drop(inbox, "r.npy", tiny_capture(2), SIDECAR)
    settled(inbox)

    class Killed(BaseException):
        """The watcher killed mid-job: nothing after it runs, the row stays running."""

    def broken(spikes, video, *args, **kwargs):
        raise OSError("worker lost") if video.endswith("flaky.zarr") else Killed()

    with monkeypatch.context() as patched, pytest.raises(Killed):
        patched.setattr(watcher, "reconstruct", broken)
        watcher.watch_once(str(inbox), str(outbox), WatchOptions(tile=16, every=5, backoff=0), client)
    assert {name: row.state for name, row in rows(outbox).items()} == {"flaky": "failed", "r": "running"}

    drop(inbox, "flaky.npy", tiny_capture(3), SIDECAR)  # sent again, corrected
    drop(inbox, "r.npy", tiny_capture(4), SIDECAR)
    settled(inbox)
    counts = watcher.watch_once(str(inbox), str(outbox), WatchOptions(tile=16, every=5), client)
    assert counts == {"processed": 2, "waiting": 0, "skipped": 0, "refused": 0}
    shown = rows(outbox)
    assert {name: (row.state, row.attempts, row.error) for name, row in shown.items()} == {
        "flaky": ("done", 2, None), "r": ("done", 2, None)}
    assert sorted(row.state for row in Ledger(outbox).rows()) == ["done", "done", "superseded", "superseded"]
    assert all(row.fingerprint == shown[row.name].fingerprint for row in Ledger(outbox).rows() if row.state == "done")


def test_an_output_folder_that_cannot_be_written_is_retried_and_done_once_it_can_be(tmp_path, cli):
    """``OUTBOX/spikes`` not writable (chmod 555; a read-only file system alike): a problem of OUTBOX, not of the
    recording, which was recorded ``failed (final)`` and never tried again once the folder was fixed. Now it is
    retried with back-off, as a full disk is, and done once the folder can be written."""
    prefix = as_a_user()
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    (outbox / "spikes").mkdir(parents=True)
    drop(inbox, "a.npy", tiny_capture(), SIDECAR)
    settled(inbox)
    (outbox / "spikes").chmod(0o555)
    try:
        result = watch_once_process(inbox, outbox, prefix)
    finally:
        (outbox / "spikes").chmod(0o755)
    assert result.returncode == 0, result.stderr
    row = rows(outbox)["a"]
    assert (row.state, row.final, row.attempts) == ("failed", 0, 1) and row.next_try is not None
    assert row.error == (f"cannot write {outbox / 'spikes' / 'a.zarr'}: the folder {outbox / 'spikes'} is not "
                         f"writable (no permission, or a read-only file system)")
    assert f"WARNING cscsr.watch: a: failed, will retry in 60 s (attempt 1 of 3): {row.error}" in result.stderr

    with sqlite3.connect(outbox / "ledger.sqlite") as db:  # let the back-off pass
        db.execute("UPDATE recordings SET next_try = 0")
    again = cli("watch", inbox, outbox, "--once", "--workers", 1, "--settle", 0, "--tile", 16, "--every", 5)
    assert again.exit_code == 0, again.stderr
    assert (rows(outbox)["a"].state, rows(outbox)["a"].attempts) == ("done", 2)
    assert (outbox / "a.mp4").stat().st_size > 0
