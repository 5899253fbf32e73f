"""``cscsr watch``: an inbox processed once per recording, bad input recorded, kills survived."""

import json
import os
import sqlite3
import subprocess
import time

import pytest

from cscsr import samples
from pipeline.inbox.ledger import Ledger
from pipeline.inbox.watch import WatchOptions, outbox_lock, parse_interval, watch_once
from stages.errors import InputError
from tests.conftest import CSCSR, committed_tasks, kill_mid_job
from tests.test_simulate import chunk_files

REDS = {"height": samples.REDS_HEIGHT, "width": samples.REDS_WIDTH, "cfa": "mono", "flip": True}


def settled(folder) -> None:
    """Make everything in ``folder`` a minute old, as if copied in long ago."""
    past = time.time() - 60
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            os.utime(os.path.join(root, name), (past, past))


def drop(inbox, name: str, data: bytes, sidecar=None) -> None:
    (inbox / name).write_bytes(data)
    if sidecar is not None:
        stem = name.rsplit(".", 1)[0]
        (inbox / f"{stem}.json").write_text(sidecar if isinstance(sidecar, str) else json.dumps(sidecar))


def states(outbox) -> dict:
    return {row.name: (row.state, row.final, row.attempts, row.error) for row in Ledger(outbox).rows()}


def test_bad_input_is_recorded_and_never_stops_the_others(tmp_path, client, cli):
    inbox, outbox = tmp_path / "inbox", tmp_path / "box" / "outbox"
    inbox.mkdir()
    reds = open(samples.path(samples.REDS_DAT), "rb").read()
    drop(inbox, "good.dat", reds, REDS)
    drop(inbox, "truncated.dat", reds[:100_001], REDS)
    drop(inbox, "nonsense.dat", reds, "{height: tall")
    drop(inbox, "wrongtype.dat", reds, {**REDS, "height": "250"})
    drop(inbox, "badfps.dat", reds, {**REDS, "fps": -1})  # said as the sidecar's field, not as an option --fps
    drop(inbox, "notes.txt", b"hello")
    drop(inbox, "sneaky.dat", reds, {**REDS, "name": "../../escaped"})
    settled(inbox)
    drop(inbox, "growing.dat", reds[:50_000], REDS)  # just landed: left for a later pass

    counts = watch_once(str(inbox), str(outbox), WatchOptions(tile=128), client)
    assert counts == {"processed": 1, "waiting": 1, "skipped": 0, "refused": 6}  # truncated: refused on ingest
    got = states(outbox)
    assert got["good"][:3] == ("done", 0, 1)
    assert got["truncated"][:2] == ("failed", 1) and "12500" in got["truncated"][3]  # names the frame size
    assert "not JSON" in got["nonsense"][3] and "height must be int" in got["wrongtype"][3]
    assert got["badfps"][3] == "sidecar badfps.json: fps must be > 0, got -1.0"
    assert "unknown kind of file 'notes.txt'" in got["notes"][3]
    assert "unsafe name '../../escaped'" in got["../../escaped"][3]
    assert "growing" not in got
    assert sorted(os.listdir(outbox)) == [".watch.lock", "good.mp4", "good.zarr", "ledger.sqlite", "spikes"] \
        or sorted(os.listdir(outbox)) == ["good.mp4", "good.zarr", "ledger.sqlite", "spikes"]
    assert os.listdir(outbox / "spikes") == ["good.zarr"]  # truncated's store removed, no claim file left
    assert sorted(os.listdir(tmp_path)) == ["box", "inbox"] and os.listdir(tmp_path / "box") == ["outbox"]

    settled(inbox)  # the growing file stopped growing: taken now (and refused: 50,000 bytes is not whole frames)
    again = watch_once(str(inbox), str(outbox), WatchOptions(tile=128), client)
    assert again == {"processed": 0, "waiting": 0, "skipped": 7, "refused": 1}  # good, truncated and the 5 refused
    # before: handled
    assert states(outbox)["good"][2] == 1 and states(outbox)["growing"][0] == "failed"  # done once, not twice
    assert len(Ledger(outbox).rows()) == 8  # one row per recording, however many passes

    result = cli("status", outbox)
    assert result.exit_code == 0 and "good" in result.stdout and "done" in result.stdout
    lines = json.loads(cli("status", outbox, "--json").stdout)  # one JSON list, one object per recording
    assert {line["name"] for line in lines} >= {"good", "truncated", "notes"}


