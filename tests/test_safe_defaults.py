"""Issue 37, point 2: defaults that cannot silently damage a result.

1. The watcher guesses no CFA (it took every raw capture without a sidecar ``cfa`` as RGGB, while ``ingest``
   takes mono: a mono capture dropped in an inbox was demosaicked into colour speckle, with no warning).
2. ``evaluate-testset`` checks a named scheduler before it claims or replaces ``--out`` (the existing
   ``--out`` itself is refused unless ``--overwrite``: ``tests/reliability/test_silent_overwrites_and_bounds.py``).
3. A ``memory://`` input or output of a job whose tasks run in worker processes is refused up front, in one line
   (it failed only after every task had run, then advised a ``--resume`` that could not help).
4. ``-q`` prints nothing but errors and the result lines (the dashboard link came through); ``-v`` adds the
   job's plan and one line per task for ``reconstruct`` and ``ingest`` (it added nothing).
"""

import json
import logging
import os
import re

import fsspec
import numpy as np
import pytest
import zarr

from pipeline.jobs.ingest import IngestOptions
from pipeline.inbox.watch import WatchOptions, watch, watch_once
from stages.errors import InputError
from tests.conftest import integrate_and_fire, smooth_rate, write_dat
from tests.test_watch import drop, settled, states
from tests.test_watch_log import tiny_capture

MEMORY_REFUSAL = "memory:// lives in this process only, and this job's tasks run in worker processes"


def one_line_refusal(result, *fragments) -> None:
    assert result.exit_code == 1, (result.stdout, result.stderr)
    assert result.stderr.startswith("error: ") and result.stderr.count("\n") == 1, result.stderr
    for fragment in fragments:
        assert fragment in result.stderr, result.stderr


@pytest.fixture
def spikes(cli, tmp_path):
    """A 16x16 mono spike store of 41 frames (one output frame), ingested in this process."""
    write_dat(tmp_path / "scene.dat", integrate_and_fire(smooth_rate(16, 16), 41))
    store = tmp_path / "spikes.zarr"
    assert cli("ingest", tmp_path / "scene.dat", store, "--height", 16, "--width", 16).exit_code == 0
    return store


def memory_clean(prefix: str) -> bool:
    return not fsspec.filesystem("memory").exists(prefix)


# --- 1. the watcher guesses no CFA ---------------------------------------------------------------------

def test_the_watcher_refuses_a_raw_capture_whose_cfa_is_stated_nowhere(tmp_path, client):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "mono.npy", tiny_capture(), {"height": 16, "width": 16})  # a sidecar, but no cfa in it
    drop(inbox, "bare.npy", tiny_capture(1))  # no sidecar at all
    settled(inbox)
    options = WatchOptions(tile=16, every=5, settle=0)

    # before: both processed as RGGB (demosaicked colour speckle), no warning
    counts = watch_once(str(inbox), str(outbox), options, client)
    assert counts == {"processed": 0, "waiting": 0, "skipped": 0, "refused": 2}
    got = states(outbox)
    assert got["mono"][:2] == ("failed", 1) and got["bare"][:2] == ("failed", 1)
    assert got["mono"][3] == ('no CFA for mono.npy: give its sidecar mono.json a "cfa" (mono, rggb, bggr, grbg, '
                              'gbrg), or start the watcher with --cfa; none is guessed')
    assert "bare.json" in got["bare"][3]
    assert not (outbox / "spikes").exists() and not list(outbox.glob("*.zarr"))  # nothing ingested

    # stated in its sidecar: taken as stated (the sidecar lands after the capture: the refusal is not final)
    (inbox / "mono.json").write_text(json.dumps({"height": 16, "width": 16, "cfa": "mono"}))
    settled(inbox)
    counts = watch_once(str(inbox), str(outbox), options, client)
    assert counts["processed"] == 1 and counts["skipped"] == 1 and counts["refused"] == 0  # bare: refused before,
    # handled: not logged again
    assert zarr.open_group(str(outbox / "spikes" / "mono.zarr"), mode="r").attrs["cfa"] == "mono"
    assert states(outbox)["mono"][0] == "done"

    # --cfa: what a capture whose sidecar names none is taken to be
    stated = WatchOptions(tile=16, every=5, settle=0, defaults=IngestOptions(cfa="mono"))
    counts = watch_once(str(inbox), str(outbox), stated, client)
    assert counts == {"processed": 1, "waiting": 0, "skipped": 1, "refused": 0}  # mono.npy: the same key, done
    assert zarr.open_group(str(outbox / "spikes" / "bare.zarr"), mode="r").attrs["cfa"] == "mono"


