"""The watcher's log lines (``logging``, timestamped, one per event) and the global ``-q/--quiet`` and
``-v/--verbose`` options."""

import json
import logging
import re

import numpy as np

from tests.test_watch import drop, settled

LINE = re.compile(r"^(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d[+-]\d{4}) (DEBUG|INFO|WARNING|ERROR) cscsr\.watch: (.*)$")


def tiny_capture(seed: int = 0) -> bytes:
    """A 50-frame 16x16 spike capture as the bytes of a .npy file."""
    import io

    buffer = io.BytesIO()
    np.save(buffer, (np.random.default_rng(seed).random((50, 16, 16)) < 0.3).astype(np.uint8))
    return buffer.getvalue()


def records(text: str) -> list[tuple[str, str]]:
    """(level, message) of every log line; any other line on the stream fails the test."""
    lines = [line for line in text.splitlines() if line.strip()]
    matched = [LINE.match(line) for line in lines]
    assert all(matched), f"not a log line: {[l for l, m in zip(lines, matched) if not m]}"
    return [(m.group(2), m.group(3)) for m in matched]


def watch_args(inbox, outbox, *more):
    return ["watch", inbox, outbox, "--once", "--workers", 1, "--settle", 0, "--tile", 16, "--every", 5, *more]


def test_the_watcher_logs_one_timestamped_line_per_event(tmp_path, cli):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "good.npy", tiny_capture(), {"height": 16, "width": 16, "cfa": "rggb"})
    drop(inbox, "nonsense.npy", tiny_capture(1), "{height: tall")
    settled(inbox)

    result = cli(*watch_args(inbox, outbox))
    assert result.exit_code == 0 and result.stdout == ""  # log lines are not results: never on stdout
    logged = records(result.stderr)
    good = [message for level, message in logged if message.startswith("good: ")]
    assert [m.split()[1] for m in good] == ["found", "claimed", "ingested", "reconstructed", "exported", "done"]
    assert all(level == "INFO" for level, message in logged if message.startswith("good: "))
    assert str(outbox / "good.mp4") in good[4] and str(outbox / "good.zarr") in good[5]
    failed = [(level, message) for level, message in logged if message.startswith("nonsense: ")]
    assert len(failed) == 1 and failed[0][0] == "ERROR"
    assert "failed: sidecar nonsense.json is not JSON" in failed[0][1]  # the reason, on the same line
    assert logged[-1] == ("INFO", f"pass over {inbox}: 1 processed, 0 still settling, 0 already handled, 1 refused")

    again = cli("-v", *watch_args(inbox, outbox))  # nothing new: skips are DEBUG lines, shown with -v
    assert ("DEBUG", "good: skipped: already done") in records(again.stderr)
    assert ("DEBUG", f"nonsense: skipped: refused before ({inbox / 'nonsense.npy'})") in records(again.stderr)
    quiet = cli("-q", *watch_args(inbox, outbox))
    assert quiet.exit_code == 0 and quiet.stdout == "" and quiet.stderr.strip() == ""  # warnings and errors only

    status = json.loads(cli("status", outbox, "--json").stdout)  # one JSON list
    assert {row["name"]: row["state"] for row in status} == {"good": "done", "nonsense": "failed"}  # unchanged


