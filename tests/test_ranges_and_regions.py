"""Parts of a recording (``reconstruct --start/--stop``, ``--region``) and the priced plan (``--dry-run``), on a real
LocalCluster(n_workers=2) and real Zarr stores.

- A time range gives exactly the matching frames of a whole run (the same centres, each window read whole
  where it reaches outside the range; the gain is the whole recording's), in spike frames or in seconds.
- A region gives exactly the matching part of a whole run cut into the same tiles (TFP and TFI).
- The output records its part, ``info`` shows it, ``--resume`` refuses another part.
- Bad ranges and regions are one line, exit 1, and nothing created (the Python API refuses them too).
- ``--dry-run`` creates nothing (no output, no claim, no folder above OUT, nothing beside it, no key in its bucket
  or memory, no temporary store left) and prints the plan.
"""

import fsspec
import json
import os
from fractions import Fraction

import numpy as np
import pytest
import zarr

from pipeline.compute.estimate import hours, hours_table, output_bytes
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from pipeline.jobs.reconstruct_tasks import block_frames
from stages.errors import InputError, InputTypeError
from stages.reconstruction.ranges import parse_region, parse_time, spike_frame
from tests.conftest import smooth_rate
from tests.test_bad_input import assert_refused

HEIGHT, WIDTH, FRAMES, FPS = 48, 64, 200, 1000.0  # LR; 200 spike frames are 0.2 s


