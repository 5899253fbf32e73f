"""Lazy simulation (#45): ``lazy.simulate`` gives the ``simulate`` job's spikes whatever the chunking and computes
nothing until asked; ``lazy.to_spikes`` writes the job's store (its identity), resumes a failed run to the bytes of
an uninterrupted one, gives the same bytes on a two-process cluster, and refuses bad input in one line before
anything is written."""

import importlib
import os
import re
import shutil
import time

import dask
import dask.array as da
import imageio.v3 as iio

import numpy as np
import pytest
import xarray as xr

from pipeline.lazy.simulate import SpikesIncomplete, simulate, to_spikes
from pipeline.lazy.spikes import open_spikes
from pipeline.jobs.simulate import SimulateOptions, simulate as simulate_job
from pipeline.stores.spike_store import COMMITTED, open_spike_store, store_identity
from stages.capture.bits import pack_rows
from stages.errors import InputError, InputTypeError
from tests.test_parallel_ingest import store_files

N_FRAMES = 70  # spike frames, one per scene frame: the job's video source positions are then the frames themselves
HR_HEIGHT, HR_WIDTH = 32, 48  # x4 -> 8x12 LR: a packed row of 2 bytes, the second half empty
SETTINGS = [dict(cfa="rggb", reset="zero", noise="none", seed=0),
            dict(cfa="gbrg", reset="subtract", noise="realistic", seed=5, brightness=0.4)]
JOB_ONLY = ("source", "frames", "state", "spike_count", "identity")  # what only a finished store records


