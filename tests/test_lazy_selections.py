"""``cscsr.lazy`` keeps xarray's promises (#55): a selection (``isel``/``sel``, slicing) of spikes, windows or HR is
honoured exactly, with the recording's coordinates carried through, or refused in one line before anything is
written; every block ``to_video`` writes is checked against its chunk; a resume refuses another graph.

Known answers: a selection of frames gives the windows, bytes and record of ``start=``/``stop=`` on the whole
recording; a crop of pixels gives the whole reconstruction's interior, at the recording's HR coordinates, with the
recording's gain; a written selection of ``hr`` reads back (``open_video``) as that selection.
"""

import dataclasses
import os
import pathlib

import dask
import dask.array as da
import numpy as np
import pytest
import xarray as xr
import zarr

from cscsr import lazy
from pipeline.jobs.info import summarize
from pipeline.jobs.simulate import SimulateOptions
from pipeline.lazy import written as lazy_written
from stages.errors import InputError, InputTypeError
from tests.test_ranges_and_regions import FPS, FRAMES, HEIGHT, WIDTH, recording  # noqa: F401 - 200 frames, no gain


@pytest.fixture(autouse=True)
def threads():
    with dask.config.set(scheduler="threads"):
        yield


def stored(url: str) -> tuple[np.ndarray, np.ndarray, dict]:
    group = zarr.open_group(str(url), mode="r")
    return group["video"][:], group["frames"][:], dict(group.attrs)


def refused(call, fragment: str, kind=InputError) -> str:
    with pytest.raises(kind) as raised:
        call()
    message = str(raised.value)
    assert fragment in message and "\n" not in message, message
    return message


# ---- 1. time ----

def test_a_run_of_frames_is_start_and_stop_on_the_recording(recording, tmp_path):
    """isel(t=slice(30, 120)) and sel(t=...) of the same frames: the output frames whose whole window lies in
    them (centres 60, 80 on the recording's grid), recorded as start 50, stop 100: the bytes and record of
    windows(start=50, stop=100) on the whole recording, its automatic gain included."""
    spikes = lazy.open_spikes(recording)
    by_index = lazy.windows(spikes.isel(t=slice(30, 120)), every=20)
    by_time = lazy.windows(spikes.sel(t=slice(30 / FPS, 119 / FPS)), every=20)
    ranged = lazy.windows(spikes, every=20, start=50, stop=100)
    for win in (by_index, by_time):
        assert win.frame.values.tolist() == [60, 80] == ranged.frame.values.tolist()
        assert np.array_equal(win.t.values, ranged.t.values) and (win.attrs["start"], win.attrs["stop"]) == (50, 100)
        assert np.array_equal(win.values, ranged.values)
    lazy.to_video(lazy.tfp(by_index, tile=16), str(tmp_path / "selected.zarr"))
    lazy.to_video(lazy.tfp(ranged, tile=16), str(tmp_path / "ranged.zarr"))
    selected, reference = stored(tmp_path / "selected.zarr"), stored(tmp_path / "ranged.zarr")
    assert np.array_equal(selected[0], reference[0]) and selected[1].tolist() == [60, 80]
    assert selected[2] == reference[2]  # start, stop, the recording's shape, its automatic gain ...
    assert selected[2]["source_shape"] == [FRAMES, HEIGHT, WIDTH]
    refused(lambda: lazy.windows(spikes.isel(t=slice(45, 100)), every=20), "no output frame's window of 41")


@pytest.mark.parametrize("pick", ["every-2nd", "reversed", "shuffled", "repeated"])
def test_frames_that_are_not_a_run_are_refused(recording, pick):
    spikes = lazy.open_spikes(recording)
    index = {"every-2nd": slice(None, None, 2), "reversed": slice(None, None, -1),
             "shuffled": np.random.default_rng(0).permutation(FRAMES), "repeated": [*range(100), *range(99, 199)]}[pick]
    fragment = {"every-2nd": "skips (a step of 2)", "reversed": "runs backwards", "shuffled": "frame",
                "repeated": "repeats"}[pick]
    message = refused(lambda: lazy.windows(spikes.isel(t=index), every=10), fragment)
    assert "isel(t=slice(a, b))" in message


# ---- 2. space ----