def test_recordings_whose_outputs_would_collide_keep_their_own(tmp_path, client):
    """``a.dat`` and ``a.spikes.zarr`` in one inbox: the capture's spike store was ``OUTBOX/a.spikes.zarr``,
    the very path of the other recording's video, which overwrote it. Now each keeps its own outputs."""
    import zarr

    from pipeline.jobs.ingest import IngestOptions, ingest
    from tests.conftest import integrate_and_fire, smooth_rate, write_dat
    from tests.reliability.test_overlap import snapshot

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    write_dat(inbox / "a.dat", integrate_and_fire(smooth_rate(16, 16, seed=1), 101, seed=1))
    (inbox / "a.json").write_text(json.dumps({"height": 16, "width": 16, "cfa": "rggb"}))
    ingest(str(inbox / "a.dat"), str(tmp_path / "expected.zarr"), IngestOptions(16, 16, cfa="rggb"), progress=False)
    write_dat(tmp_path / "other.dat", integrate_and_fire(smooth_rate(16, 16, seed=2), 123, seed=2))
    ingest(str(tmp_path / "other.dat"), str(inbox / "a.spikes.zarr"), IngestOptions(16, 16, cfa="rggb"), progress=False)
    settled(inbox)
    inbox_before = snapshot(inbox)

    counts = watch_once(str(inbox), str(outbox), WatchOptions(tile=16, settle=0), client)
    assert counts["processed"] == 2 and counts["refused"] == 0
    assert {name: state[:2] for name, state in states(outbox).items()} == {"a": ("done", 0), "a.spikes": ("done", 0)}

    def opened(path):
        return zarr.open_group(str(path), mode="r")

    made_from = opened(outbox / "a.zarr").attrs["source"]  # the spike store ingested from a.dat
    spikes, expected = opened(made_from), opened(tmp_path / "expected.zarr")
    assert "video" not in spikes and (spikes["spikes"][:] == expected["spikes"][:]).all()  # a.dat's, intact
    assert made_from == str(outbox / "spikes" / "a.zarr")
    assert opened(outbox / "a.spikes.zarr").attrs["source"] == str(inbox / "a.spikes.zarr")
    assert opened(outbox / "a.zarr")["video"].shape[0] == 2 and opened(outbox / "a.spikes.zarr")["video"].shape[0] == 3
    assert snapshot(inbox) == inbox_before  # the recordings themselves untouched
    assert sorted(p for p in os.listdir(outbox) if not p.startswith(".")) == [
        "a.mp4", "a.spikes.mp4", "a.spikes.zarr", "a.zarr", "ledger.sqlite", "spikes"]


def test_failures_are_retried_with_back_off_then_quarantined(tmp_path, client, monkeypatch):
    import pipeline.inbox.watch

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "flaky.dat", open(samples.path(samples.REDS_DAT), "rb").read(), REDS)
    settled(inbox)
    calls = []

    def broken(*args, **kwargs):
        calls.append(args)
        raise OSError("disk on fire")

    monkeypatch.setattr(pipeline.inbox.watch, "reconstruct", broken)
    options = WatchOptions(max_attempts=3, backoff=3600)
    watch_once(str(inbox), str(outbox), options, client)
    state, final, attempts, error = states(outbox)["flaky"]
    assert (state, final, attempts) == ("failed", 0, 1) and "OSError: disk on fire" in error
    watch_once(str(inbox), str(outbox), options, client)
    assert len(calls) == 1  # the back-off (an hour) has not passed: not retried yet
    for _ in range(3):
        with sqlite3.connect(outbox / "ledger.sqlite") as db:  # let the back-off pass
            db.execute("UPDATE recordings SET next_try = 0")
        watch_once(str(inbox), str(outbox), options, client)
    assert len(calls) == 3 and states(outbox)["flaky"][:3] == ("quarantined", 0, 3)