def test_a_pass_that_refused_every_recording_exits_non_zero(tmp_path, cli):
    """``watch --once`` for cron: a pass that refused everything it found says so in one line and exits 1 (it exited
    0); one that took a recording beside a refused one ends as usual (the test above). A refusal is said once: a
    later pass that finds nothing new ends as usual (it exited 1 on every pass, pointing at lines it did not
    print, so cron alerted every few minutes for ever), and one that refuses a new recording says so again."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "nonsense.npy", tiny_capture(1), "{height: tall")
    drop(inbox, "nocfa.npy", tiny_capture(2), {"height": 16, "width": 16})
    settled(inbox)

    result = cli(*watch_args(inbox, outbox))
    assert result.exit_code == 1, result.stderr
    *logged, last = result.stderr.strip().splitlines()
    assert last == f"error: every recording in {inbox} was refused (2): see the lines above, or cscsr status {outbox}"
    assert [level for level, message in records("\n".join(logged))] == ["ERROR", "ERROR", "INFO"]  # each, the pass
    again = cli(*watch_args(inbox, outbox))  # refused before: handled, nothing new
    assert again.exit_code == 0 and "error" not in again.stderr, again.stderr
    drop(inbox, "broken.npy", tiny_capture(3), "{width: wide")
    settled(inbox)
    newly = cli(*watch_args(inbox, outbox))
    assert newly.exit_code == 1 and newly.stderr.strip().splitlines()[-1].startswith(
        f"error: every recording in {inbox} was refused (1)")



def test_a_capture_refused_as_truncated_while_processed_is_refused_too(tmp_path, cli):
    """A truncated capture is bad input found during its ingest, not before: it was counted as processed, and a
    ``--once`` pass of it alone exited 0. Now it is refused as a nonsense sidecar is: one line, exit status 1."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "cut.dat", bytes(100), {"height": 16, "width": 16, "cfa": "rggb"})  # 3 frames of 32 bytes, and 4
    settled(inbox)

    result = cli(*watch_args(inbox, outbox))
    assert result.exit_code == 1, result.stderr
    *logged, last = result.stderr.strip().splitlines()
    assert last == f"error: every recording in {inbox} was refused (1): see the lines above, or cscsr status {outbox}"
    assert records("\n".join(logged))[-1] == ("INFO", f"pass over {inbox}: 0 processed, 0 still settling, 0 already "
                                                        f"handled, 1 refused")
    row = json.loads(cli("status", outbox, "--json").stdout)[0]
    assert (row["name"], row["state"], bool(row["final"])) == ("cut", "failed", True) and "32" in row["error"]
    again = cli(*watch_args(inbox, outbox))  # refused before: handled, nothing new
    assert again.exit_code == 0, again.stderr

def test_a_retry_is_a_warning_and_log_file_takes_the_lines(tmp_path, cli, monkeypatch):
    import pipeline.inbox.watch

    def broken(*args, **kwargs):
        raise OSError("disk on fire")

    monkeypatch.setattr(pipeline.inbox.watch, "reconstruct", broken)
    inbox, outbox, log = tmp_path / "inbox", tmp_path / "outbox", tmp_path / "logs" / "watch.log"
    inbox.mkdir()
    log.parent.mkdir()
    drop(inbox, "flaky.npy", tiny_capture(), {"height": 16, "width": 16, "cfa": "rggb"})
    settled(inbox)
    result = cli(*watch_args(inbox, outbox, "--log-file", log))
    assert result.exit_code == 0 and result.stdout == "" and result.stderr.strip() == ""  # all in the file
    logged = records(log.read_text())
    assert [level for level, message in logged if "will retry" in message] == ["WARNING"]
    assert ("WARNING", "flaky: failed, will retry in 60 s (attempt 1 of 3): OSError: disk on fire") in logged

    cli(*watch_args(inbox, outbox, "--log-file", log))  # appended, not replaced
    assert len(records(log.read_text())) > len(logged)

    inside = cli(*watch_args(inbox, tmp_path / "other", "--log-file", inbox / "watch.log"))
    assert inside.exit_code == 1 and inside.stderr.startswith("error: output") and "is inside input" in inside.stderr
    assert len(inside.stderr.strip().splitlines()) == 1 and not (inbox / "watch.log").exists()
    folder = cli(*watch_args(inbox, tmp_path / "other", "--log-file", tmp_path / "logs"))
    assert folder.exit_code == 1 and folder.stderr.strip() == f"error: --log-file {tmp_path / 'logs'} is a folder: " \
                                                               f"give a file to append the log lines to"