def test_a_crop_is_the_whole_reconstruction_s_interior_at_the_recording_s_pixels(recording, tmp_path):
    spikes = lazy.open_spikes(recording)
    whole = lazy.tfp(lazy.windows(spikes, every=20), tile=16)
    crop = lazy.tfp(lazy.windows(spikes.isel(y=slice(16, 48), x=slice(16, 64)), every=20), tile=16)
    assert crop.y.values.tolist() == list(range(64, 192)) and crop.x.values.tolist() == list(range(64, 256))
    assert float(crop.gain) == float(whole.gain)  # the recording's automatic gain, not the crop's
    # the crop's tiles are the whole frame's (both cut every 16 from a multiple of 16): a tile whose halo stays
    # inside the crop reads what the whole frame's reads, and makes its bytes; one at the crop's edge sees the edge
    inner = dict(y=slice(4 * 32, None), x=slice(4 * 32, None))
    assert np.array_equal(crop.sel(**inner).values, whole.sel(**inner).values)
    assert not np.array_equal(crop.values, whole.sel(y=crop.y, x=crop.x).values)  # the edges are the crop's own
    lazy.to_video(crop, str(tmp_path / "crop.zarr"))
    attrs = stored(tmp_path / "crop.zarr")[2]
    assert attrs["region"] == [16, 48, 16, 64] and attrs["source_shape"] == [FRAMES, HEIGHT, WIDTH]
    assert summarize(str(tmp_path / "crop.zarr"))  # cscsr info reads it


def test_a_crop_s_odd_offsets_and_steps_are_refused(recording):
    spikes = lazy.open_spikes(recording)
    refused(lambda: lazy.windows(spikes.isel(y=slice(1, None))), "selection at y=1: the rggb colour pattern")
    refused(lambda: lazy.windows(spikes.isel(x=slice(0, 31))), "x end 31")
    refused(lambda: lazy.windows(spikes.isel(x=slice(None, None, 2))), "skips (a step of 2)")
    refused(lambda: lazy.windows(spikes.isel(y=slice(8, 40)), region="0:16,0:64"), "outside the selected pixels")


# ---- 3. windows ----

def test_windows_selected_along_dt_are_refused_and_along_t_honoured(recording, tmp_path):
    win = lazy.windows(lazy.open_spikes(recording), every=20)
    refused(lambda: lazy.tfp(win.isel(dt=slice(10, 31))), "selection along dt")
    refused(lambda: lazy.tfp(win.isel(dt=slice(None, None, -1))), "selection along dt")
    refused(lambda: lazy.tfp(win.isel(t=[0, 2])), "skip output frames")
    part = lazy.tfp(win.isel(t=slice(2, 5)), tile=16)
    assert part.frame.values.tolist() == [60, 80, 100]
    assert np.array_equal(part.values, lazy.tfp(win, tile=16).isel(t=slice(2, 5)).values)
    lazy.to_video(part, str(tmp_path / "part.zarr"))
    assert (stored(tmp_path / "part.zarr")[2]["start"], stored(tmp_path / "part.zarr")[2]["stop"]) == (60, 101)


# ---- 4. blocks ----

@pytest.mark.parametrize("bad", ["a row short", "float", "nan"])
def test_a_block_unlike_its_chunk_fails_the_write_and_the_store_is_never_complete(recording, tmp_path, bad):
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=20), tile=16)
    change = {"a row short": lambda block: block[:, :-1], "float": lambda block: block / 2.0,
              "nan": lambda block: np.full(block.shape, np.nan)}[bad]
    broken = hr.copy(data=hr.data.map_blocks(change, dtype=np.uint8))  # what dask is told is not what it gets
    refused(lambda: lazy.to_video(broken, str(tmp_path / "out.zarr")), "where its chunk is uint8")
    assert zarr.open_group(str(tmp_path / "out.zarr"), mode="r").attrs["state"] == "writing"


# ---- 5 and 6. a selection of hr ----