def moving_scene(height: int, width: int, frames: int, seed: int = 0) -> np.ndarray:
    """(frames, H, W) 0/1 spikes of a scene sliding right one pixel every 4 frames (integrate and fire), so that
    every output frame differs from its neighbours."""
    rate = smooth_rate(height, width, seed=seed)
    accumulator = np.random.default_rng(seed).random(rate.shape)
    spikes = np.empty((frames, height, width), np.uint8)
    for t in range(frames):
        accumulator += np.roll(rate, t // 4, axis=1)
        spikes[t] = accumulator >= 1
        accumulator -= spikes[t]
    return spikes


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> str:
    """200 frames of a moving RGGB scene, LR 48x64 (HR 192x256), 1000 fps, no gain: exposed automatically."""
    folder = tmp_path_factory.mktemp("ranges")
    np.save(folder / "scene.npy", moving_scene(HEIGHT, WIDTH, FRAMES))
    store = str(folder / "scene.zarr")
    ingest(str(folder / "scene.npy"), store, IngestOptions(cfa="rggb", fps=FPS), progress=False)
    return store


@pytest.fixture(scope="module")
def whole(recording, client, tmp_path_factory) -> dict:
    """Whole-recording runs (every 7: 23 output frames; tile 16) by method: the reference every part is cut from
    (cut with the same tile: a tile's edge can round one level otherwise)."""
    folder = tmp_path_factory.mktemp("whole")
    runs = {}
    for method in ("tfp", "tfi"):
        out = str(folder / f"{method}.zarr")
        reconstruct(recording, out, ReconstructOptions(method=method, every=7, tile=16), client=client, progress=False)
        runs[method] = out
    return runs


def video(url: str) -> tuple[np.ndarray, np.ndarray, dict]:
    group = zarr.open_group(url, mode="r")
    return group["video"][:], group["frames"][:], dict(group.attrs)


def matching_frames(whole_url: str, centres: np.ndarray) -> np.ndarray:
    frames, whole_centres, _ = video(whole_url)
    index = np.searchsorted(whole_centres, centres)
    assert np.array_equal(whole_centres[index], centres)  # the same centres as the whole run's
    return frames[index]


def nothing_made(folder) -> None:
    """No output, no claim file, nothing at all in ``folder`` (tests give each job a fresh one)."""
    assert os.listdir(folder) == [], os.listdir(folder)


# --- time ranges ------------------------------------------------------------------------------

@pytest.mark.parametrize("start,stop", [(50, 130), ("0.05s", "130ms"), ("0.0495s", "0.1295s")])
def test_a_time_range_is_the_matching_frames_of_a_whole_run(recording, whole, client, tmp_path, start, stop):
    """[50, 130): centres 55, 62, ... 125 of the whole run's 20, 27, ...; the first window reads frames 35..75 and
    the last 105..145, outside the range. Seconds round up to a frame: 0.0495 s at 1000 fps is frame 50."""
    out = str(tmp_path / "part.zarr")
    counts = reconstruct(recording, out, ReconstructOptions(every=7, tile=16, start=start, stop=stop), client=client,
                         progress=False)
    frames, centres, attrs = video(out)
    assert list(centres) == list(range(55, 130, 7)) and counts["frames"] == 11
    np.testing.assert_array_equal(frames, matching_frames(whole["tfp"], centres))
    assert attrs["gain"] == video(whole["tfp"])[2]["gain"]  # the whole recording's exposure, not the range's
    assert (attrs["start"], attrs["stop"], attrs["region"]) == (50, 130, [0, HEIGHT, 0, WIDTH])
    assert attrs["fps"] == FPS / 7 and attrs["state"] == "complete"


def test_the_automatic_exposure_is_the_recording_s_whatever_its_output_frames(recording, whole, client, tmp_path):
    """Measured on the recording's middle window (centre 100 of 200 frames), not on its middle output frame (97 every
    7, 102 every 41): the frame centred on 20 is the same bytes every 7 and every 41, and the lazy graph agrees."""
    from cscsr import lazy

    out = str(tmp_path / "every41.zarr")
    reconstruct(recording, out, ReconstructOptions(every=41, tile=16), client=client, progress=False)
    frames, centres, attrs = video(out)
    assert list(centres) == [20, 61, 102, 143] and attrs["gain"] == video(whole["tfp"])[2]["gain"]
    np.testing.assert_array_equal(frames[:1], matching_frames(whole["tfp"], centres[:1]))
    assert float(lazy.windows(lazy.open_spikes(recording), every=13).coords["auto_gain"]) == attrs["gain"]
    group = zarr.open_group(out, mode="r+")  # an output begun by a rule of before: resumed with the gain it records
    group.attrs.update({"gain": attrs["gain"] * 1.25, "state": "writing"})
    group["committed"][3] = 0
    reconstruct(recording, out, ReconstructOptions(every=41, tile=16, resume=True), client=client, progress=False)
    resumed, _, resumed_attrs = video(out)
    assert resumed_attrs["gain"] == attrs["gain"] * 1.25 and resumed_attrs["state"] == "complete"
    np.testing.assert_array_equal(resumed[:3], frames[:3])
    assert resumed[3].mean() > frames[3].mean() + 5  # the last frame made again, brighter


def test_a_range_near_the_recordings_ends_has_only_the_centres_a_window_fits_around(recording, whole, client,
                                                                                     tmp_path):
    """A range edge closer than W//2 = 20 frames to an end simply has no centre there."""
    out = str(tmp_path / "ends.zarr")
    reconstruct(recording, out, ReconstructOptions(every=7, tile=16, start=0, stop=30), client=client, progress=False)
    frames, centres, _ = video(out)
    assert list(centres) == [20, 27]
    np.testing.assert_array_equal(frames, matching_frames(whole["tfp"], centres))
    out = str(tmp_path / "end.zarr")
    reconstruct(recording, out, ReconstructOptions(every=7, tile=16, start="0.17s"), client=client, progress=False)
    assert list(video(out)[1]) == [174]  # the last centre whose window fits (174 + 20 = 194 < 200)


def test_times_in_seconds_become_spike_frames_exactly():
    assert parse_time("--start", "1500ms") == Fraction(3, 2) and parse_time("--start", "2.5s") == Fraction(5, 2)
    assert parse_time("--start", "1200") == 1200 and parse_time("--start", 7) == 7
    assert parse_time("--stop", None) is None
    assert spike_frame(Fraction("0.1"), 30000.0) == 3000  # 0.1 * 30000 is 3000.0000000000005 in floating point
    assert spike_frame(Fraction("0.00005"), 20000.0) == 1 and spike_frame(Fraction("0.00004"), 20000.0) == 1
    assert spike_frame(Fraction(0), 20000.0) == 0 and spike_frame(42, 20000.0) == 42


def test_a_network_range_keeps_the_whole_runs_batches():
    """A range's tasks batch the frames a whole run batches together (the network's numbers may depend on its
    batch): [first, first + n) of the whole run's output, cut at the whole run's multiples of the batch."""
    assert block_frames(7, 4, first=3) == (1, 4, 2)  # whole-run frames 3 | 4..7 | 8, 9
    assert block_frames(8, 4, first=0) == (4, 4) and block_frames(0, 4, first=0) == (0,)
    assert block_frames(3000, 1, first=5) == (3,) * 1000  # one window a pass: at most WINDOW_BLOCKS blocks


def test_a_part_s_first_and_last_blocks_run_the_whole_run_s_batches(recording):
    """The network's numbers can depend on its batch (its size, its other windows: one grey level at a few pixels,
    a user's sweep found): a part's first and last blocks ran fewer windows than a whole run's. They now run the whole
    run's batch they are in and keep their own frames, in the job and the lazy graphs alike (``cut``). A stand-in for
    a network whose every image says the batch it ran in shows it: a part's frames are the whole run's."""
    import dataclasses

    from cscsr import lazy
    from pipeline.jobs.reconstruct_tasks import MethodSpec
    from pipeline.lazy.video import FunctionReconstructor, _reconstructed
    from pipeline.lazy.windows import check_windows

    @dataclasses.dataclass(frozen=True)
    class BatchProbe(FunctionReconstructor):
        batch: int = 4

        def many(self, windows):  # each image: 16 x the batch's size + its place in it; its window's bits
            return [np.stack(np.broadcast_arrays(np.uint8(16 * len(windows) + i), np.uint8(w.packed.sum() % 251),
                                                 np.zeros((w.packed.shape[1], w.width), np.uint8)), axis=-1)
                    for i, w in enumerate(windows)]

    probe = BatchProbe(func=None, scale=1, halo=0, name="probe")

    def run(win):
        return _reconstructed(check_windows(win), MethodSpec("probe", own=probe), probe, 1, 64, 1.0, 1, False).values

    windows = lazy.windows(lazy.open_spikes(recording), every=7)  # 23 output frames: batches 0..3, ..., 20..22
    whole = run(windows)
    assert sorted(set(whole[:20, 0, 0, 0] // 16)) == [4] and sorted(set(whole[20:, 0, 0, 0] // 16)) == [3]
    for part in (windows.isel(t=slice(5, 15)), windows.isel(t=slice(9, 10)), windows.isel(t=slice(18, 23)),
                 lazy.windows(lazy.open_spikes(recording), every=7, start=50, stop=120)):
        first = int((part.coords["frame"][0] - 20) // 7)
        np.testing.assert_array_equal(run(part), whole[first : first + part.sizes["t"]])


# --- regions ---------------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["tfp", "tfi"])
def test_a_region_is_the_matching_part_of_a_whole_run(recording, whole, client, tmp_path, method):
    """Tiles cut inside the region on the whole run's tile boundaries, their halo read from outside it: the same
    bytes as the whole run's, for TFP and TFI."""
    out = str(tmp_path / "region.zarr")
    reconstruct(recording, out, ReconstructOptions(method=method, every=7, tile=16, region="16:32,16:48"), client=client,
                progress=False)
    frames, centres, attrs = video(out)
    assert frames.shape == (23, 16 * 4, 32 * 4, 3) and attrs["region"] == [16, 32, 16, 48]
    np.testing.assert_array_equal(frames, matching_frames(whole[method], centres)[:, 64:128, 64:192])


def test_a_region_off_the_byte_columns_is_read_from_any_column(recording, client, tmp_path):
    """A region may start on any even column (any column in mono): its tiles read the packed spikes shifted
    (``tile_windows``), and give the whole run's bytes there."""
    options = {"method": "tfp", "every": 7, "tile": 64}
    whole_out, out = str(tmp_path / "whole.zarr"), str(tmp_path / "region.zarr")
    reconstruct(recording, whole_out, ReconstructOptions(**options), client=client, progress=False)
    reconstruct(recording, out, ReconstructOptions(**options, region="8:40,2:34"), client=client, progress=False)
    frames, _, attrs = video(out)
    assert frames.shape == (23, 32 * 4, 32 * 4, 3) and attrs["region"] == [8, 40, 2, 34]
    np.testing.assert_array_equal(frames, video(whole_out)[0][:, 32:160, 8:136])


def test_a_region_and_a_range_together_with_open_ends(recording, whole, client, tmp_path):
    out = str(tmp_path / "corner.zarr")
    reconstruct(recording, out, ReconstructOptions(every=7, tile=16, region=":16,48:", start=100), client=client,
                progress=False)
    frames, centres, attrs = video(out)
    assert (attrs["start"], attrs["stop"], attrs["region"]) == (100, FRAMES, [0, 16, 48, WIDTH])
    assert list(centres) == list(range(104, 180, 7))
    np.testing.assert_array_equal(frames, matching_frames(whole["tfp"], centres)[:, :64, 192:])


# --- what the output records -----------------------------------------------------------------

def test_the_part_is_recorded_shown_and_checked_on_resume(recording, client, cli, tmp_path):
    out = str(tmp_path / "part.zarr")
    options = ReconstructOptions(every=7, tile=8, start=50, stop=130, region="8:32,16:48")
    reconstruct(recording, out, options, client=client, progress=False)
    result = cli("info", out, "--json")
    assert result.exit_code == 0, result.stderr
    shown = json.loads(result.stdout)
    assert (shown["start"], shown["stop"], shown["region"], shown["spike_frames"]) == (50, 130, [8, 32, 16, 48],
                                                                                        "55..125")
    assert "region" in cli("info", out).stdout

    again = ReconstructOptions(**{**options.__dict__, "resume": True})
    assert reconstruct(recording, out, again, client=client, progress=False)["tasks_skipped"] == 11 * 3 * 4
    for other, said in [({"stop": 137}, "stop 130 -> 137"), ({"start": None, "stop": None}, "start 50 -> 0"),
                        ({"region": "8:32,16:40"}, "region [8, 32, 16, 48] -> [8, 32, 16, 40]")]:
        with pytest.raises(InputError, match=f"other parameters.*{said.replace('[', '.').replace(']', '.')}"):
            reconstruct(recording, out, ReconstructOptions(**{**again.__dict__, **other}), client=client,
                        progress=False)


def test_an_output_from_before_parts_resumes_as_the_whole_recording(recording, client, tmp_path):
    """An output written before ``start``/``stop``/``region`` were recorded was all of its recording."""
    out = str(tmp_path / "old.zarr")
    options = ReconstructOptions(every=41, tile=16)
    reconstruct(recording, out, options, client=client, progress=False)
    group = zarr.open_group(out, mode="r+")
    for name in ("start", "stop", "region"):
        del group.attrs[name]
    group["committed"][1] = 0  # one frame to finish
    counts = reconstruct(recording, out, ReconstructOptions(every=41, tile=16, resume=True), client=client,
                         progress=False)
    assert counts["tasks_run"] == 12
    with pytest.raises(InputError, match="other parameters.*start 0 -> 50"):
        reconstruct(recording, out, ReconstructOptions(every=41, tile=16, resume=True, start=50), client=client,
                    progress=False)


# --- refusals --------------------------------------------------------------------------------

BAD = [
    (["--start", 190], "spike frames [190, 200) hold no output frame"),
    (["--start", 0, "--stop", 15], "spike frames [0, 15) hold no output frame"),
    (["--start", 200], "--start 200 is outside the recording (200 spike frames"),
    (["--stop", 201], "--stop 201 is outside the recording"),
    (["--stop", "0.3s"], "--stop 0.3s (spike frame 300) is outside the recording"),
    (["--start", 60, "--stop", 50], "is reversed"),
    (["--start", 60, "--stop", 60], "is empty"),
    (["--start", "0.06s", "--stop", 60], "is empty"),
    (["--start", "2min"], "unknown unit 'min'"),
    (["--start", "1.5"], "spike frames are whole numbers"),
    (["--stop", "soon"], "--stop must be spike frames (1200) or seconds with a unit"),
    (["--start", "-5"], "--start must be >= 0"),
    (["--region", "8:32,16:72"], "is outside the recording (48x64 LR pixels"),
    (["--region", "48:,0:8"], "is outside the recording"),
    (["--region", "32:8,0:64"], "is reversed"),
    (["--region", "8:8,0:64"], "is empty"),
    (["--region", "8:32,13:48"], "X0 13 is odd"),
    (["--region", "7:32,16:48"], "Y0 7 is odd: the rggb CFA repeats every 2 pixels"),
    (["--region", "8:31,16:48"], "Y1 31 is odd"),
    (["--region", "8:32,16:47"], "X1 47 is odd"),
    (["--region", "8-32,16-48"], "--region must be Y0:Y1,X0:X1"),
    (["--region", "8:32"], "--region must be Y0:Y1,X0:X1"),
    (["--json"], "--json is for --dry-run"),
]


@pytest.mark.parametrize("dry_run", [False, True])
def test_bad_ranges_and_regions_are_one_line_and_create_nothing(recording, cli, tmp_path, dry_run):
    folder = tmp_path / "outputs"
    folder.mkdir()
    for args, said in BAD:
        if dry_run and args == ["--json"]:
            continue
        result = cli("reconstruct", recording, folder / "out.zarr", "--every", 7, "--workers", 1, *args,
                     *(["--dry-run"] if dry_run else []))
        assert result.exit_code == 1, args
        assert_refused(result, said)
        nothing_made(folder)


def test_the_python_api_refuses_them_as_strictly(recording, tmp_path):
    from cscsr import reconstruct as api_reconstruct

    out = tmp_path / "out.zarr"
    for options, said in [({"start": "2min"}, "unknown unit"), ({"region": "7:32,16:48"}, "Y0 7 is odd"),
                          ({"start": 150, "stop": 40}, "reversed"), ({"region": (0, 8, 0, 80)}, "outside"),
                          ({"stop": -1}, "must be >= 0")]:
        with pytest.raises(InputError, match=said):
            api_reconstruct(recording, out, every=7, workers=1, **options)
    for options in [{"start": 1.5}, {"region": 5}, {"region": (0, 8, 0)}, {"start": True}]:
        with pytest.raises(InputTypeError):
            api_reconstruct(recording, out, workers=1, **options)
    with pytest.raises(TypeError, match="dry_run must be True or False"):
        api_reconstruct(recording, out, workers=1, dry_run="yes")
    nothing_made(tmp_path)
    assert parse_region((0, None, 8, 16)) == (0, None, 8, 16)


# --- the priced plan -------------------------------------------------------------------------

@pytest.fixture
def quick(monkeypatch):
    """Dry runs that measure for 0.3 s rather than 3 (a round of a task a worker at least all the same)."""
    import pipeline.jobs.dry_run

    monkeypatch.setattr(pipeline.jobs.dry_run, "SAMPLE_SECONDS", 0.3)


def test_a_dry_run_creates_nothing_and_prints_the_plan(recording, cli, tmp_path, quick):
    folder = tmp_path / "outputs"
    folder.mkdir()
    out = folder / "out.zarr"
    result = cli("reconstruct", recording, out, "--every", 7, "--tile", 16, "--start", "0.05s", "--stop", 130,
                 "--region", "8:40,0:64", "--workers", 1, "--dry-run", "--json")
    assert result.exit_code == 0, result.stderr
    plan = json.loads(result.stdout)
    nothing_made(folder)
    assert not [path for path in fsspec.filesystem("memory").ls("/") if "cscsr-dry-run" in str(path)]
    assert (plan["frames"], plan["spike_frames"], plan["start"], plan["stop"]) == (11, "55..125", 50, 130)
    assert plan["region"] == [8, 40, 0, 64] and (plan["hr_height"], plan["hr_width"]) == (128, 256)
    assert plan["tile_lr"] == 16 and plan["tiles_per_frame"] == 2 * 4 and plan["tasks"] == plan["tasks_to_run"] == 88
    assert plan["method"] == "tfp" and plan["weights"] is None and plan["runs_on"] == "any worker"
    measured = plan["measured"]  # tasks of the job, in a segment's local cluster alike (one worker)
    assert plan["measured_on"] == "1 local worker" and plan["workers"] == measured["workers"] == 1
    assert measured["tasks"] >= 3 and measured["bytes"] > 0 and measured["hr_pixels"] >= 2 * 16 * 16 * 16
    assert 0 < plan["seconds_per_task"] < 5 and plan["output_bytes"] > measured["bytes"] / measured["tasks"]
    assert list(plan["hours"]) == ["1", "8", "64"]
    assert plan["hours"]["1"] == pytest.approx(88 * plan["seconds_per_task"] / 3600)
    assert plan["hours"]["64"] == pytest.approx(2 * plan["seconds_per_task"] / 3600)  # 2 rounds: 64 tasks, then 24
    assert plan["job_seconds"] == pytest.approx(88 * plan["seconds_per_task"] + plan["segment_start_seconds"])

    table = cli("reconstruct", recording, out, "--every", 7, "--workers", 1, "--dry-run")
    assert table.exit_code == 0, table.stderr
    assert "output frames" in table.stdout and "estimated time" in table.stdout and "64" in table.stdout
    nothing_made(folder)


def test_a_dry_run_refuses_what_a_real_run_refuses_and_counts_what_a_resume_has_left(recording, whole, cli,
                                                                                      tmp_path, quick):
    out = whole["tfp"]
    assert_refused(cli("reconstruct", recording, out, "--every", 7, "--tile", 16, "--workers", 1, "--dry-run"),
                   "already exists", "--resume or --overwrite")
    assert_refused(cli("reconstruct", recording, out, "--every", 41, "--tile", 16, "--resume", "--workers", 1,
                       "--dry-run"), "other parameters", "every 7 -> 41")
    before = sorted(os.listdir(out))
    result = cli("reconstruct", recording, out, "--every", 7, "--tile", 16, "--resume", "--workers", 1, "--dry-run",
                 "--json")
    assert result.exit_code == 0, result.stderr
    plan = json.loads(result.stdout)
    assert plan["tasks"] == 23 * 3 * 4 and plan["tasks_to_run"] == 0 and plan["hours"]["1"] == 0
    assert sorted(os.listdir(out)) == before
    assert_refused(cli("reconstruct", recording, tmp_path / "none.zarr", "--resume", "--workers", 1, "--dry-run"),
                   "does not exist")


def test_a_dry_run_on_the_cluster_measures_on_its_workers(recording, client, tmp_path):
    from cscsr import reconstruct as api_reconstruct

    planned = api_reconstruct(recording, tmp_path / "out.zarr", every=7, tile=16, client=client, dry_run=True)
    nothing_made(tmp_path)
    plan = planned.counts
    assert planned.attrs == {} and plan["measured_on"] == "2 workers of the cluster" and plan["workers"] == 2
    assert plan["tasks"] == 23 * 3 * 4 and plan["segment_start_seconds"] == 0
    assert plan["measured"]["tasks"] % 2 == 0  # whole rounds of a task per worker
    assert plan["job_seconds"] == pytest.approx(-(-plan["tasks"] // 2) * plan["seconds_per_task"])
    real = tmp_path / "real.zarr"
    reconstruct(recording, str(real), ReconstructOptions(every=7, tile=16), client=client, progress=False)
    size = sum(path.stat().st_size for path in (real / "video" / "c").rglob("*") if path.is_file())
    assert plan["output_bytes"] == pytest.approx(size, rel=0.1)  # from the bytes per pixel of the middle tasks
    leftovers = client.run(lambda: [str(p) for p in fsspec.filesystem("memory").ls("/") if "cscsr-dry-run" in str(p)])
    assert all(found == [] for found in leftovers.values())


def test_the_estimate_is_whole_rounds_of_the_measured_task():
    assert hours(36.0, 10, 1) == pytest.approx(0.1)
    assert hours(36.0, 10, 8) == pytest.approx(0.02)  # 2 rounds: 8 tasks, then 2
    assert hours(36.0, 10, 64) == pytest.approx(0.01) and hours(36.0, 0, 8) == 0
    assert hours_table(3.6, 1000) == {"1": 1.0, "8": pytest.approx(0.125), "64": pytest.approx(0.016)}
    assert output_bytes(1000, 100, 10_000) == 100_000 and output_bytes(0, 0, 5) == 0
    with pytest.raises(ValueError):
        hours(1.0, 1, 0)


def test_a_network_dry_run_measures_on_the_gpu_workers(recording, tmp_path, quick):
    """A cluster with a worker that advertises a GPU (no CUDA here: the network runs on its CPU) and one that does
    not: the network's tasks, and so the measure, go to the GPU worker only."""
    from pipeline.compute.cluster import GPU
    from tests.test_gpu_workers import cluster

    options = ReconstructOptions(method="cscsr", weights="lite", every=41, tile=64)  # one task: 4 windows
    with cluster(gpu={GPU: 1}, cpu=None) as client:
        plan = reconstruct(recording, str(tmp_path / "out.zarr"), options, client=client, dry_run=True)
    assert plan["runs_on"] == "GPU workers" and "lite" in plan["weights"]  # the shipped file's path
    assert plan["measured_on"] == "1 GPU worker of the cluster" and plan["workers"] == 1
    assert plan["frames"] == 4 and plan["frames_per_task"] == 4 and plan["measured"]["bytes"] > 0
    nothing_made(tmp_path)


def test_a_dry_run_writes_nowhere_near_its_output(recording, cli, tmp_path, monkeypatch, quick):
    """OUT in folders that do not exist: none is made, nothing appears beside them; the sample tasks wrote into a
    folder under this machine's temporary folder (the segment's local cluster shares it), gone after."""
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    monkeypatch.setenv("TMPDIR", str(temporary))  # the segment's fresh process and its workers: theirs too
    outputs = tmp_path / "outputs"
    outputs.mkdir()
    out = outputs / "missing" / "deeper" / "out.zarr"
    result = cli("reconstruct", recording, out, "--every", 7, "--tile", 16, "--workers", 1, "--dry-run", "--json")
    assert result.exit_code == 0, result.stderr
    plan = json.loads(result.stdout)
    assert plan["measured"]["bytes"] > 0 and plan["output_bytes"] > 0
    nothing_made(outputs)
    assert not [name for name in os.listdir(temporary) if name.startswith("cscsr-dry-run")]


def test_the_dry_run_scratch_is_a_temporary_folder_or_each_workers_memory(client, tmp_path, monkeypatch):
    """A folder under this machine's temporary folder where every worker can write it (the local cluster's), else
    each worker's memory (workers of another machine: they cannot); the folder removed after either way."""
    import tempfile

    from pipeline.jobs.dry_run import _scratch

    class Elsewhere:  # a cluster whose workers see none of this machine's folders
        def run(self, function, *args, workers):
            return {address: False for address in workers}

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    able = list(client.scheduler_info()["workers"])
    with _scratch(client, able) as url:
        folder = os.path.dirname(url)
        assert os.path.dirname(folder) == str(tmp_path) and os.path.basename(folder).startswith("cscsr-dry-run-")
    assert os.listdir(tmp_path) == []
    with _scratch(Elsewhere(), able) as url:
        assert url.startswith("memory://cscsr-dry-run-")
    assert os.listdir(tmp_path) == []


def test_a_dry_run_of_an_s3_output_writes_no_key(recording, client, s3_endpoint, quick):
    """On the cluster, OUT in a versioned bucket (a key written and deleted leaves a version and a delete marker):
    no key was ever written there (the tasks wrote under this machine's temporary folder, removed after); the plan
    is priced all the same."""
    import boto3

    from cscsr import reconstruct as api_reconstruct

    s3 = boto3.client("s3")
    s3.create_bucket(Bucket="dry-run-bucket")
    s3.put_bucket_versioning(Bucket="dry-run-bucket", VersioningConfiguration={"Status": "Enabled"})
    planned = api_reconstruct(recording, "s3://dry-run-bucket/plans/out.zarr", every=7, tile=16, client=client,
                              dry_run=True)
    assert planned.counts["measured"]["bytes"] > 0 and planned.counts["output_bytes"] > 0
    versions = s3.list_object_versions(Bucket="dry-run-bucket")
    assert not versions.get("Versions") and not versions.get("DeleteMarkers"), versions
    leftovers = client.run(lambda: [str(p) for p in fsspec.filesystem("memory").ls("/") if "cscsr-dry-run" in str(p)])
    assert all(found == [] for found in leftovers.values())


class Recorded(dict):
    """The memory file system's store, recording every key ever set."""

    def __init__(self, *args):
        super().__init__(*args)
        self.set = []

    def __setitem__(self, key, value):
        self.set.append(key)
        super().__setitem__(key, value)


def test_a_dry_run_of_a_memory_output_writes_no_key(recording, monkeypatch, quick):
    """A client of two workers in this process (so that ``memory://`` is allowed) that cannot reach this machine's
    temporary folder (as a remote cluster's): the sample's store is made once in the memory they share, and removed
    after; no key of OUT was ever set."""
    from distributed import Client, LocalCluster
    from fsspec.implementations.memory import MemoryFileSystem

    store = Recorded(MemoryFileSystem.store)
    monkeypatch.setattr(MemoryFileSystem, "store", store)
    monkeypatch.setattr("pipeline.jobs.dry_run._writable", lambda folder: False)
    out = "memory://dry-run-plans/out.zarr"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as local, \
            Client(local) as client:
        plan = reconstruct(recording, out, ReconstructOptions(every=7, tile=16), client=client, dry_run=True)
    assert plan["workers"] == 2 and plan["measured"]["bytes"] > 0
    assert not [key for key in store.set if "dry-run-plans" in key], store.set
    assert [key for key in store.set if key.startswith("/cscsr-dry-run-")]  # the sample's store, in this process
    assert not [key for key in store if "cscsr-dry-run" in key or "dry-run-plans" in key]


def test_a_dry_run_on_workers_that_share_no_folder_measures_in_their_memory(recording, client, tmp_path,
                                                                           monkeypatch, quick):
    """Worker processes that cannot reach this machine's temporary folder (as a remote cluster's): the sample's store
    is made in each one's memory, priced the same, and removed after; nothing beside OUT."""
    monkeypatch.setattr("pipeline.jobs.dry_run._writable", lambda folder: False)  # sent by value to the workers
    plan = reconstruct(recording, str(tmp_path / "out.zarr"), ReconstructOptions(every=7, tile=16), client=client,
                       dry_run=True)
    assert plan["workers"] == 2 and plan["measured"]["bytes"] > 0 and plan["measured"]["tasks"] >= 6
    nothing_made(tmp_path)
    leftovers = client.run(lambda: [str(p) for p in fsspec.filesystem("memory").ls("/") if "cscsr-dry-run" in str(p)])
    assert all(found == [] for found in leftovers.values())