def test_quiet_and_verbose_on_ingest(tmp_path, cli):
    (tmp_path / "a.npy").write_bytes(tiny_capture())
    forced = {"FORCE_COLOR": "1", "COLUMNS": "400"}  # rich draws its bar although stderr is not a terminal

    def ingest(*flags, store):
        from typer.testing import CliRunner

        from pipeline.cli import app

        result = CliRunner().invoke(app, [*flags, "ingest", str(tmp_path / "a.npy"), str(tmp_path / store)], env=forced)
        return result.exit_code, result.stdout, result.stderr

    code, out, err = ingest(store="plain.zarr")
    assert code == 0 and "50/50" in err and "ingest" in err  # the progress bar, on stderr
    for flags, store in ((("-q",), "quiet.zarr"), (("--quiet",), "quiet2.zarr")):
        q_code, q_out, q_err = ingest(*flags, store=store)
        assert q_code == 0 and q_err == "" and q_out == out.replace("plain.zarr", store)  # same result, no bar
    v_code, v_out, v_err = ingest("-v", store="verbose.zarr")
    assert v_code == 0 and v_out == out.replace("plain.zarr", "verbose.zarr") and "50/50" in v_err
    both = cli("-q", "-v", "ingest", tmp_path / "a.npy", tmp_path / "both.zarr")
    assert both.exit_code == 1 and both.stderr.strip() == "error: -q/--quiet and -v/--verbose exclude each other: give one"
    assert not (tmp_path / "both.zarr").exists()
    from pipeline.compute.progress import _quiet

    assert _quiet is False and logging.getLogger("cscsr").level == logging.NOTSET  # nothing left behind in-process


def test_verbose_lets_dask_warnings_through():
    from pipeline.compute.cluster import _dask_log_level

    logger = logging.getLogger("cscsr")
    assert _dask_log_level() == logging.ERROR
    logger.setLevel(logging.DEBUG)
    try:
        assert _dask_log_level() == logging.WARNING
    finally:
        logger.setLevel(logging.NOTSET)


def test_log_lines_survive_rotation_and_names_that_would_split_them(tmp_path, cli, monkeypatch):
    """--log-file moved away by log rotation (logrotate without copytruncate) while the watcher runs: its lines went
    on into the moved file for ever; now the file is opened again at its path. A file in INBOX whose name holds a
    newline split its lines, and could forge one; now each control character is shown escaped, each line one
    record."""
    import pipeline.inbox.watch

    inbox, outbox, log = tmp_path / "inbox", tmp_path / "outbox", tmp_path / "watch.log"
    inbox.mkdir()
    forged = "x.dat\n2025-01-01T00:00:00+0000 INFO cscsr.watch: x: done in 1.0 s"
    drop(inbox, forged + ".dat", b"\0" * 64)
    settled(inbox)
    real_pass = pipeline.inbox.watch.watch_once

    def rotated(*args):
        counts = real_pass(*args)
        log.rename(tmp_path / "watch.log.1")  # the pass's lines are written; logrotate moves the file
        return counts

    monkeypatch.setattr(pipeline.inbox.watch, "watch_once", rotated)
    result = cli(*watch_args(inbox, outbox, "--log-file", log))
    assert result.exit_code == 1 and "was refused (1)" in result.stderr  # the forged name: an unsafe name
    before, after = records((tmp_path / "watch.log.1").read_text()), records(log.read_text())
    assert after == [("INFO", f"pass over {inbox}: 0 processed, 0 still settling, 0 already handled, 1 refused")]
    (level, message), = before  # one record, one line: the name's newline escaped
    assert level == "ERROR" and message.startswith(r"x.dat\n2025-01-01T00:00:00+0000 INFO cscsr.watch: x: done in "
                                                   r"1.0 s: failed: unsafe name 'x.dat\n2025")