def test_a_sliced_hr_is_written_with_its_region_and_read_back(recording, tmp_path):
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=20), tile=16)
    sliced = hr.isel(t=slice(1, 4), y=slice(8, 64), x=slice(32, 128))
    lazy.to_video(sliced, str(tmp_path / "sliced.zarr"))
    video, frames, attrs = stored(tmp_path / "sliced.zarr")
    assert attrs["region"] == [2, 16, 8, 32] and (attrs["start"], attrs["stop"]) == (40, 81)
    assert np.array_equal(video, sliced.values) and frames.tolist() == [40, 60, 80]
    back = lazy.open_video(tmp_path / "sliced.zarr")
    assert back.dims == sliced.dims and back.attrs == {**sliced.attrs, "region": [2, 16, 8, 32], "start": 40,
                                                       "stop": 81}
    for name in ("t", "frame", "y", "x", "gain"):
        assert np.array_equal(back[name].values, sliced[name].values), name
    assert np.array_equal(back.values, sliced.values)
    assert summarize(str(tmp_path / "sliced.zarr"))
    from pipeline.jobs.export import export

    export(str(tmp_path / "sliced.zarr"), str(tmp_path / "pngs"))
    assert sorted(os.listdir(tmp_path / "pngs")) == [f"frame_{c:08d}.png" for c in (40, 60, 80)]


@pytest.mark.parametrize("pick", ["repeated", "reversed", "gapped", "cut pixel", "cut colour cell"])
def test_a_selection_of_hr_that_cannot_be_written_is_refused_before_anything_exists(recording, tmp_path, pick):
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=20), tile=16)
    selected, fragment = {"repeated": (hr.isel(t=[0, 0, 1]), "repeat"),
                          "reversed": (hr.isel(t=slice(None, None, -1)), "run backwards"),
                          "gapped": (hr.isel(t=[0, 2]), "skip output frames"),
                          "cut pixel": (hr.isel(y=slice(3, 64)), "cuts through LR pixels (scale=4)"),
                          "cut colour cell": (hr.isel(y=slice(4, 132)), "LR y0 1, y1 33, odd: the rggb colour")}[pick]
    refused(lambda: lazy.to_video(selected, str(tmp_path / "out.zarr")), fragment)
    assert not os.listdir(tmp_path)


# ---- 7. memory:// and worker processes ----

def test_memory_stores_are_refused_up_front_where_tasks_run_in_other_processes(recording, tmp_path):
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=50), tile=16)
    lazy.to_video(hr, "memory://lazy-hr.zarr")  # threads: this process's own memory
    memory_spikes = "memory://lazy-spikes.zarr"
    lazy.to_spikes(lazy.open_spikes(recording), memory_spikes)
    from_memory = lazy.tfp(lazy.windows(lazy.open_spikes(memory_spikes), every=50), tile=16)
    with dask.config.set(scheduler="processes"):
        refused(lambda: lazy.to_video(hr, "memory://other-hr.zarr"), "memory:// lives in this process only")
        refused(lambda: lazy.open_spikes(memory_spikes), "memory:// lives in this process only")
        refused(lambda: lazy.to_video(from_memory, str(tmp_path / "hr.zarr")), "cannot use memory://lazy-spikes.zarr")
    assert not os.listdir(tmp_path)


# ---- 8. simulate ----

def test_simulate_refuses_a_float_scene_that_is_not_intensities():
    scene = np.full((50, 32, 32, 3), 0.5, np.float32)
    for value, shown in ((255.0, "255.0"), (np.nan, "nan"), (np.inf, "inf"), (-0.1, "-0.1")):
        bad = scene.copy()
        bad[7, 3, 3, 0] = value
        refused(lambda: lazy.simulate(xr.DataArray(bad, dims=("t", "y", "x", "rgb"))), "scene frame 7 holds")
        lazy_bad = lazy.simulate(xr.DataArray(da.from_array(bad, chunks=(10, -1, -1, -1)), dims=("t", "y", "x", "rgb")))
        message = refused(lambda: lazy_bad.compute(), "scene frame 7 holds")  # lazy: when its block is computed
        assert shown in message and "[0, 1]" in message
    assert lazy.simulate(xr.DataArray(scene, dims=("t", "y", "x", "rgb"))).shape == (50, 8, 8)


def test_simulate_s_default_reset_is_the_simulate_job_s():
    import inspect

    assert inspect.signature(lazy.simulate).parameters["reset"].default == SimulateOptions().reset
    assert "ingest" in inspect.getdoc(lazy.simulate)  # and it says why ingest's differs


