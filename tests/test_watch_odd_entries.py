"""``cscsr watch`` over an inbox holding entries that are not what their names say (#48): a folder named like
a sidecar, named pipes named as a capture, a sidecar and a Zarr store's metadata, a socket, a folder named as a
capture, a file named as a store. Each is recorded as failed with a reason naming what it is, nothing is opened
that could block (a named pipe's reader waits for a writer forever), and the good capture beside them is done."""

import json
import os
import signal
import socket
import subprocess

import fsspec
import pytest

from pipeline.inbox.ledger import Ledger
from pipeline.inbox.watch import WatchOptions, watch_once
from tests.conftest import CSCSR
from tests.test_watch import drop, settled
from tests.test_watch_log import LINE, tiny_capture

BOUND = 120  # seconds: a pass over these tiny captures takes a few; one blocked on a named pipe, forever
SIDECAR = {"height": 16, "width": 16, "cfa": "rggb"}


def watch_once_process(inbox, outbox, prefix=()) -> subprocess.CompletedProcess:
    """``cscsr watch INBOX OUTBOX --once`` as a user runs it, in a process group of its own, started through
    ``prefix`` (e.g. ``setpriv ...``): one still running after BOUND seconds is killed with its cluster, and fails
    the test."""
    command = [*prefix, CSCSR, "watch", str(inbox), str(outbox), "--once", "--workers", "1", "--settle", "0",
               "--tile", "16", "--every", "5"]
    with subprocess.Popen(command, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True) as process:
        try:
            stdout, stderr = process.communicate(timeout=BOUND)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()
            pytest.fail(f"cscsr watch --once still running after {BOUND} s: a read in the inbox blocked")
    return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)


def logged(text: str) -> list[tuple[str, str]]:
    """(level, message) of the watcher's log lines in ``text`` (a process's standard error: other lines pass)."""
    return [(match.group(2), match.group(3)) for line in text.splitlines() if (match := LINE.match(line))]