def test_a_second_watcher_is_refused_and_intervals_parse(tmp_path, cli):
    (tmp_path / "inbox").mkdir()
    (tmp_path / "outbox").mkdir()
    with outbox_lock(str(tmp_path / "outbox")):
        result = cli("watch", tmp_path / "inbox", tmp_path / "outbox", "--once", "--workers", 1)
    assert result.exit_code == 1 and "another cscsr watch is already working" in result.stdout + result.stderr
    assert parse_interval("10m") == 600 and parse_interval("90") == 90 and parse_interval("1h") == 3600
    with pytest.raises(InputError, match="30s, 10m or 1h"):
        parse_interval("soon")
    assert cli("status", tmp_path / "inbox").exit_code == 1  # no ledger there
    both = cli("watch", tmp_path / "inbox", tmp_path / "fresh", "--once", "--interval", "5m", "--workers", 1)
    assert both.exit_code == 1 and both.stderr.strip() == ("error: --once and --interval 5m contradict each other: "
                                                           "--once makes one pass, --interval passes again and "
                                                           "again: give one")
    assert not (tmp_path / "fresh").exists()
    huge = cli("watch", tmp_path / "inbox", tmp_path / "fresh", "--interval", "99999999999h", "--workers", 1)
    assert huge.exit_code == 1 and huge.stderr.strip() == ("error: --interval must be at most 168h (a week), got "
                                                           "'99999999999h': for rarer passes, run cscsr watch --once "
                                                           "from cron")  # not an OverflowError after the first pass
    assert not (tmp_path / "fresh").exists() and parse_interval("168h") == 7 * 24 * 3600


def _ledger_state(outbox, name):
    try:
        row = next((r for r in Ledger(outbox).rows() if r.name == name), None)
    except sqlite3.Error:
        return None
    return row.state if row else None


def test_killing_the_watcher_mid_job_loses_nothing_and_duplicates_nothing(tmp_path):
    """A real ``cscsr watch`` process group is SIGKILLed while it reconstructs; the next pass finishes the
    job: one ledger row (2 attempts), outputs byte-identical to an uninterrupted watcher's."""
    from pipeline.compute.hold import hold_environment
    from pipeline.jobs.simulate import SimulateOptions, simulate
    from tests.test_simulate import picture
    import imageio.v3 as iio

    inbox = tmp_path / "inbox"
    inbox.mkdir()
    iio.imwrite(tmp_path / "scene.png", picture("coffee", 128))
    simulate(str(tmp_path / "scene.png"), str(inbox / "scene.zarr"),
             SimulateOptions(scale=4, frames=250, motion="random", speed=0.3), workers=1, progress=False)
    settled(inbox)
    args = ["watch", str(inbox), None, "--once", "--workers", "1", "--every", "5", "--tile", "16", "--settle", "0"]

    def command(outbox):
        return [CSCSR] + [str(outbox) if a is None else a for a in args]

    subprocess.run(command(tmp_path / "clean"), check=True, capture_output=True)

    killed = tmp_path / "killed"
    # the job's tasks hold after the 30th (pipeline.compute.hold): the kill lands mid-job on any machine, under any load
    kill_mid_job(command(killed), lambda: (_ledger_state(killed, "scene") == "running"
                                           and committed_tasks(killed / "scene.zarr") >= 20),
                 env={**os.environ, **hold_environment(30, tmp_path / "never")})
    total = len(range(20, 250 - 20, 5)) * 4  # tiles of 16 of LR 32x32
    assert _ledger_state(killed, "scene") == "running" and 20 <= committed_tasks(killed / "scene.zarr") < total

    subprocess.run(command(killed), check=True, capture_output=True)
    rows = Ledger(killed).rows()
    assert [(r.name, r.state, r.attempts) for r in rows] == [("scene", "done", 2)]
    assert chunk_files(str(killed / "scene.zarr")) == chunk_files(str(tmp_path / "clean" / "scene.zarr"))
    assert sorted(p for p in os.listdir(killed) if not p.startswith(".")) == ["ledger.sqlite", "scene.mp4", "scene.zarr"]