# ---- 9. writes ----

def test_paths_are_taken_as_the_jobs_take_them(recording, tmp_path):
    spikes = lazy.open_spikes(pathlib.Path(recording))
    assert lazy.to_video(lazy.tfp(lazy.windows(spikes, every=50), tile=16), tmp_path / "hr.zarr")["frames"] == 4
    assert lazy.to_spikes(spikes, tmp_path / "copy.zarr")["frames"] == FRAMES


def test_chunk_frames_beyond_the_recording_are_clamped_to_it(recording, tmp_path):
    result = lazy.to_spikes(lazy.open_spikes(recording), str(tmp_path / "copy.zarr"), chunk_frames=10**9)
    assert zarr.open_group(str(tmp_path / "copy.zarr"), mode="r")["spikes"].chunks[0] == FRAMES  # not 119 GiB
    assert result["frames"] == FRAMES and result["tasks"] == 1


def test_an_empty_url_and_a_file_where_a_store_should_be_are_refused(recording, tmp_path):
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=50), tile=16)
    refused(lambda: lazy.to_video(hr, ""), "url is empty")
    refused(lambda: lazy.to_video(hr, 5), "url must be a path or URL", InputTypeError)
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    refused(lambda: lazy.to_video(hr, str(notes), resume=True), "cannot resume")
    assert notes.read_text() == "mine" and os.listdir(tmp_path) == ["notes.txt"]


# ---- 10. resume ----

def test_a_resume_refuses_another_graph_and_finishes_the_same_one(recording, tmp_path, monkeypatch):
    monkeypatch.setattr(lazy_written, "BLOCKS_AT_ONCE", 1)
    failing = tmp_path / "fail"
    win = lazy.windows(lazy.open_spikes(recording), every=20)

    def hr_of(level: int):  # a function whose closure says how bright: one graph per level
        def grey(window):
            if failing.exists() and window.shape[1] == 32:  # the second row of tiles (16 rows and a halo of 8)
                raise RuntimeError("disk full")
            return np.full((4 * window.shape[1], 4 * window.shape[2], 3), level, np.uint8)

        return lazy.apply(win, grey, scale=4, halo=8, tile=16)

    out = str(tmp_path / "out.zarr")
    failing.touch()
    with pytest.raises(RuntimeError, match="disk full"):
        lazy.to_video(hr_of(7), out)
    failing.unlink()
    refused(lambda: lazy.to_video(hr_of(9), out, resume=True), "not the graph that wrote it")
    brighter = hr_of(7).copy(data=hr_of(7).data.map_blocks(lambda block: block + 1))
    refused(lambda: lazy.to_video(brighter, out, resume=True), "not the graph that wrote it")
    counts = lazy.to_video(hr_of(7), out, resume=True)  # built again from the same code: the same graph
    assert counts["tasks_skipped"] > 0 and stored(out)[2]["state"] == "complete"
    assert (stored(out)[0] == 7).all()


# ---- the graph's tools ----

def test_tasks_are_named_by_stage_and_counted_in_the_job_s_units(recording, tmp_path):
    win = lazy.windows(lazy.open_spikes(recording), every=20)
    hr = lazy.tfp(win, tile=32)  # 8 frames, 2x2 tiles
    stages = {key[0].rsplit("-", 1)[0] for key in hr.data.__dask_graph__() if isinstance(key, tuple)}
    assert "tfp" in stages and "windows" not in stages, stages  # each block reads its own tile from the store
    between = lazy.tfp(win.copy(data=win.data.map_blocks(np.copy)), tile=32)  # a function between stages
    stages = {key[0].rsplit("-", 1)[0] for key in between.data.__dask_graph__() if isinstance(key, tuple)}
    assert {"spikes", "windows", "copy", "tfp"} <= stages, stages  # read and unpacked, windowed, its, reconstructed
    out = str(tmp_path / "hr.zarr")
    fresh = lazy.to_video(hr, out)
    again = lazy.to_video(hr, out, resume=True)  # nothing left to do
    assert fresh == {"frames": 8, "tasks_run": 8 * 4, "tasks_skipped": 0}  # a frame's tile each, as the job counts
    assert again == {"frames": 8, "tasks_run": 0, "tasks_skipped": fresh["tasks_run"]}


