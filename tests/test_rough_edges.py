"""Rough edges of issue #48, each held by a test that failed before its fix.

- Dry runs print durations readably (``0.5 s``, ``3 min``, ``1.2 h``, never ``0.000139591`` hours; ``--json`` keeps
  the exact numbers); ingest's plan shows no task larger than the capture, and prices the task it would run;
  reconstruct's dry run never times more tasks than the job has (or a few rounds of its workers).
- Result lines: ingest's names its frames; a ``--workers`` ingest of one task runs in this process, and says so;
  jobs that share a client print its dashboard link once.
"""

import json
import re

import numpy as np
import pytest
from distributed import Client, LocalCluster

from pipeline.cli.recordings import duration
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.jobs.dry_run import MOST_TASKS, _most_sampled
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from tests.conftest import write_dat

FRAMES, SIDE = 301, 16


@pytest.fixture
def dat(tmp_path) -> str:
    """A 301-frame 16x16 .dat: one default task is far more frames than that."""
    path = tmp_path / "c.dat"
    write_dat(path, (np.random.default_rng(0).random((FRAMES, SIDE, SIDE)) < 0.2).astype(np.uint8))
    return str(path)


# --- dry runs ---------------------------------------------------------------------------------

def test_durations_are_read_in_the_unit_that_suits_them():
    assert [duration(s) for s in (0.0005, 0.5, 41, 180, 9000, 36000)] == \
        ["0.0005 s", "0.5 s", "41 s", "3 min", "2.5 h", "10 h"]


def test_ingest_dry_run_shows_times_not_hours_and_no_task_larger_than_the_capture(dat, cli, tmp_path):
    store = tmp_path / "s.zarr"
    plan = json.loads(cli("ingest", dat, store, "--height", SIDE, "--width", SIDE, "--dry-run", "--json").stdout)
    assert plan["frames"] == FRAMES and plan["tasks"] == 1 and plan["task_frames"] == FRAMES
    assert plan["hours"]["1"] == pytest.approx(plan["seconds_per_task"] / 3600)  # exact numbers in JSON
    table = cli("ingest", dat, store, "--height", SIDE, "--width", SIDE, "--dry-run")
    assert table.exit_code == 0, table.stderr
    rows = {line.split("│")[1].strip(): line.split("│")[2].strip() for line in table.stdout.splitlines()
            if line.count("│") == 3}
    assert rows["task_frames"] == str(FRAMES)
    for key in ("time on 1 worker", "time on 64 workers", "seconds_per_task"):
        assert re.fullmatch(r"[0-9.]+ (s|min|h)", rows[key]), (key, rows[key])
    assert not store.exists()


def test_a_dry_run_samples_no_more_tasks_than_the_job_has():
    assert _most_sampled(14, 1) == 13  # and a warm-up task: the 14 of the job
    assert _most_sampled(14, 2) == 12 and _most_sampled(14, 4) == 8  # whole rounds of a task a worker
    assert _most_sampled(1, 1) == 1 and _most_sampled(3, 2) == 2  # one timed round at least (a task for each)
    assert _most_sampled(10**6, 2) == MOST_TASKS * 2


def dry_run_on_one_worker(tmp_path, monkeypatch, seconds: float, frames: int) -> dict:
    """The plan of a TFP dry run (every 7, tiles of 16) of ``frames`` frames of LR 16x32 that samples for about
    ``seconds``, on a cluster of one worker in this process."""
    import pipeline.jobs.dry_run

    monkeypatch.setattr(pipeline.jobs.dry_run, "SAMPLE_SECONDS", seconds)
    np.save(tmp_path / "s.npy", (np.random.default_rng(1).random((frames, 16, 32)) < 0.2).astype(np.uint8))
    ingest(str(tmp_path / "s.npy"), str(tmp_path / "s.zarr"), IngestOptions(cfa="rggb"), progress=False)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as local, \
            Client(local) as client:
        return reconstruct(str(tmp_path / "s.zarr"), str(tmp_path / "out.zarr"),
                           ReconstructOptions(every=7, tile=16), client=client, dry_run=True)