def scene(n_frames: int = N_FRAMES, height: int = HR_HEIGHT, width: int = HR_WIDTH) -> np.ndarray:
    """(t, y, x, 3) uint8: a smooth random picture panning right a pixel a frame, flickering: every pixel changes."""
    rng = np.random.default_rng(1)
    coarse = rng.random((height // 8 + 1, (width + n_frames) // 8 + 1, 3))
    picture = np.kron(coarse, np.ones((8, 8, 1)))[:height]  # (y, x + t, 3)
    flicker = 0.75 + 0.25 * np.sin(np.arange(n_frames) / 3)
    return np.stack([np.round(255 * flicker[t] * picture[:, t:t + width]) for t in range(n_frames)]).astype(np.uint8)


def frames_array(frames: np.ndarray, chunk: int) -> xr.DataArray:
    return xr.DataArray(da.from_array(frames, chunks=(chunk, -1, -1, -1)), dims=("t", "y", "x", "rgb"))


@pytest.fixture(scope="module", params=SETTINGS, ids=lambda settings: f"{settings['reset']}-{settings['noise']}")
def job(request, client, tmp_path_factory):
    """(scene frames, settings, the store the ``simulate`` job made of them): a folder of as many PNG frames as
    spike frames, ``--interp linear``, on the shared two-worker cluster."""
    folder = tmp_path_factory.mktemp("scene")
    frames = scene()
    for t, frame in enumerate(frames):
        iio.imwrite(folder / f"{t:03d}.png", frame)
    store = str(tmp_path_factory.mktemp("job") / "job.zarr")
    simulate_job(str(folder), store, SimulateOptions(scale=4, frames=N_FRAMES, interp="linear", **request.param),
                 scheduler=client.scheduler.address, progress=False)
    return frames, request.param, store


@pytest.mark.parametrize("chunk", [7, 41, N_FRAMES])
def test_equals_the_simulate_job_whatever_the_chunking(job, chunk):
    frames, settings, store = job
    spikes = simulate(frames_array(frames, chunk), **settings)
    assert spikes.dims == ("t", "y", "x") and spikes.dtype == bool and spikes.shape == (N_FRAMES, 8, 12)
    assert spikes.chunks[0] == frames_array(frames, chunk).chunks[0]  # the frames' chunks along t
    stored = open_spike_store(store)
    np.testing.assert_array_equal(pack_rows(spikes.values), stored.spikes[:])
    assert 0.05 < spikes.values.mean() < 0.6  # spikes to compare, not a blank
    assert {k: v for k, v in spikes.attrs.items() if k not in JOB_ONLY} == \
        {k: v for k, v in stored.attrs.items() if k not in JOB_ONLY}
    assert spikes.attrs["frames"] == N_FRAMES  # the recording's length, which a selection of it keeps
    np.testing.assert_allclose(spikes.t.values, np.arange(N_FRAMES) / 20000.0)
    other_seed = simulate(frames_array(frames, chunk), **{**settings, "seed": settings["seed"] + 1})
    assert not np.array_equal(other_seed.values, spikes.values)  # the comparison above can fail


def test_to_spikes_writes_the_job_s_recording(job, tmp_path):
    """Another chunking and cut into tasks than the job's, the same recording: its identity, its spike count."""
    frames, settings, store = job
    out = str(tmp_path / "lazy.zarr")
    result = to_spikes(simulate(frames_array(frames, 9), **settings), out, chunk_frames=8, task_frames=16)
    written, made = open_spike_store(out), open_spike_store(store)
    assert written.complete and written.spikes.chunks[0] == 8 != made.spikes.chunks[0]
    assert store_identity(written) == store_identity(made)
    assert written.spike_count == made.spike_count == result["spikes"] > 0
    assert result["tasks"] == result["tasks_run"] == 5 and result["tasks_skipped"] == 0
    committed = written.group[COMMITTED]
    assert committed.attrs["task_frames"] == 16 and committed[:].min() >= 0 and committed[:].sum() == result["spikes"]
    copy = str(tmp_path / "copy.zarr")  # a store read lazily and written again: the same recording
    to_spikes(open_spikes(out), copy)
    assert store_identity(open_spike_store(copy)) == store_identity(made)


def test_to_spikes_writes_the_job_s_truth_and_evaluate_scores_a_lazy_video_beside_the_methods(job, client, tmp_path, cli,
                                                                                             monkeypatch):
    """``truth=`` the scene: the simulate job's ground truth, byte for byte; ``evaluate(videos=)`` then scores a
    video written by ``lazy.to_video`` beside the built-in methods (the truth read once for both), and it scores
    exactly as the job's tfp."""
    from cscsr import lazy
    import pipeline.jobs.evaluate as evaluation
    from pipeline.jobs.evaluate import evaluate
    from pipeline.stores.ground_truth import TRUTH, TRUTH_FRAMES, read_truth

    frames, settings, store = job
    out = str(tmp_path / "lazy.zarr")
    to_spikes(simulate(frames_array(frames, 9), **settings), out, chunk_frames=8, truth=frames_array(frames, 5))
    written, made = open_spike_store(out), open_spike_store(store)
    for name in (TRUTH, TRUTH_FRAMES):
        np.testing.assert_array_equal(written.group[name][:], made.group[name][:])
    assert written.group[TRUTH].shape[0] == 1 and written.complete  # 70 frames: one centre, 20
    with dask.config.set(scheduler="threads"):
        lazy.to_video(lazy.tfp(lazy.windows(open_spikes(out), every=41)), str(tmp_path / "mine.zarr"))
    truth_reads = []
    monkeypatch.setattr(evaluation, "read_truth", lambda store: truth_reads.append(store.url) or read_truth(store))
    rows = evaluate(out, ["tfp"], str(tmp_path / "evaluation"), videos={"mine": str(tmp_path / "mine.zarr")},
                    workers=1, progress=False)
    assert truth_reads == [out]  # once: for the checks of the store and the video, and for the scores
    monkeypatch.undo()
    assert [row["method"] for row in rows] == ["tfp", "mine"] and rows[1]["seconds_per_image"] is None
    metrics = (tmp_path / "evaluation" / "metrics.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in metrics[1:]] == ["tfp", "mine"]  # per frame too: the methods, then videos
    assert rows[0]["psnr"] == rows[1]["psnr"] and rows[0]["ssim"] == rows[1]["ssim"]  # the same bytes, scored alike
    summary = (tmp_path / "evaluation" / "summary.csv").read_text()
    assert summary.splitlines()[2].startswith("mine,") and (tmp_path / "evaluation" / "comparison.png").exists()
    refusals = {"a name of its own": {"tfp": str(tmp_path / "mine.zarr")},
                "not an HR video store": {"other": out}}
    for fragment, videos in refusals.items():
        with pytest.raises(InputError, match=fragment) as raised:
            evaluate(out, ["tfp"], str(tmp_path / "refused"), videos=videos, workers=1, progress=False)
        assert "\n" not in str(raised.value) and not (tmp_path / "refused").exists()
    done = cli("evaluate", out, "--methods", "", "--video", f"mine={tmp_path / 'mine.zarr'}", "--out",
               tmp_path / "cli", "--scheduler", client.scheduler.address)
    assert done.exit_code == 0 and "mine" in done.stdout and "written" in done.stdout, done.stdout + done.stderr
    assert f"{rows[1]['psnr']:.2f}" in done.stdout
    shutil.copytree(tmp_path / "mine.zarr", tmp_path / "lost.zarr")
    next(p for p in (tmp_path / "lost.zarr" / "video").rglob("*") if p.is_file() and p.name.isdigit()).unlink()
    with pytest.raises(InputError, match="has lost data") as raised:  # it would be scored as black
        evaluate(out, ["tfp"], str(tmp_path / "refused"), videos={"lost": str(tmp_path / "lost.zarr")}, workers=1,
                 progress=False)
    assert "\n" not in str(raised.value) and not (tmp_path / "refused").exists()
    bad = cli("evaluate", out, "--video", "mine", "--out", tmp_path / "cli2", "--scheduler", client.scheduler.address)
    assert bad.exit_code != 0 and "give NAME=URL" in bad.stdout + bad.stderr and not (tmp_path / "cli2").exists()
    with pytest.raises(InputError, match="truth= must be the scene"):
        to_spikes(simulate(frames_array(frames, 9), **settings), str(tmp_path / "bad.zarr"),
                  truth=frames_array(frames[:, :16], 5))
    assert not (tmp_path / "bad.zarr").exists()


def test_evaluate_refuses_a_video_at_another_scale_and_labels_a_region_as_it_scores_it(job, tmp_path, monkeypatch):
    """A x2 video of a x4 store was scored against the truth's top-left quarter (12 dB, no error); a region's
    panel in comparison.png was labelled with the PSNR of its black-padded frame, not the one metrics.csv has."""
    from cscsr import lazy
    import pipeline.jobs.evaluate as evaluation
    from pipeline.jobs.evaluate import evaluate

    _, _, store = job
    with dask.config.set(scheduler="threads"):
        windows = lazy.windows(open_spikes(store), every=41)
        lazy.to_video(lazy.tfp(windows, scale=2), str(tmp_path / "x2.zarr"))
        lazy.to_video(lazy.tfp(lazy.windows(open_spikes(store), every=41, region="0:4,4:12")),
                      str(tmp_path / "part.zarr"))
    with pytest.raises(InputError, match=r"x2.zarr is at scale 2, and the truth at scale 4 \(32x48 HR\)"):
        evaluate(store, [], str(tmp_path / "refused"), videos={"x2": str(tmp_path / "x2.zarr")}, workers=1)
    assert not (tmp_path / "refused").exists()
    labels = []
    original = evaluation.labelled
    monkeypatch.setattr(evaluation, "labelled", lambda image, text: labels.append(text) or original(image, text))
    (row,) = evaluate(store, [], str(tmp_path / "scored"), videos={"part": str(tmp_path / "part.zarr")}, workers=1)
    assert row["frames"] == 1 and labels[1] == f"part: {row['psnr']:.2f} dB this frame"  # one truth frame: its own


def test_open_frames_of_the_job_s_source_writes_the_job_s_store_spikes_and_truth(job, tmp_path):
    """``cscsr simulate`` of a folder of as many frames as spike frames is ``to_spikes(simulate(open_frames(folder)),
    truth=open_frames(folder))``: every chunk of spikes and truth, the attributes (the source's place included)."""
    from cscsr import lazy
    from pipeline.stores.ground_truth import TRUTH, TRUTH_FRAMES

    frames, settings, store = job
    folder = open_spike_store(store).attrs["source"]
    scene = lazy.open_frames(folder, chunk_frames=9)
    assert scene.dims == ("t", "y", "x", "rgb") and scene.shape == frames.shape and scene.dtype == np.uint8
    assert scene.data.chunks[0] == (9,) * 7 + (7,) and scene.attrs == {"source": folder, "motion": "video"}
    np.testing.assert_array_equal(scene[20:30].values, frames[20:30])  # read a block at a time, as stored
    out = str(tmp_path / "lazy.zarr")
    to_spikes(lazy.simulate(scene, **settings), out, truth=scene)
    written, made = open_spike_store(out), open_spike_store(store)
    for name in ("spikes", TRUTH, TRUTH_FRAMES):
        np.testing.assert_array_equal(written.group[name][:], made.group[name][:])
    assert {k: v for k, v in written.attrs.items() if k != "identity"} == \
        {k: v for k, v in made.attrs.items() if k != "identity"}
    assert store_identity(written) == store_identity(made)


def test_open_frames_of_a_video_reads_each_block_in_one_pass_the_frames_the_job_reads(tmp_path):
    """A block of a video's frames is decoded by one reader, in order (the job's reader decodes from the start, or
    a seek, for each frame): the same frames."""
    import imageio.v2 as iio2
    from cscsr import lazy
    from pipeline.stores.frame_sources import open_frame_source

    writer = iio2.get_writer(str(tmp_path / "v.mp4"), fps=25, codec="libx264", quality=8, macro_block_size=1)
    for frame in scene(20, 16, 24):
        writer.append_data(frame)
    writer.close()
    source = open_frame_source(str(tmp_path / "v.mp4"))
    one_by_one = np.stack([source.read(index) for index in range(source.n_frames)])
    frames = lazy.open_frames(tmp_path / "v.mp4", chunk_frames=7)
    assert frames.shape == (20, 16, 24, 3) and frames.data.chunks[0] == (7, 7, 6)
    np.testing.assert_array_equal(frames.values, one_by_one)
    np.testing.assert_array_equal(frames[9:13].values, one_by_one[9:13])  # across two blocks, each from its start


@pytest.mark.parametrize("motion", ["random", "static"])
def test_a_picture_under_motion_is_the_job_s_scene_spikes_and_truth(motion, tmp_path):
    """``open_frames(picture, frames=, motion=, seed=)`` is the scene ``cscsr simulate PICTURE --motion`` makes:
    the job's camera path of its seed, each frame rendered (or the picture in every frame): the job's spikes,
    truth, the path's flow between truth frames, and attributes."""
    from cscsr import lazy
    from pipeline.stores.ground_truth import TRUTH, TRUTH_FRAMES

    picture = tmp_path / "scene.png"
    iio.imwrite(picture, scene(1, 64, 96)[0])
    options = dict(scale=4, cfa="rggb", reset="subtract", noise="realistic", seed=3)
    job = str(tmp_path / "job.zarr")
    path = {"speed": 1.5} if motion == "random" else {}  # the path's speed shapes a random path alone
    simulate_job(str(picture), job, SimulateOptions(frames=90, motion=motion, **path, **options),
                 workers=1, progress=False)
    frames = lazy.open_frames(picture, frames=90, motion=motion, seed=3, chunk_frames=16, **path)
    assert frames.shape == (90, 64, 96, 3) and frames.attrs["motion"] == motion
    assert frames.dtype == (np.float32 if motion == "random" else np.uint8)
    out = str(tmp_path / "lazy.zarr")
    to_spikes(lazy.simulate(frames, **options), out, truth=frames)
    written, made = open_spike_store(out), open_spike_store(job)
    for name in ("spikes", TRUTH, TRUTH_FRAMES) + (("flow",) if motion == "random" else ()):
        np.testing.assert_array_equal(written.group[name][:], made.group[name][:])
    assert ("flow" in written.group) == (motion == "random")
    assert {k: v for k, v in written.attrs.items() if k != "identity"} == \
        {k: v for k, v in made.attrs.items() if k != "identity"}
    if motion == "random":  # the scene moves: another seed, another path
        other = lazy.open_frames(picture, frames=90, motion=motion, seed=4, speed=1.5)
        assert not np.array_equal(other[60].values, frames[60].values)
        # what the job would not make is not recorded as its: the path of another seed, a part of a longer path
        with pytest.raises(InputError, match=r"camera path of seed 3 .*simulate\(seed=4\)"):
            lazy.simulate(frames, **{**options, "seed": 4})
        with pytest.raises(InputError, match=r"frames are 60 of a camera path of 90 frames: .*frames=60\)"):
            lazy.simulate(frames.isel(t=slice(0, 60)), **options)
        # nor the truth of another path: it was written, scored 4.5 dB lower, under the attributes of seed 3
        other = lazy.open_frames(picture, frames=90, motion=motion, seed=4, speed=1.5, chunk_frames=16)
        with pytest.raises(InputError, match="truth= is not the scene these spikes were simulated from"):
            to_spikes(lazy.simulate(frames, **options), str(tmp_path / "other.zarr"), truth=other)
        assert not (tmp_path / "other.zarr").exists()


def test_a_folder_s_frames_rewritten_in_place_are_a_new_graph(tmp_path):
    """The graph's name says which version of the frames it reads: a picture rewritten inside the folder (the
    folder's own time unchanged) makes another, so a cluster holding the old one does not answer for the new."""
    from cscsr import lazy

    for t in range(3):
        iio.imwrite(tmp_path / f"{t}.png", np.full((8, 8, 3), t, np.uint8))
    before = lazy.open_frames(tmp_path)
    assert lazy.open_frames(tmp_path).data.name == before.data.name  # the same frames: the same graph
    os.utime(tmp_path / "1.png", ns=(1, 1))  # as if rewritten long ago: the time alone
    iio.imwrite(tmp_path / "1.png", np.full((8, 8, 3), 9, np.uint8))
    after = lazy.open_frames(tmp_path)
    assert after.data.name != before.data.name and after[1].values.max() == 9


def test_open_frames_refuses_what_simulate_cannot_read_in_one_line(tmp_path):
    from cscsr import lazy

    (tmp_path / "empty").mkdir()
    frames = tmp_path / "mixed"
    frames.mkdir()
    iio.imwrite(frames / "0.png", np.zeros((8, 8, 3), np.uint8))
    iio.imwrite(frames / "1.png", np.zeros((8, 8), np.uint8))  # grey after colour
    for call, fragment in ((lambda: lazy.open_frames(tmp_path / "nothing"), "no such file or folder"),
                           (lambda: lazy.open_frames(tmp_path / "empty"), "holds no images"),
                           (lambda: lazy.open_frames(frames, chunk_frames=0), "chunk_frames must be >= 1"),
                           (lambda: lazy.open_frames(frames).values, "frame 1 is uint8 with 1 colours"),
                           (lambda: lazy.open_frames(frames, frames=50, motion="random"), "for a picture; "),
                           (lambda: lazy.open_frames(frames / "0.png"), "give frames= and motion="),
                           (lambda: lazy.open_frames(frames / "0.png", frames=50, motion="wobble"), "'wobble'"),
                           (lambda: lazy.open_frames(frames / "0.png", frames=50, motion="random", seed=-1),
                            "seed must be >= 0"),
                           (lambda: lazy.open_frames(frames / "0.png", frames=0, motion="static"),
                            "frames must be >= 1")):
        with pytest.raises(InputError, match=re.escape(fragment)) as raised:
            call()
        assert "\n" not in str(raised.value)
    assert lazy.open_frames(frames, chunk_frames=1)[:1].values.shape == (1, 8, 8, 3)  # frame 0 alone: read


def test_simulate_computes_nothing_until_asked():
    def unreadable(block):
        raise RuntimeError("a frame was read")

    frames = da.zeros((N_FRAMES, HR_HEIGHT, HR_WIDTH, 3), np.uint8, chunks=(10, -1, -1, -1))
    frames = frames.map_blocks(unreadable, dtype=np.uint8)
    spikes = simulate(xr.DataArray(frames, dims=("t", "y", "x", "rgb")), noise="realistic")  # builds the graph only
    assert spikes.chunks[0] == (10,) * 7
    with pytest.raises(RuntimeError, match="a frame was read"):
        spikes[:1].values


def _fails_until(block: np.ndarray, flag: str, frame: int, block_info=None) -> np.ndarray:
    """``block`` as it is, but the block holding spike frame ``frame`` fails while ``flag`` does not exist."""
    start, stop = block_info[0]["array-location"][0]
    if start <= frame < stop and not os.path.exists(flag):
        raise OSError("disk full")
    return block


def failing_at_frame_55(tmp_path):
    """(scene frames, their spikes, the same spikes failing at frame 55 until ``flag`` exists, ``flag``)."""
    frames = frames_array(scene(), 10)
    spikes = simulate(frames, reset="subtract", noise="realistic", seed=2)
    flag = str(tmp_path / "fixed")
    return frames, spikes, spikes.copy(data=spikes.data.map_blocks(_fails_until, flag, 55, dtype=bool)), flag


def test_a_failed_to_spikes_resumes_to_the_bytes_of_an_uninterrupted_one(tmp_path):
    frames, spikes, failing, flag = failing_at_frame_55(tmp_path)
    whole, resumed = str(tmp_path / "whole.zarr"), str(tmp_path / "resumed.zarr")
    with dask.config.set(scheduler="synchronous"):  # the tasks before the failure run first
        to_spikes(spikes, whole, chunk_frames=8)
        with pytest.raises(SpikesIncomplete, match="disk full"):
            to_spikes(failing, resumed, chunk_frames=8)
        committed = open_spike_store(resumed, allow_incomplete=True).group[COMMITTED][:]
        assert 0 < (committed >= 0).sum() < len(committed)  # kept what it committed, and not all
        with pytest.raises(InputError, match="incomplete"):
            open_spike_store(resumed)
        with pytest.raises(InputError, match="other attributes .*seed 2 -> 3"):
            to_spikes(simulate(frames, reset="subtract", noise="realistic", seed=3), resumed, resume=True)
        with pytest.raises(InputError, match="chunks of 8"):
            to_spikes(failing, resumed, chunk_frames=16, resume=True)
        open(flag, "w").close()
        result = to_spikes(failing, resumed, resume=True)
    assert result["tasks_skipped"] == (committed >= 0).sum() and result["tasks_run"] == (committed < 0).sum()
    assert store_files(resumed) == store_files(whole)  # every byte: chunks, commit record, attributes, identity


def test_a_resume_needs_the_truth_it_was_begun_with_and_opens_the_store_once_a_purpose(tmp_path, monkeypatch):
    """A failed ``to_spikes(truth=)`` resumes only with the truth again, to the bytes of an uninterrupted one; the
    resume opens the store once for the checks before the claim (its cut and its truth) and once under the claim."""
    lazy_simulate = importlib.import_module("pipeline.lazy.simulate")  # pipeline.lazy.simulate is the function
    writes = importlib.import_module("pipeline.stores.spike_writes")  # the store's writes (the job's, resumed here)

    frames, spikes, failing, flag = failing_at_frame_55(tmp_path)
    whole, resumed = str(tmp_path / "whole.zarr"), str(tmp_path / "resumed.zarr")
    with dask.config.set(scheduler="synchronous"):  # the tasks before the failure run first
        to_spikes(spikes, whole, chunk_frames=8, truth=frames)
        with pytest.raises(SpikesIncomplete, match="disk full"):
            to_spikes(failing, resumed, chunk_frames=8, truth=frames)
        with pytest.raises(InputError, match="begun with truth=: give the same scene frames"):
            to_spikes(failing, resumed, resume=True)
        open(flag, "w").close()
        opened = []
        for module in (lazy_simulate, writes):
            monkeypatch.setattr(module, "open_spike_store",
                                lambda url, **kwargs: opened.append(url) or open_spike_store(url, **kwargs))
        result = to_spikes(failing, resumed, resume=True, truth=frames)
    assert opened == [resumed, resumed]  # the checks before the claim, the check under it (the writer its own)
    assert result["tasks_skipped"] > 0 and result["attrs"]["state"] == "complete"
    assert store_files(resumed) == store_files(whole)  # the truth too


def _noting_process(block: np.ndarray, folder: str) -> np.ndarray:
    open(os.path.join(folder, str(os.getpid())), "w").close()
    return block


def test_to_spikes_on_a_cluster_of_processes_gives_the_same_bytes(client, tmp_path):
    """The active ``distributed.Client`` (two worker processes) runs the tasks; the bytes are the threads'."""
    spikes = simulate(frames_array(scene(), 13), cfa="grbg", noise="realistic", seed=4)
    threads, cluster = str(tmp_path / "threads.zarr"), str(tmp_path / "cluster.zarr")
    with dask.config.set(scheduler="threads"):
        to_spikes(spikes, threads, chunk_frames=8, task_frames=24)
    processes = tmp_path / "processes"
    processes.mkdir()
    noted = spikes.data.map_blocks(_noting_process, str(processes), meta=np.empty((0, 0, 0), bool))  # no call here
    to_spikes(spikes.copy(data=noted), cluster, chunk_frames=8, task_frames=24)
    assert os.listdir(processes) and str(os.getpid()) not in os.listdir(processes)  # run by the workers
    assert store_files(cluster) == store_files(threads)
    with pytest.raises(InputError, match="memory://"):  # each worker process would write its own
        to_spikes(spikes, "memory://lazy.zarr")


def _bad_simulate_calls():
    good = frames_array(scene(), 10)
    return [
        (lambda: simulate(good.values), InputTypeError, "must be an xarray.DataArray"),
        (lambda: simulate(good.isel(rgb=0)), InputError, "must have dims"),
        (lambda: simulate(good.rename(rgb="c")), InputError, "must have dims"),
        (lambda: simulate(good.astype(np.int16)), InputError, "got int16"),
        (lambda: simulate(good.astype(bool)), InputError, "got bool"),
        (lambda: simulate(good.isel(rgb=[0, 1])), InputError, "rgb of size 1, 3 or 4"),
        (lambda: simulate(good, scale=3), InputError, "scale must be one of"),
        (lambda: simulate(good, scale=4.0), InputTypeError, "scale must be an integer"),  # Python words
        (lambda: simulate(good, cfa="xyz"), InputError, "xyz"),
        (lambda: simulate(good, noise="loud"), InputError, "unknown noise 'loud'"),
        (lambda: simulate(good, reset="half"), InputError, "unknown reset mode 'half'"),
        (lambda: simulate(good, brightness=0), InputError, "brightness"),
        (lambda: simulate(good, seed=-1), InputError, "seed"),
        (lambda: simulate(good, fps=0), InputError, "fps"),
        (lambda: simulate(good.isel(t=slice(0, 20))), InputError, "frames=20 is too few"),
        (lambda: simulate(good.isel(y=slice(0, 28))), InputError, "not divisible by 2*scale = 8"),
    ]


@pytest.mark.parametrize("index", range(len(_bad_simulate_calls())))
def test_simulate_refuses_bad_input_in_one_line(index):
    call, kind, fragment = _bad_simulate_calls()[index]
    with pytest.raises(kind) as raised:
        call()
    assert fragment in str(raised.value) and "\n" not in str(raised.value)


def on_processes(call):
    """``call()`` with Dask's multiprocessing scheduler active: where each process would write its own memory://."""
    with dask.config.set(scheduler="processes"):
        return call()


def test_to_spikes_refuses_bad_input_in_one_line_before_anything_is_written(tmp_path):
    spikes = simulate(frames_array(scene(), 10))
    existing = str(tmp_path / "existing.zarr")
    to_spikes(spikes, existing)
    out = str(tmp_path / "out.zarr")
    lacking = spikes.copy()
    del lacking.attrs["height"]
    calls = [
        (lambda: to_spikes(spikes.values, out), InputTypeError, "must be an xarray.DataArray"),
        (lambda: to_spikes(spikes.transpose("t", "x", "y"), out), InputError, "must have dims"),
        (lambda: to_spikes(spikes.astype(np.uint8), out), InputError, "must be bool"),
        (lambda: to_spikes(spikes.compute(), out), InputError, "dask-backed"),
        (lambda: to_spikes(spikes[:, :4], out), InputError, "a selection of pixels (y 0:4, x 0:12 of the recording's 8x12)"),
        (lambda: to_spikes(spikes[:0], out), InputError, "no frame"),
        (lambda: to_spikes(lacking, out), InputError, "lack height"),
        (lambda: to_spikes(spikes, 5), InputTypeError, "url must be a path or URL"),
        (lambda: to_spikes(spikes, ""), InputError, "url is empty"),
        (lambda: to_spikes(spikes.isel(t=slice(None, None, 2)), out), InputError, "skips (a step of 2)"),
        (lambda: to_spikes(spikes.isel(t=slice(None, None, -1)), out), InputError, "runs backwards"),
        (lambda: to_spikes(spikes, out, overwrite="yes"), InputTypeError, "overwrite"),
        (lambda: to_spikes(spikes, out, progress="no"), InputTypeError, "progress"),
        (lambda: to_spikes(spikes, out, task_frames=0), InputError, "task_frames"),
        (lambda: to_spikes(spikes, out, resume=True), InputError, "cannot resume"),
        (lambda: to_spikes(spikes, existing, resume=True, overwrite=True), InputError, "contradict"),
        (lambda: to_spikes(spikes, existing), InputError, "already exists"),
        (lambda: to_spikes(open_spikes(existing), existing, overwrite=True), InputError, existing),
        (lambda: on_processes(lambda: to_spikes(spikes, "memory://lazy.zarr")), InputError, "memory://"),
    ]
    before = store_files(tmp_path)
    for call, kind, fragment in calls:
        with pytest.raises(kind) as raised:
            call()
        assert fragment in str(raised.value) and "\n" not in str(raised.value), str(raised.value)
        assert store_files(tmp_path) == before and not os.path.exists(out)
    with dask.config.set(scheduler="threads"):  # this process's own memory:// store
        assert to_spikes(spikes, f"memory://{tmp_path.name}.zarr")["spikes"] == open_spike_store(existing).spike_count


@pytest.mark.parametrize("on", ["threads", "client"])
def test_progress_counts_each_frame_written_once_on_a_client_or_dask_s_own_scheduler(on, client, tmp_path,
                                                                                      monkeypatch):
    """``progress=True``: a bar of the frames written, advanced as each task is written (spikes computed from a
    scene, and a capture's frames written by ingest's tasks); a resume's bar holds every frame, those committed
    before shown done from its start."""
    import contextlib

    from cscsr import lazy
    from tests.conftest import write_dat

    bars = []

    @contextlib.contextmanager
    def recorded(description, total, *, done=0, unit="frames", enabled=True):
        bars.append({"description": description, "total": total, "done": done, "advanced": [], "enabled": enabled})
        yield bars[-1]["advanced"].append

    monkeypatch.setattr(importlib.import_module("pipeline.stores.spike_writes"), "progress_bar", recorded)
    bits = (np.random.default_rng(4).random((50, 8, 16)) < 0.2).astype(np.uint8)
    write_dat(tmp_path / "c.dat", bits)
    frames, spikes, failing, flag = failing_at_frame_55(tmp_path)
    with dask.config.set(scheduler=client if on == "client" else "threads"):
        to_spikes(spikes, str(tmp_path / "s.zarr"), chunk_frames=8, progress=True)
        to_spikes(lazy.open_capture(tmp_path / "c.dat", height=8, width=16), str(tmp_path / "c.zarr"),
                  chunk_frames=5, task_frames=10, progress=True)
        with pytest.raises(SpikesIncomplete):
            to_spikes(failing, str(tmp_path / "f.zarr"), chunk_frames=8, progress=True)
        done = open_spike_store(str(tmp_path / "f.zarr"), allow_incomplete=True).group[COMMITTED][:] >= 0
        open(flag, "w").close()
        to_spikes(failing, str(tmp_path / "f.zarr"), resume=True, progress=True)
    whole, capture, failed, resumed = bars
    written_first = sum(min(8, N_FRAMES - 8 * i) for i in np.flatnonzero(done))  # frames the failed run committed
    assert whole["description"] == f"to_spikes {tmp_path / 's.zarr'}" and whole["enabled"]
    assert whole["total"] == N_FRAMES and sorted(whole["advanced"]) == [6] + [8] * 8  # a chunk a task, as written
    assert capture["total"] == 50 and capture["advanced"] == [10] * 5
    # the failed task not counted (nor, on dask's own scheduler, one that finished after the failure was raised)
    assert failed["total"] == N_FRAMES and 0 < sum(failed["advanced"]) <= written_first
    assert failed["done"] == 0 and resumed["total"] == N_FRAMES and resumed["done"] == written_first
    assert sum(resumed["advanced"]) == N_FRAMES - written_first
    assert store_files(tmp_path / "f.zarr") == store_files(tmp_path / "s.zarr")


@pytest.mark.parametrize("kind", ["video", "picture"])
def test_on_one_client_the_simulate_job_runs_the_lazy_stages_tasks(kind, client, tmp_path):
    """``cscsr simulate`` is a front door to the lazy stages: on one client its Dask tasks are those of
    ``to_spikes(simulate(open_frames(...)), truth=scene)`` (a video of fewer frames than spike frames, interpolated
    by flow at LR; a picture along the camera path), the same key prefixes and the same bytes, flow included."""
    from distributed import get_task_stream
    from cscsr import lazy

    if kind == "video":
        source = tmp_path / "frames"
        source.mkdir()
        for t, frame in enumerate(scene(4, 64, 64)[::1]):
            iio.imwrite(source / f"{t}.png", np.roll(frame, 5 * t, axis=1))
        motion = None
    else:
        source = tmp_path / "scene.png"
        iio.imwrite(source, scene(1, 64, 64)[0])
        motion = "random"
    settings = dict(scale=4, seed=2, noise="realistic", reset="subtract")
    with get_task_stream(client) as job:
        simulate_job(str(source), str(tmp_path / "job.zarr"),
                     SimulateOptions(frames=100, motion=motion, chunk_frames=20, truth_every=30, **settings),
                     scheduler=client.scheduler.address, progress=False)
    with get_task_stream(client) as graph:
        frames = lazy.open_frames(source, frames=100, motion=motion, seed=2, chunk_frames=20)
        to_spikes(lazy.simulate(frames, truth_every=30, **settings), str(tmp_path / "lazy.zarr"), chunk_frames=20,
                  truth=frames)
    def stage(key) -> str:  # the key's name without its token
        return re.sub(r"-[0-9a-f]{32}", "", key[0] if isinstance(key, tuple) else key)

    ran = {name: sorted(stage(r["key"]) for r in stream.data) for name, stream in (("job", job), ("graph", graph))}
    assert ran["job"] == ran["graph"]
    assert ran["job"].count("to-spikes") == 5 and ran["job"].count("truth") == 2  # at frames 20 and 50
    assert ran["job"].count("truth-flow") == (1 if kind == "picture" else 0)  # from one truth frame to the next
    assert ran["job"].count("simulated-spikes-source-motion") == (3 if kind == "video" else 0)  # once a pair
    written, made = open_spike_store(str(tmp_path / "lazy.zarr")), open_spike_store(str(tmp_path / "job.zarr"))
    for name in ("spikes", "truth", "truth_frames") + (("flow",) if kind == "picture" else ()):
        np.testing.assert_array_equal(written.group[name][:], made.group[name][:])
    assert {k: v for k, v in written.attrs.items() if k != "identity"} == \
        {k: v for k, v in made.attrs.items() if k != "identity"}


def test_a_video_over_more_spike_frames_is_interpolated_between_its_frames(tmp_path):
    """``open_frames(video, frames=N)``: the video's frames spread evenly over N spike frames, each spike frame the
    blend of the two frames it lies between (linear), its source frames exact where it lies on one; the scale of
    the motion's estimate is simulate's own, refused otherwise."""
    from cscsr import lazy

    for t, frame in enumerate(scene(3, 16, 24)):
        iio.imwrite(tmp_path / f"{t}.png", frame)
    source = scene(3, 16, 24).astype(np.float32) / 255
    frames = lazy.open_frames(tmp_path, frames=41, interp="linear", chunk_frames=8)
    assert frames.shape == (41, 16, 24, 3) and frames.dtype == np.float32 and frames.data.chunks[0][0] == 8
    assert frames.attrs == {"source": str(tmp_path), "motion": "video", "interp": "linear", "scale": 4}
    values = frames.values
    np.testing.assert_allclose(values[[0, 20, 40]], source, atol=1e-6)  # frames 0, 20, 40 lie on the video's
    np.testing.assert_allclose(values[5], 0.75 * source[0] + 0.25 * source[1], atol=1e-6)
    with pytest.raises(InputError, match=r"open_frames\(scale=4\).*simulate\(scale=2\)"):
        simulate(frames, scale=2)
    with pytest.raises(InputError, match="unknown interpolation 'cubic'"):
        lazy.open_frames(tmp_path, frames=41, interp="cubic")
    with pytest.raises(InputError, match="motion= is for a picture"):
        lazy.open_frames(tmp_path, frames=41, motion="random")


@pytest.mark.parametrize("on", ["client", "threads"])
def test_to_spikes_writes_in_bounded_rounds_each_block_once_to_the_same_bytes(on, client, tmp_path, monkeypatch):
    """Writes go to the scheduler a round at a time (``WRITES_AT_ONCE`` tasks), what later rounds need carried over
    (the integrator's state, the sensor's draws: never more), each block fired once, the bytes of one round."""
    writes, executor = (importlib.import_module(f"pipeline.{name}") for name in ("stores.spike_writes",
                                                                                 "compute.executor"))
    spikes = simulate(frames_array(scene(), 5), reset="subtract", noise="realistic", seed=2)  # 14 blocks
    whole, rounded = str(tmp_path / "whole.zarr"), str(tmp_path / "rounds.zarr")
    to_spikes(spikes, whole, chunk_frames=5)  # one round: 14 tasks of 5 frames
    rounds, made = [], executor._rounds
    monkeypatch.setattr(writes, "WRITES_AT_ONCE", 4)
    monkeypatch.setattr(executor, "_rounds", lambda *args: [rounds.append(r) or r for r in made(*args)])
    with dask.config.set(scheduler=client if on == "client" else "threads"):
        to_spikes(spikes, rounded, chunk_frames=5)
    assert [len(keys) for keys, *_ in rounds] == [4, 4, 4, 2]
    fired = [key for _, graph, *_ in rounds for key in graph if "-fired" in str(key)]
    assert len(fired) == len(set(fired)) == 14  # each block fired once, in the round that writes it
    assert all(len(needed_later) <= 3 for *_, needed_later in rounds)  # the state, dark current, thresholds
    assert store_files(rounded) == store_files(whole)


def _fails_while(flag: str, value: int) -> int:
    if os.path.exists(flag):
        raise OSError("transient")
    return value


def test_a_key_carried_between_rounds_that_failed_is_computed_afresh_on_the_same_client(client, tmp_path):
    """A round's task that later rounds read, failed for a passing cause, is released with its round: the next call
    on the same client computes it afresh instead of getting the old error back (a resume would otherwise fail)."""
    import operator

    from pipeline.compute.executor import computed

    flag = tmp_path / "failing"
    flag.touch()
    graph = {"a": (_fails_while, str(flag), 1), "w0": (operator.add, "a", 0), "w1": (operator.add, "a", 1)}
    with pytest.raises(OSError, match="transient") as failed:  # kept: its traceback holds the call's futures
        computed(graph, {"w0": 1, "w1": 1}, lambda frames: None, client, at_once=1)  # "a": carried to round 2
    flag.unlink()
    deadline = time.monotonic() + 10  # releases reach the scheduler a moment later
    while client.run_on_scheduler(lambda dask_scheduler: "a" in dask_scheduler.tasks):
        assert time.monotonic() < deadline, "the failed key is still held by the cluster"
        time.sleep(0.05)
    assert computed(graph, {"w0": 1, "w1": 1}, lambda frames: None, client, at_once=1) == [1, 2]
    assert failed.value.__traceback__ is not None  # the error was alive throughout


def test_a_made_scene_is_known_by_its_data_and_its_blocks_not_by_its_attributes(tmp_path):
    """Two chunkings of one scene are two graphs (one cluster never confuses their blocks); a scene whose attributes
    were dropped is still the job's: its camera path's seed checked, its motion and source recorded."""
    from cscsr import lazy

    picture = tmp_path / "scene.png"
    iio.imwrite(picture, scene(1, 32, 48)[0])
    by_10, by_20 = (lazy.open_frames(picture, frames=60, motion="random", seed=3, chunk_frames=n) for n in (10, 20))
    assert by_10.data.name != by_20.data.name
    assert simulate(by_10, seed=3).data.name != simulate(by_20, seed=3).data.name
    bare = xr.DataArray(by_10.data, dims=by_10.dims)  # its attributes gone
    with pytest.raises(InputError, match=r"camera path of seed 3 .*simulate\(seed=4\)"):
        simulate(bare, seed=4)
    recorded = simulate(bare, seed=3).attrs
    assert (recorded["motion"], recorded["source"]) == ("random", str(picture))