def test_progress_reports_a_line_a_round_when_piped(recording, tmp_path, monkeypatch, capfd):
    monkeypatch.setattr(lazy_written, "BLOCKS_AT_ONCE", 2)
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=20), tile=32)
    lazy.to_video(hr, str(tmp_path / "hr.zarr"), progress=True)
    lines = [line for line in capfd.readouterr().err.splitlines() if line.startswith("to_video")]
    assert lines[-1].endswith(": 32 of 32 tasks") and len(lines) == 16  # 32 blocks (a frame's tile each), 2 a round
    group = zarr.open_group(str(tmp_path / "hr.zarr"), mode="r+")  # frames 5-7's tiles lost: a resume makes them
    group["committed"][5:] = 0
    group.attrs["state"] = "writing"
    lazy.to_video(hr, str(tmp_path / "hr.zarr"), resume=True, progress=True)
    lines = [line for line in capfd.readouterr().err.splitlines() if line.startswith("to_video")]
    assert [line.rsplit(": ", 1)[1] for line in lines] == [f"{n} of 32 tasks" for n in (22, 24, 26, 28, 30, 32)]


def test_a_slice_of_hr_computes_only_its_windows(recording):
    calls = []

    def counted(window):  # one call per window and tile
        calls.append(window.shape)
        return np.zeros((4 * window.shape[1], 4 * window.shape[2], 3), np.uint8)

    hr = lazy.apply(lazy.windows(lazy.open_spikes(recording), every=20), counted, scale=4)  # 8 frames, one tile
    assert hr.data.chunks[0] == (1,) * 8  # a block per output frame: the job's task of a method like this one
    hr.isel(t=3).compute()
    assert len(calls) == 1


def test_open_video_refuses_an_unfinished_store_and_a_lost_chunk(recording, tmp_path):
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=50), tile=32)
    out = str(tmp_path / "hr.zarr")
    lazy.to_video(hr, out)
    assert np.array_equal(lazy.open_video(out).values, hr.values)
    chunk = next(path for path in (tmp_path / "hr.zarr" / "video" / "c").rglob("*") if path.is_file())
    chunk.unlink()
    refused(lambda: lazy.open_video(out), "has lost data")
    zarr.open_group(out, mode="r+").attrs["state"] = "writing"
    refused(lambda: lazy.open_video(out), "is incomplete")


def test_windows_sliced_in_space_say_so(recording):
    """Windows of a region with their margin: a slice that keeps the region and the method's halo is honoured; one
    that cuts the halo is refused naming the slice (not the margin); one inside the region is refused."""
    win = lazy.windows(lazy.open_spikes(recording), every=50, region="16:32,16:32")  # kept: y 0:48, x 0:64
    kept = lazy.tfp(win.isel(y=slice(8, 40), x=slice(8, 40)), tile=16)
    assert np.array_equal(kept.values, lazy.tfp(win, tile=16).values)
    refused(lambda: lazy.tfp(win.isel(y=slice(12, 40))), "they were sliced (y 12:40, x 0:64 of the y 0:48, x 0:64")
    refused(lambda: lazy.tfp(win.isel(y=slice(20, 40))), "inside their region")


RESUMED = """
import os, sys
import dask, numpy as np
from cscsr import lazy
from pipeline.lazy import written
recording, out, flag, resume = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4] == "resume"
written.BLOCKS_AT_ONCE = 1

def dimmed(block, block_info=None):  # output frames from 5 on fail while the flag exists (a full disk)
    if os.path.exists(flag) and block_info[0]["chunk-location"][0] >= 5:
        raise RuntimeError("disk full")
    return block // 2

hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=20), tile=48)
hr = hr.copy(data=hr.data.map_blocks(dimmed, dtype=np.uint8))
with dask.config.set(scheduler="synchronous"):
    print(lazy.to_video(hr, out, resume=resume)["tasks_skipped"])
"""