def test_reconstruct_dry_run_of_a_small_job_times_at_most_its_tasks(tmp_path, monkeypatch):
    plan = dry_run_on_one_worker(tmp_path, monkeypatch, 30.0, 120)  # tasks of milliseconds: the cap stops it
    assert plan["tasks"] < 40 and plan["measured"]["tasks"] + plan["workers"] <= plan["tasks"]
    assert plan["seconds_per_task"] > 0


def test_a_dry_run_of_tasks_longer_than_its_sampling_time_times_one_round(tmp_path, monkeypatch):
    """Tasks that take longer than the sampling time (the network's on a whole 1000x1000 frame, a minute each) are
    timed once a worker after the warm-up: three rounds made a dry run cost half the job."""
    plan = dry_run_on_one_worker(tmp_path, monkeypatch, 0.0, 300)  # every task is longer than no time
    assert plan["tasks"] > 10 and plan["measured"]["tasks"] == 1 and plan["seconds_per_task"] > 0


# --- result lines -----------------------------------------------------------------------------

def test_ingest_result_names_its_frames(dat, cli, tmp_path):
    result = cli("ingest", dat, tmp_path / "s.zarr", "--height", SIDE, "--width", SIDE)
    assert result.exit_code == 0, result.stderr
    assert re.fullmatch(rf"\S+s\.zarr: {FRAMES} frames 16x16, cfa mono, \d+ spikes\n", result.stdout)


def test_a_parallel_ingest_of_one_task_runs_in_this_process_and_says_so(dat, cli, tmp_path, monkeypatch):
    import pipeline.jobs.ingest

    def no_cluster(*args, **kwargs):
        raise AssertionError("a local cluster was started for one task")

    monkeypatch.setattr(pipeline.jobs.ingest, "in_segments", no_cluster)  # what starts local clusters
    result = cli("ingest", dat, tmp_path / "s.zarr", "--height", SIDE, "--width", SIDE, "--workers", 2)
    assert result.exit_code == 0, result.stderr
    assert "(1 task run, 0 already committed)" in result.stdout
    assert [line for line in result.stderr.splitlines() if "one task" in line and "in this process" in line]
    plan = json.loads(cli("ingest", dat, tmp_path / "t.zarr", "--height", SIDE, "--width", SIDE, "--workers", 2,
                          "--dry-run", "--json").stdout)
    assert plan["runs_on"] == "this process"


def test_jobs_on_one_client_print_its_dashboard_once(tmp_path, capsys):
    np.save(tmp_path / "s.npy", (np.random.default_rng(1).random((90, 16, 16)) < 0.2).astype(np.uint8))
    ingest(str(tmp_path / "s.npy"), str(tmp_path / "s.zarr"), IngestOptions(cfa="rggb"), progress=False)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address="127.0.0.1:0") as local, \
            Client(local) as client:
        for name in ("a", "b", "c"):
            reconstruct(str(tmp_path / "s.zarr"), str(tmp_path / f"{name}.zarr"), ReconstructOptions(every=41),
                        client=client)
    assert capsys.readouterr().err.count("dashboard: ") == 1


# --- status -----------------------------------------------------------------------------------