def test_entries_that_are_not_regular_files_are_refused_and_the_pass_goes_on(tmp_path, monkeypatch):
    """A real ``cscsr watch --once`` (a process, a cluster) over a local inbox, twice: both passes end, every odd
    entry is one failed row naming what it is, the good capture is done once."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "good.npy", tiny_capture(), SIDECAR)
    drop(inbox, "boxed.npy", tiny_capture(1))
    (inbox / "boxed.json").mkdir()  # a folder named like the capture's sidecar: IsADirectoryError every pass
    (inbox / "boxed.json" / "cfa").write_text("rggb")
    drop(inbox, "piped.npy", tiny_capture(2))
    os.mkfifo(inbox / "piped.json")  # a named pipe as the sidecar: reading it waits for a writer
    os.mkfifo(inbox / "pipe.dat")  # a named pipe as the capture
    (inbox / "pipe.json").write_text(json.dumps(SIDECAR))
    (inbox / "folder.dat").mkdir()  # a folder named as a capture
    (inbox / "piped_store.zarr").mkdir()  # a store whose metadata is a named pipe
    os.mkfifo(inbox / "piped_store.zarr" / "zarr.json")
    (inbox / "flat.zarr").write_bytes(b"not a store")  # a file named as a store
    with monkeypatch.context() as here, socket.socket(socket.AF_UNIX) as listening:
        here.chdir(inbox)  # bound by a relative name: a long basetemp would pass a socket path's 108 bytes
        listening.bind("socket.npy")  # the socket file stays when the socket is closed
    settled(inbox)

    result = watch_once_process(inbox, outbox)
    assert result.returncode == 0, result.stderr
    reasons = {"boxed": "boxed.json is a folder, not a regular file",
               "piped": "piped.json is a named pipe (FIFO), not a regular file",
               "pipe": "pipe.dat is a named pipe (FIFO), not a regular file",
               "folder": "folder.dat is a folder, not a regular file",
               "piped_store": "piped_store.zarr/zarr.json is a named pipe (FIFO), not a regular file",
               "flat": "flat.zarr is a regular file, not a folder",
               "socket": "socket.npy is a socket, not a regular file"}
    rows = {row.name: row for row in Ledger(outbox).rows()}
    assert {name: (row.state, row.final) for name, row in rows.items()} == {
        "good": ("done", 0), **{name: ("failed", 1) for name in reasons}}
    for name, reason in reasons.items():
        assert rows[name].error.startswith(reason + ": refused") and "\n" not in rows[name].error, rows[name].error
    errors = [message for level, message in logged(result.stderr) if level == "ERROR"]
    assert sorted(message.split(": failed: ")[0] for message in errors) == sorted(reasons)  # one line each
    assert logged(result.stderr)[-1] == ("INFO", f"pass over {inbox}: 1 processed, 0 still settling, 0 already "
                                                  f"handled, 7 refused")
    assert sorted(p for p in os.listdir(outbox) if not p.startswith(".")) == [
        "good.mp4", "good.zarr", "ledger.sqlite", "spikes"]
    assert os.listdir(outbox / "spikes") == ["good.zarr"] and os.path.getsize(outbox / "good.mp4") > 0

    again = watch_once_process(inbox, outbox)  # the next pass: refused before, not refused again, nothing crashes
    assert again.returncode == 0, again.stderr
    assert logged(again.stderr)[-1] == ("INFO", f"pass over {inbox}: 0 processed, 0 still settling, 8 already "
                                                 f"handled, 0 refused")
    assert len(Ledger(outbox).rows()) == 8


def test_an_object_store_inbox_refuses_a_folder_named_as_a_file_and_a_file_named_as_a_store(tmp_path):
    """On an object store (``memory://``) every entry is a file or a folder (a prefix): a prefix named like a
    sidecar or a capture, or an object named like a Zarr store, is refused; the capture beside them is found
    (and left to settle)."""
    fs = fsspec.filesystem("memory")
    inbox = f"memory://odd-entries-{tmp_path.name}"
    fs.pipe({f"{inbox}/good.npy": tiny_capture(), f"{inbox}/good.json": json.dumps(SIDECAR).encode(),
             f"{inbox}/boxed.npy": tiny_capture(1), f"{inbox}/boxed.json/cfa": b"rggb",
             f"{inbox}/folder.dat/part": b"\0" * 32, f"{inbox}/flat.zarr": b"not a store"})
    try:
        counts = watch_once(inbox, str(tmp_path / "outbox"), WatchOptions(settle=3600), client=None)
    finally:
        fs.rm(inbox, recursive=True)
    assert counts == {"processed": 0, "waiting": 1, "skipped": 0, "refused": 3}
    errors = {row.name: row.error for row in Ledger(tmp_path / "outbox").rows()}
    assert errors == {"boxed": "boxed.json is a folder, not a regular file: refused (only regular files and "
                               "NAME.zarr folders are read)",
                      "folder": "folder.dat is a folder, not a regular file: refused (only regular files and "
                                "NAME.zarr folders are read)",
                      "flat": "flat.zarr is a regular file, not a folder: refused (a NAME.zarr recording is the "
                              "folder of a Zarr store)"}


def test_a_store_given_as_the_inbox_is_refused_in_one_line_before_the_outbox_is_made(tmp_path, cli):
    """A recording's own store given as INBOX was walked as a folder of recordings: a line refusing each of its
    arrays, then a failed pass, with OUTBOX made. Now one line, and nothing made."""
    import zarr

    store = tmp_path / "rec.zarr"
    zarr.open_group(str(store), mode="w").create_array("spikes", shape=(4, 2), dtype="uint8")
    outbox = tmp_path / "out"
    result = cli("watch", store, outbox, "--once", "--settle", "0")
    assert result.exit_code != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "is a Zarr store, not a folder of recordings" in lines[0], result.stderr
    assert not outbox.exists()