def test_a_resume_in_another_process_is_the_same_graph(recording, tmp_path):
    """A call that failed in one process is resumed by the same code in another: the graph's token is the same
    there (Dask hashes the function by its code and closure), so the resume runs only what was left."""
    import subprocess
    import sys

    out, flag = str(tmp_path / "hr.zarr"), tmp_path / "flag"
    flag.touch()
    args = [sys.executable, "-c", RESUMED, recording, out, str(flag)]
    failed = subprocess.run([*args, "fresh"], capture_output=True, text=True, timeout=300)
    assert failed.returncode != 0 and "disk full" in failed.stderr
    flag.unlink()
    resumed = subprocess.run([*args, "resume"], capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert int(resumed.stdout.split()[-1]) == 5 * 2  # frames 0..4 (2 tiles each) committed before the failure
    assert stored(out)[2]["state"] == "complete"


# ---- 8. coordinates changed or dropped, spikes computed from a store's (the second probe of xarray habits) ----

@pytest.mark.parametrize("where", ["spikes", "windows", "windows rechunked"])
def test_a_relabelled_frame_is_refused_not_read_at_its_new_numbers(recording, where):
    """``assign_coords(frame=frame + 20)`` keeps the data and its ``t``: reading the store at the new numbers gave
    other frames than an identical rechunked array held (and "lost data" past the end). The ``t`` coordinate no
    longer agrees with ``frame``: refused in one line, on either path."""
    spikes = lazy.open_spikes(recording)
    if where == "spikes":
        refused(lambda: lazy.windows(spikes.assign_coords(frame=spikes.frame + 20), every=20),
                "the t and frame coordinates of spikes disagree (t 0 s at frame 20, 1000 frames a second)")
        return
    win = lazy.windows(spikes, every=20, stop=150)
    if where == "windows rechunked":
        win = win.chunk({"t": 2})
    refused(lambda: lazy.tfp(win.assign_coords(frame=win.frame + 20)), "the t and frame coordinates of windows disagree")


def test_dropped_or_moved_coordinates_are_refused_before_anything_exists(recording, tmp_path):
    """Without its coordinates a part of the recording was taken for another part (spikes or windows without ``y``
    read from row 0; windows without ``dt`` cut to 21 frames recorded as 41); ``hr`` whose ``y`` moved was written
    whole and then refused as a damaged store. Each is refused in one line, and nothing is written."""
    spikes = lazy.open_spikes(recording)
    refused(lambda: lazy.windows(spikes.isel(y=slice(8, 24)).drop_vars("y")), "spikes: the y coordinate is missing")
    win = lazy.windows(spikes, every=20, region="12:20,16:24", margin=8)
    assert win.attrs["kept"] == [4, 28, 8, 32]
    refused(lambda: lazy.tfp(win.chunk({"t": 3}).drop_vars("y")), "windows: the y coordinate is missing")
    refused(lambda: lazy.tfp(win.assign_coords(y=np.arange(win.sizes["y"]))), "outside the y 4:28, x 8:32")
    refused(lambda: lazy.tfp(win.drop_vars("dt").isel(dt=slice(10, 31))), "the dt coordinate is missing")
    refused(lambda: lazy.tfp(win.drop_vars("frame")), "the frame coordinate is missing")
    refused(lambda: lazy.tfp(win.pad(t=(1, 0), constant_values=False)), "frame numbers [nan, 20.0, 40.0]")
    hr = lazy.tfp(lazy.windows(spikes, every=20), tile=16)
    refused(lambda: lazy.to_video(hr.assign_coords(y=hr.y + 4), str(tmp_path / "a.zarr")),
            "hr holds HR y 4:196, outside the 0:192 it was made of")
    refused(lambda: lazy.to_video(hr.isel(y=slice(8, 24)).drop_vars("y"), str(tmp_path / "b.zarr")),
            "hr: the y coordinate is missing")
    refused(lambda: lazy.to_video(hr.drop_vars("gain"), str(tmp_path / "c.zarr")), "hr lacks its gain coordinate")
    assert not os.listdir(tmp_path)


def test_a_selection_whose_coordinates_moved_together_is_read_at_them(recording):
    """Frames 0..99 relabelled 100..199 (``frame`` and ``t`` moved alike, so they agree): the windows held frames
    0..99's bits, and the output recorded 120, 140, 160. A store's spikes as it holds them are read from it at their
    coordinates: the windows are frames 100..199's, rechunked or not."""
    spikes = lazy.open_spikes(recording)
    part = spikes.isel(t=slice(0, 100), x=slice(8, 40))
    moved = part.assign_coords(frame=part.frame + 100, t=part.t + 100 / FPS)
    truth = lazy.windows(spikes.isel(t=slice(100, 200), x=slice(8, 40)), every=20)
    assert not np.array_equal(truth.values, lazy.windows(part, every=20).isel(t=slice(0, 3)).values)
    for given in (moved, moved.chunk({"t": 7})):
        win = lazy.windows(given, every=20)
        assert win.frame.values.tolist() == truth.frame.values.tolist() == [120, 140, 160]
        np.testing.assert_array_equal(win.values, truth.values)


def test_a_selection_of_pixels_is_recorded_as_the_frame_s_edges_and_no_job_resumes_it(recording, client, tmp_path):
    """The selected pixels stand for the frame's edges (a method's halo stops there), so near them the pixels differ
    from the job's ``--region`` of the same part, whose halo reads beyond it. Both recorded the same attributes and
    each resumed the other's store, mixing the two. The selection is recorded (``edges``): each refuses the other."""
    from pipeline.jobs.reconstruct import reconstruct
    from pipeline.jobs.reconstruct_plan import ReconstructOptions

    spikes = lazy.open_spikes(recording)
    selected, job = str(tmp_path / "selected.zarr"), str(tmp_path / "job.zarr")
    hr = lazy.tfp(lazy.windows(spikes.isel(y=slice(8, 40), x=slice(16, 48)), every=20), tile=16)
    lazy.to_video(hr, selected)
    options = ReconstructOptions(method="tfp", every=20, tile=16, region="8:40,16:48")
    reconstruct(recording, job, options, client=client, progress=False)
    (ours, _, ours_attrs), (theirs, _, theirs_attrs) = stored(selected), stored(job)
    assert ours_attrs["edges"] == [8, 40, 16, 48] and theirs_attrs["edges"] is None
    assert ours_attrs["region"] == theirs_attrs["region"] == [8, 40, 16, 48]
    assert not np.array_equal(ours, theirs)  # the pixels near the edges
    refused(lambda: lazy.to_video(hr, job, resume=True), "(edges None -> [8, 40, 16, 48])")
    with pytest.raises(InputError, match=r"\(edges \[8, 40, 16, 48\] -> None\)"):
        reconstruct(recording, selected, dataclasses.replace(options, resume=True), client=client, progress=False)


def test_spikes_computed_from_a_store_s_are_exposed_and_recorded_as_their_own(recording, tmp_path):
    """xarray keeps the attributes that name the store through ``&``, ``~`` and ``where``: such spikes were exposed
    with the store's automatic gain and recorded as made from it. Their gain is now their own, the one they get
    once written and read back (the known answer), and no source is recorded; a part of them, whose recording's
    gain needs all of it, asks for gain=. A selection or a rechunk of the store's spikes keeps the store's gain."""
    spikes = lazy.open_spikes(recording)
    every_other = xr.DataArray(np.arange(FRAMES) % 2 == 0, dims="t")
    masked = spikes & every_other
    hr = lazy.tfp(lazy.windows(masked, every=20), tile=16)
    lazy.to_spikes(masked, str(tmp_path / "masked.zarr"))
    stored_then_read = lazy.tfp(lazy.windows(lazy.open_spikes(tmp_path / "masked.zarr"), every=20), tile=16)
    assert float(hr.gain) == float(stored_then_read.gain) != float(lazy.tfp(lazy.windows(spikes, every=20)).gain)
    assert np.array_equal(hr.values, stored_then_read.values)
    assert hr.attrs["source"] is None and hr.attrs["source_identity"] is None
    refused(lambda: lazy.windows(masked.isel(t=slice(0, 150)), every=20).pipe(lazy.tfp), "give gain=")
    whole = float(lazy.tfp(lazy.windows(spikes, every=20)).gain)
    rechunked = lazy.tfp(lazy.windows(spikes.isel(t=slice(10, 150)).chunk({"t": 7}), every=20))
    assert float(rechunked.gain) == whole and rechunked.attrs["source_identity"] == spikes.attrs["identity"]