def test_status_shows_a_recording_once_in_its_latest_state_as_one_json_document(cli, tmp_path):
    from pipeline.inbox.ledger import Ledger

    ledger, source = Ledger(tmp_path), str(tmp_path / "inbox" / "a.dat")
    ledger.record_refusal("refused", "a", source, "sidecar a.json is not JSON")  # then the sidecar was fixed
    ledger.queue("fixed", "a", source, "bytes", {"method": "tfp"})
    ledger.start("fixed", "a")
    ledger.done("fixed", 1.5)
    ledger.record_refusal("other", "b", str(tmp_path / "inbox" / "b.txt"), "unknown kind of file 'b.txt'")
    rows = json.loads(cli("status", tmp_path, "--json").stdout)  # one JSON list, not JSON Lines
    assert [(row["name"], row["state"], row["attempts"]) for row in rows] == [("a", "done", 2), ("b", "failed", 1)]
    assert rows[0]["params"] == {"method": "tfp"} and rows[1]["params"] == {}  # objects, not JSON inside JSON
    assert rows[0]["final"] is False and rows[1]["final"] is True  # booleans, not 0 and 1
    table = cli("status", tmp_path)
    assert table.exit_code == 0 and "2 recordings" in table.stdout
    assert [line for line in table.stdout.splitlines() if "│ a " in line][0].count("done") == 1
    assert len([line for line in table.stdout.splitlines() if line.startswith("│ a ")]) == 1


# --- nonsense video-store attributes ----------------------------------------------------------

@pytest.fixture(scope="module")
def video_store(tmp_path_factory) -> str:
    """A complete video store of a region (LR 0:8,8:32 of a 16x32 recording, x4), 2 frames."""
    folder = tmp_path_factory.mktemp("video")
    np.save(folder / "s.npy", (np.random.default_rng(1).random((90, 16, 32)) < 0.2).astype(np.uint8))
    ingest(str(folder / "s.npy"), str(folder / "s.zarr"), IngestOptions(cfa="rggb"), progress=False)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as local, \
            Client(local) as client:
        reconstruct(str(folder / "s.zarr"), str(folder / "v.zarr"), ReconstructOptions(every=41, region="0:8,8:32"),
                    client=client, progress=False)
    return str(folder / "v.zarr")


def edited_copy(store: str, folder, attrs: dict | None = None, channels: int | None = None) -> str:
    """A copy of ``store`` with ``attrs`` set, or its video's metadata (its own and the consolidated copy) saying
    ``channels``."""
    import shutil

    copy = str(folder / "edited.zarr")
    shutil.copytree(store, copy)
    for path, at in ((f"{copy}/zarr.json", ("consolidated_metadata", "metadata", "video")),
                     (f"{copy}/video/zarr.json", ())):
        with open(path) as handle:
            document = json.load(handle)
        node = document
        for key in at:
            node = node[key]
        if channels is not None:
            node["shape"][3] = node["chunk_grid"]["configuration"]["chunk_shape"][3] = channels
        if attrs is not None and path.endswith(f"{copy}/zarr.json"):
            document["attributes"].update(attrs)
        with open(path, "w") as handle:
            json.dump(document, handle)
    return copy


@pytest.mark.parametrize("attrs, named", [
    ({"fps": -1.0}, "fps -1.0 is not a finite number > 0"),
    ({"fps": float("inf")}, "fps inf is not a finite number > 0"),
    ({"scale": 0}, "scale 0 is not a whole number >= 1"),
    ({"window": -41}, "window -41 is not a whole number >= 1"),
    ({"every": 0}, "every 0 is not a whole number >= 1"),
    ({"region": [0, 8, 40, 64]}, "region 0:8,40:64 is not inside the recording's 16x32 frame"),
    ({"region": [0, 4, 8, 32]}, "region 0:4,8:32 at x4 is 16x96 HR, but 'video' frames are 32x96"),
])
def test_nonsense_video_store_attributes_are_refused_in_one_line(video_store, cli, tmp_path, attrs, named):
    store = edited_copy(video_store, tmp_path, attrs)
    for args in (("info", store), ("info", store, "--json"), ("export", store, tmp_path / "v.mp4")):
        result = cli(*args)
        assert result.exit_code == 1 and result.stdout == "", (args, result.stdout)
        assert result.stderr.strip().splitlines() == [f"error: video store {store}: metadata inconsistent: {named}: "
                                                      f"the store was altered or damaged; make it again with cscsr "
                                                      f"reconstruct --overwrite"], args
    assert not (tmp_path / "v.mp4").exists()