def test_the_watchers_cfa_is_checked_and_shown_without_a_default(cli, tmp_path):
    from typer.testing import CliRunner

    from pipeline.cli import app

    (tmp_path / "inbox").mkdir()
    one_line_refusal(cli("watch", tmp_path / "inbox", tmp_path / "outbox", "--once", "--cfa", "rgbw"),
                     "unknown CFA 'rgbw'")
    assert not (tmp_path / "outbox").exists()
    shown = " ".join(CliRunner().invoke(app, ["watch", "--help"], env={"COLUMNS": "200"}).stdout
                     .replace("│", " ").split())
    assert "never guessed" in shown and "[default: rggb]" not in shown


# --- 2. evaluate-testset: every option before the output ------------------------------------------------

def test_evaluate_testset_checks_its_scheduler_before_claiming_out(tmp_path, monkeypatch):
    import pipeline.jobs.testset as testset

    tset = tmp_path / "set"
    tset.mkdir()
    (tset / "manifest.json").write_text(json.dumps({"items": [{"picture": "coffee", "alpha": 0.8, "seed": 1}]}))
    monkeypatch.setattr(testset, "checked_evaluation", lambda *args: None)  # the stores' checks: not the point

    def claimed(url):
        raise AssertionError(f"{url} claimed before the scheduler was checked")

    monkeypatch.setattr(testset, "claimed", claimed)
    with pytest.raises(InputError, match="cannot reach Dask scheduler tcp://127.0.0.1:1"):
        testset.evaluate_testset(str(tset), ["tfp"], str(tmp_path / "ev"), scheduler="tcp://127.0.0.1:1",
                                 progress=False)
    assert sorted(os.listdir(tmp_path)) == ["set"]


# --- 3. memory:// with worker processes ---------------------------------------------------------------

def test_memory_outputs_and_inputs_of_jobs_on_worker_processes_are_refused_up_front(cli, tmp_path, spikes):
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "scene.png", np.zeros((64, 64, 3), np.uint8))
    # before: reconstruct ran every task (each worker writing into a memory of its own), then "9 of 9 output frames
    # failed ... run again with --resume"; simulate failed on its first truth frame
    one_line_refusal(cli("reconstruct", spikes, "memory://safe/v.zarr", "--workers", 1),
                     "cannot use memory://safe/v.zarr: " + MEMORY_REFUSAL, "give a path or another URL")
    one_line_refusal(cli("simulate", tmp_path / "scene.png", "memory://safe/s.zarr", "--motion", "static",
                         "--workers", 1), "cannot use memory://safe/s.zarr: " + MEMORY_REFUSAL)
    one_line_refusal(cli("evaluate", spikes, "--out", "memory://safe/ev", "--workers", 1),
                     "cannot use memory://safe/ev: " + MEMORY_REFUSAL)
    one_line_refusal(cli("make-testset", "memory://safe/set", "--workers", 1), "cannot use memory://safe/set")
    one_line_refusal(cli("evaluate-testset", tmp_path, "--out", "memory://safe/ev2"), "cannot use memory://safe/ev2")
    one_line_refusal(cli("ingest", tmp_path / "scene.dat", "memory://safe/i.zarr", "--height", 16, "--width", 16,
                         "--workers", 1), "cannot use memory://safe/i.zarr: " + MEMORY_REFUSAL,
                     "or ingest without --workers or --scheduler")
    assert memory_clean("/safe")  # nothing written, not even a claim
    assert sorted(os.listdir(tmp_path)) == ["scene.dat", "scene.png", "spikes.zarr"]


def test_memory_is_refused_with_a_client_of_worker_processes_and_kept_for_one_in_this_process(tmp_path, client):
    from distributed import Client, LocalCluster

    from pipeline.jobs.ingest import ingest
    from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
    from pipeline.stores.video_store import open_video_store

    write_dat(tmp_path / "scene.dat", integrate_and_fire(smooth_rate(16, 16), 41))
    ingest(str(tmp_path / "scene.dat"), "memory://shared/s.zarr", IngestOptions(16, 16), progress=False)
    try:
        with pytest.raises(InputError, match="cannot use memory://shared/s.zarr: " + re.escape(MEMORY_REFUSAL)):
            reconstruct("memory://shared/s.zarr", str(tmp_path / "v.zarr"), client=client, progress=False)
        with pytest.raises(InputError, match="cannot use memory://shared/i.zarr"):
            ingest(str(tmp_path / "scene.dat"), "memory://shared/i.zarr", IngestOptions(16, 16), client=client,
                   progress=False)
        assert not (tmp_path / "v.zarr").exists() and memory_clean("/shared/i.zarr")
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as local, \
                Client(local) as here:  # workers in this process share its memory: as before
            counts = reconstruct("memory://shared/s.zarr", "memory://shared/v.zarr", ReconstructOptions(tile=8),
                                 client=here, progress=False)
        assert counts["frames"] == 1
        assert open_video_store("memory://shared/v.zarr").attrs["state"] == "complete"
    finally:
        fsspec.filesystem("memory").rm("/shared", recursive=True)