def test_a_video_store_of_four_channels_is_not_an_rgb_video_store(video_store, cli, tmp_path):
    store = edited_copy(video_store, tmp_path, channels=4)
    for args in (("info", store), ("export", store, tmp_path / "v.mp4")):
        result = cli(*args)
        assert result.exit_code == 1 and "lost data" not in result.stderr + result.stdout
        assert result.stderr.strip().splitlines() == [
            f"error: {store} is not an RGB video store: its 'video' is uint8 (2, 32, 96, 4), not (frames, height, "
            f"width, 3) uint8: give a store made by cscsr reconstruct"], args


def test_the_untouched_store_passes(video_store, cli):
    assert json.loads(cli("info", video_store, "--json").stdout)["state"] == "complete"


# --- keys and sidecars that mean nothing ------------------------------------------------------

@pytest.mark.parametrize("capture, layout", [("c.dat", None), ("c.npy", None), ("c.bin", "dat")])
def test_a_key_for_a_capture_without_keys_is_refused_before_anything_is_made(dat, cli, tmp_path, capture, layout):
    import shutil

    source = tmp_path / capture
    if capture.endswith(".npy"):
        np.save(source, np.zeros((8, SIDE, SIDE), np.uint8))
    elif str(source) != dat:
        shutil.copy(dat, source)
    store = tmp_path / "new" / "s.zarr"
    args = ["ingest", source, store, "--height", SIDE, "--width", SIDE, "--key", "spk"]
    for dry_run in ([], ["--dry-run"]):
        result = cli(*args, *(["--layout", layout] if layout else []), *dry_run)
        assert result.exit_code == 1 and result.stdout == ""
        (line,) = result.stderr.strip().splitlines()
        assert line.startswith("error: --key names an array inside a .npz, and ") and "leave --key out" in line
    assert not (tmp_path / "new").exists()


def test_the_watcher_records_sidecar_fields_that_mean_nothing_beside_their_recording(tmp_path, cli):
    from pipeline.inbox.ledger import Ledger
    from pipeline.inbox.watch import WatchOptions, discover, watch_once
    from tests.test_watch import settled

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    write_dat(inbox / "a.dat", np.zeros((41, SIDE, SIDE), np.uint8))
    (inbox / "a.json").write_text(json.dumps({"height": SIDE, "width": SIDE, "cfa": "mono", "key": "spk"}))
    np.save(tmp_path / "b.npy", np.zeros((41, SIDE, SIDE), np.uint8))
    ingest(str(tmp_path / "b.npy"), str(inbox / "b.zarr"), IngestOptions(cfa="rggb"), progress=False)
    (inbox / "b.json").write_text(json.dumps({"cfa": "mono", "fps": 1000}))
    settled(inbox)
    named = tmp_path / "named"
    named.mkdir()
    ingest(str(tmp_path / "b.npy"), str(named / "c.zarr"), IngestOptions(cfa="rggb"), progress=False)
    (named / "c.json").write_text(json.dumps({"name": "cee"}))  # a name applies to a store: taken
    assert [(found.name, found.problem) for found in discover(str(named))] == [("cee", None)]
    counts = watch_once(str(inbox), str(outbox), WatchOptions(), client=None)
    assert counts == {"processed": 0, "waiting": 0, "skipped": 0, "refused": 2}
    errors = {row.name: row.error for row in Ledger(outbox).rows() if row.state == "failed" and row.final}
    assert errors == {
        "a": "sidecar a.json: key names an array inside a .npz, and a.dat has none: remove it",
        "b": "sidecar b.json: cfa, fps describe a raw capture, and b.zarr is a spike store, which records its own: "
             "remove them (only 'name' applies to a store)"}