def test_a_watcher_on_a_memory_inbox_is_refused_before_its_outbox(tmp_path):
    fsspec.filesystem("memory").makedirs("/inbox-here", exist_ok=True)
    try:
        with pytest.raises(InputError, match="cannot use memory://inbox-here: " + re.escape(MEMORY_REFUSAL)):
            watch("memory://inbox-here", str(tmp_path / "outbox"), WatchOptions(), once=True, interval=1, workers=1)
    finally:
        fsspec.filesystem("memory").rm("/inbox-here", recursive=True)
    assert not (tmp_path / "outbox").exists()


# --- 4. -q and -v mean the same for every command ----------------------------------------------------

def test_quiet_reconstruct_prints_the_result_only_and_verbose_adds_the_plan_and_tasks(cli_process, tmp_path, spikes):
    quiet = cli_process("-q", "reconstruct", spikes, tmp_path / "q.zarr", "--workers", 1)
    assert quiet.returncode == 0, quiet.stderr
    assert " ".join(quiet.stdout.split()) == f"{tmp_path / 'q.zarr'}: 1 frame (1 task run, 0 already committed)"
    assert quiet.stderr == ""  # before: "dashboard: http://127.0.0.1:.../status"

    verbose = cli_process("-v", "reconstruct", spikes, tmp_path / "v.zarr", "--workers", 1)
    assert verbose.returncode == 0, verbose.stderr
    assert " ".join(verbose.stdout.split()) == " ".join(quiet.stdout.split()).replace("q.zarr", "v.zarr")
    debug = [line.split(": ", 1)[-1] for line in verbose.stderr.splitlines() if " DEBUG cscsr." in line]
    assert any(line.startswith(f"{spikes} -> {tmp_path / 'v.zarr'}: tfp, 1 output frames x 1 tiles") for line in debug)
    assert "output frames 0-0, tile (0, 0): committed" in debug  # one line per task
    assert any(line.startswith("segment 0: 1 tasks") for line in debug)
    assert re.search(r"^dashboard: http://127\.0\.0\.1:\d+/status$", verbose.stderr, re.MULTILINE)


def test_verbose_ingest_adds_the_plan_and_a_line_per_task(cli, tmp_path):
    write_dat(tmp_path / "scene.dat", integrate_and_fire(smooth_rate(16, 16), 41))
    result = cli("-v", "ingest", tmp_path / "scene.dat", tmp_path / "s.zarr", "--height", 16, "--width", 16)
    assert result.exit_code == 0 and result.stdout.startswith(f"{tmp_path / 's.zarr'}: ")
    debug = [line.split(" DEBUG cscsr.ingest: ", 1)[1] for line in result.stderr.splitlines()
             if " DEBUG cscsr.ingest: " in line]
    assert debug[0].startswith(f"{tmp_path / 'scene.dat'} -> {tmp_path / 's.zarr'}: 41 frames of 16x16, cfa mono; "
                               "1 tasks of ") and debug[0].endswith("in this process, one stream")
    assert re.fullmatch(r"task 0 \(frames 0-40\): \d+ spikes, committed", debug[1])
    plain = cli("ingest", tmp_path / "scene.dat", tmp_path / "t.zarr", "--height", 16, "--width", 16)
    assert "DEBUG" not in plain.stderr


def test_quiet_hides_the_dashboard_of_a_job_on_a_given_client(tmp_path, spikes, client, capsys):
    from pipeline.compute.progress import set_quiet
    from pipeline.jobs.reconstruct import reconstruct

    reconstruct(str(spikes), str(tmp_path / "a.zarr"), client=client, progress=True)
    assert "dashboard: " in capsys.readouterr().err
    set_quiet(True)
    try:
        reconstruct(str(spikes), str(tmp_path / "b.zarr"), client=client, progress=True)
    finally:
        set_quiet(False)
    assert "dashboard: " not in capsys.readouterr().err


def verbose_in_segment(client, items):
    """A segment's work: whether the segment process was told ``cscsr --verbose`` (Dask's warnings follow it)."""
    from pipeline.compute.cluster import _dask_log_level

    yield logging.getLogger("cscsr").isEnabledFor(logging.DEBUG), _dask_log_level()


def test_verbose_reaches_the_segment_processes():
    from pipeline.compute.executor import in_segments

    logger = logging.getLogger("cscsr")
    logger.setLevel(logging.DEBUG)
    try:
        told = list(in_segments(verbose_in_segment, [0, 1], 1, workers=1, show_dashboard=False))  # two processes
    finally:
        logger.setLevel(logging.NOTSET)
    assert told == [(True, logging.WARNING)] * 2  # before: (False, ERROR): -v let no Dask warning through
    told = list(in_segments(verbose_in_segment, [0], 1, workers=1, show_dashboard=False))  # one: in this process
    assert told == [(False, logging.ERROR)]
