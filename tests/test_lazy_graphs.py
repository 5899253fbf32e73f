"""``cscsr.lazy``: the reconstruction's stages as lazy Dask graphs on xarray, on real Zarr stores and real clusters.

- ``to_video(reconstruct(windows(open_spikes(...))))`` writes the bytes (and attributes) ``cscsr reconstruct``
  writes with the same options: TFP, TFI and the shipped lite network, whole and with ``--start/--stop/--region``.
- Nothing is read before something computes: a million-frame recording whose chunks are all gone still builds
  its graph (a few hundred tasks), and names the lost frames when computed.
- The threaded scheduler, a ``LocalCluster`` of processes and a worker killed mid-``to_video`` give one result;
  a failed ``to_video`` is resumed to the bytes of an uninterrupted one.
- A user's function runs between stages (``map_blocks``) and as a method of its own (``apply``, tiles and halo).
- On a cluster with GPU workers the network's tasks carry the ``GPU`` resource and run there only.
- Bad input is the jobs' one line, before anything is written.
"""

import os
import pathlib
import shutil
import subprocess
import sys
import threading
import time

import dask
import numpy as np
import pytest
import xarray as xr
import zarr
from dask.utils import key_split
from distributed import Client, LocalCluster, get_task_stream

from cscsr import lazy
from pipeline.compute.cluster import GPU, GPU_SHARE
from pipeline.lazy import written as lazy_written
from pipeline.lazy.windows import MARGIN
from pipeline.lazy.windows import WINDOW_BLOCKS
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from pipeline.stores.spike_store import SPIKES, SpikeMeta, SpikeStoreWriter
from stages.errors import InputError, InputTypeError
from tests.test_gpu_workers import cluster, names
from tests.test_ranges_and_regions import FPS, FRAMES, HEIGHT, WIDTH, recording  # noqa: F401 - the fixture: 200 frames


def threaded():
    """Dask's threaded scheduler, whatever client a test module has made the default."""
    return dask.config.set(scheduler="threads")


def stored(url: str) -> tuple[np.ndarray, np.ndarray, dict]:
    group = zarr.open_group(url, mode="r")
    return group["video"][:], group["frames"][:], dict(group.attrs)


CASES = {  # the job's options -> (windows' arguments, the stage)
    "tfp": dict(method="tfp", every=17, tile=16),  # 10 output frames of 3x4 tiles
    "tfp-part": dict(method="tfp", every=7, tile=16, start=30, stop="0.15s", region="8:40,16:48"),
    "tfi": dict(method="tfi", every=20, tile=24),
    # output frames 80 to 140 of the whole run's 20, 40, ...: two blocks (80; 100 to 140), cut where the whole run's
    # batches of 4 are; two tiles (each reads the whole recording with the network's halo)
    "lite-part": dict(method="cscsr", weights="lite", every=20, tile=16, start=80, stop=160, region="8:24,16:48"),
}


def lazily(store: str, method: str, every: int, tile: int, weights=None, **part) -> xr.DataArray:
    win = lazy.windows(lazy.open_spikes(store), every=every, **part)
    if method == "tfp":
        return lazy.tfp(win, tile=tile)
    if method == "tfi":
        return lazy.tfi(win, tile=tile)
    return lazy.reconstruct(win, method=method, weights=weights, tile=tile)


@pytest.mark.parametrize("case", CASES)
def test_to_video_writes_what_the_job_writes(recording, client, case, tmp_path):
    """The job (on the module's cluster, whose workers have the network loaded once) and the lazy stages (on dask's
    threaded scheduler) write the same bytes and record."""
    options = CASES[case]
    job_counts = reconstruct(recording, str(tmp_path / "job.zarr"), ReconstructOptions(**options), client=client,
                             progress=False)
    hr = lazily(recording, **options)
    with threaded():
        counts = lazy.to_video(hr, str(tmp_path / "lazy.zarr"))
    job, made = stored(str(tmp_path / "job.zarr")), stored(str(tmp_path / "lazy.zarr"))
    assert np.array_equal(job[0], made[0]) and np.array_equal(job[1], made[1])
    assert job[2] == made[2]  # the same record: method, weights and their hash, gain, part, source, state ...
    assert counts["frames"] == len(job[1]) and counts["tasks_skipped"] == 0
    assert counts == job_counts  # in the same tasks: a block along time (a network's batch of frames) of a tile
    with threaded():  # a resume of the job's store finds all of them committed
        assert lazy.to_video(hr, str(tmp_path / "job.zarr"), resume=True)["tasks_skipped"] == counts["tasks_run"]
    assert hr.shape == job[0].shape and list(hr.coords["frame"].values) == list(job[1])
    assert np.array_equal(hr.coords["t"].values, job[1] / FPS)  # centre times in seconds


@pytest.mark.parametrize("case", ["tfp", "lite-part"])
def test_on_one_client_the_job_runs_the_lazy_graphs_tasks(recording, client, case, tmp_path):
    """The job is a front door to the lazy stages: on one client its Dask tasks are those of the equivalent
    ``to_video(reconstruct(windows(open_spikes(...))))``: the same key prefixes (the automatic exposure, a block of a
    tile read from the store, reconstructed and written), the same blocks, the same bytes."""

    options = CASES[case]
    with get_task_stream(client) as job:
        reconstruct(recording, str(tmp_path / "job.zarr"), ReconstructOptions(**options), client=client,
                    progress=False)
    with get_task_stream(client) as graph:
        lazy.to_video(lazily(recording, **options), str(tmp_path / "lazy.zarr"))
    ran = {name: sorted((key_split(r["key"]), *r["key"][1:]) for r in stream.data if isinstance(r["key"], tuple))
           for name, stream in (("job", job), ("graph", graph))}
    method = options["method"]
    assert ran["job"] == ran["graph"] and {key for key, *_ in ran["job"]} == {"auto-gain", method}
    # a task per block of a tile reads, reconstructs and writes it (its HR block never travels): every tile, once
    blocks = [tuple(rest) for key, *rest in ran["job"] if key == method]
    tiles = zarr.open_group(str(tmp_path / "job.zarr"), mode="r")["committed"].shape[1:]
    assert sorted({(ty, tx) for _, ty, tx, _ in blocks}) == [(y, x) for y in range(tiles[0]) for x in range(tiles[1])]
    assert len(set(blocks)) == len(blocks) and len(blocks) % (tiles[0] * tiles[1]) == 0
    job_video, made = stored(str(tmp_path / "job.zarr")), stored(str(tmp_path / "lazy.zarr"))
    assert np.array_equal(job_video[0], made[0]) and job_video[2] == made[2]


SELECTIONS = {  # windows of: the store, a selection of its spikes (x from 2: not on a byte), a run of windows
    "whole": lambda s, every: lazy.windows(s, every=every),
    "spikes selected": lambda s, every: lazy.windows(s.isel(t=slice(13, 170), y=slice(4, 40), x=slice(2, 58)),
                                                     every=every),
    "windows selected": lambda s, every: lazy.windows(s, every=every, region="8:40,16:48").isel(t=slice(1, 4)),
}


@pytest.mark.parametrize("method, selection", [("tfp", name) for name in SELECTIONS])
def test_windows_of_a_store_are_read_packed_by_each_block_with_the_bytes_of_the_windows_themselves(
        recording, selection, method):
    """The reconstruction of windows of a store (or of one selection) reads each block's tile and halo packed from
    the store in the block's own task: no windows (unpacked) are any task's input. A function between stages makes
    it reconstruct the windows themselves: the same bytes."""
    win = SELECTIONS[selection](lazy.open_spikes(recording), 7 if method == "tfp" else 41)  # lite: 3 or 4 windows

    def made(windows):
        if method == "tfp":
            return lazy.tfp(windows, tile=16, gain=2.0)
        return lazy.reconstruct(windows, method="cscsr", weights="lite", tile=16, gain=2.0)

    direct, between = made(win), made(win.copy(data=win.data.map_blocks(np.copy)))
    graph = direct.data.__dask_graph__()
    stages = {key[0].rsplit("-", 1)[0] for key in graph if isinstance(key, tuple)}
    assert stages == {direct.attrs["method"]}, stages  # its blocks alone, a tile each: the job's tasks
    assert any(key[0].startswith("windows") for key in between.data.__dask_graph__() if isinstance(key, tuple))
    with threaded():
        assert np.array_equal(direct.values, between.values)


def test_the_stages_are_lazy_and_say_what_they_hold(recording):
    spikes = lazy.open_spikes(recording)
    assert spikes.dims == ("t", "y", "x") and spikes.dtype == bool and spikes.shape == (FRAMES, HEIGHT, WIDTH)
    assert spikes.attrs["cfa"] == "rggb" and spikes.attrs["fps"] == FPS and spikes.coords["t"].values[2] == 2 / FPS
    stored_bits = np.unpackbits(zarr.open_group(recording, mode="r")[SPIKES][:], axis=-1, count=WIDTH,
                                bitorder="little")
    with threaded():
        assert np.array_equal(spikes.values, stored_bits.astype(bool))
    win = lazy.windows(spikes, every=20)
    assert win.dims == ("t", "dt", "y", "x") and win.shape == (8, 41, HEIGHT, WIDTH)
    with threaded():
        assert np.array_equal(win[3].values, spikes.values[60:101])  # centred on 20 + 3 * 20
    assert list(win.coords["dt"].values) == list(range(-20, 21))
    # the time overlap is dask's, no copy of the recording in the graph; a block per window's centre
    assert win.data.npartitions == 8 and spikes.data.npartitions == 1
    hr = lazy.tfp(win)
    assert hr.dims == ("t", "y", "x", "rgb") and hr.dtype == np.uint8 and hr.shape == (8, 4 * HEIGHT, 4 * WIDTH, 3)
    assert isinstance(hr.coords["gain"].data, dask.array.Array)  # the automatic exposure, not yet computed


def test_a_million_frames_build_a_small_graph_without_reading_a_chunk(tmp_path):
    """Every chunk of the recording deleted: the graph builds (it reads metadata only), and computing it names
    the frames that are lost."""
    frames, meta = 10**6, SpikeMeta(height=8, width=16, cfa="rggb", fps=20000.0)
    url = str(tmp_path / "long.zarr")
    writer = SpikeStoreWriter(url, meta, frames)
    rows = np.random.default_rng(0).integers(0, 256, (writer.chunk_frames, 8, 2), dtype=np.uint8)
    for start in range(0, frames, writer.chunk_frames):
        writer.write(start, rows[: min(writer.chunk_frames, frames - start)])
    writer.finish(spike_count=0)
    shutil.rmtree(tmp_path / "long.zarr" / SPIKES / "c")
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(url), every=41, start="10s", stop="40s"))
    assert hr.shape == (14634, 32, 64, 3)  # the centres in [200000, 800000), every 41 frames
    # a few tasks per block along t, at most WINDOW_BLOCKS of them however long the recording (here 15 windows each)
    assert hr.data.chunks[0][0] == 15 and len(hr.data.chunks[0]) <= WINDOW_BLOCKS
    assert len(hr.data.__dask_graph__()) < 10 * WINDOW_BLOCKS
    with threaded(), pytest.raises(InputError, match=r"the chunk of frames \d+\.\.\d+ is missing \(lost data\)"):
        hr[0].compute()


def test_a_reconstruction_makes_its_tasks_only_as_something_computes_them(recording, monkeypatch):
    """The blocks' tasks are made on demand (``lazy.video.BlocksLayer``): building a reconstruction, counting and
    listing its keys make none; computing one output frame makes that frame's blocks only (a frame's 12 tiles), and
    gives what computing all of it gives there."""
    from pipeline.jobs.reconstruct_tasks import TileBlocks

    made, graph = [], TileBlocks.graph
    monkeypatch.setattr(TileBlocks, "graph", lambda self, b, k: made.append((b, k)) or graph(self, b, k))
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=7), tile=16)  # 23 frames of 3x4 tiles
    layer = hr.data.__dask_graph__().layers[hr.data.name]
    assert len(layer) == len(list(layer)) == 23 * 12 and made == []
    with threaded():
        frame = hr.isel(t=3).values
        assert sorted(made) == [(3, k) for k in range(12)]  # a block a frame (TFP), a pass a tile
        assert np.array_equal(frame, hr.values[3])


LONG_RUN = """
import resource, sys
import dask, numpy as np
from cscsr import lazy
from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter
frames, url, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
writer = SpikeStoreWriter(url, SpikeMeta(height=8, width=16, cfa="rggb", fps=20000.0, gain=1.0), frames,
                          chunk_frames=50_000)
rows = np.random.default_rng(0).integers(0, 256, (50_000, 8, 2), dtype=np.uint8)
for start in range(0, frames, 50_000):
    writer.write(start, rows[: min(50_000, frames - start)])
writer.finish(spike_count=0)
with dask.config.set(scheduler="threads"):
    counts = lazy.to_video(lazy.tfp(lazy.windows(lazy.open_spikes(url), every=410)), out)
print(counts["frames"], resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024)
"""


def test_to_video_over_a_million_frames_runs_in_the_memory_of_a_tenth_of_them(tmp_path, record_property):
    """TFP of every 410th frame of a recording of 10^5 and of 10^6 spike frames (8x16 LR, chunks of 50,000 frames),
    each in a fresh process: the longer one's peak resident memory is about the shorter one's (measured 1.16x; every
    970th frame: 1.195x, too close to the bound). The longer one has more windows than ``WINDOW_BLOCKS`` (several a
    block: its graph at its bound)."""
    peaks = {}
    for frames in (100_000, 1_000_000):
        done = subprocess.run([sys.executable, "-c", LONG_RUN, str(frames), str(tmp_path / f"{frames}.zarr"),
                               str(tmp_path / f"{frames}-hr.zarr")], capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]
        written, peaks[frames] = map(int, done.stdout.split())
        assert written == len(range(20, frames - 20, 410))  # centres 20, 430, ... (methods.output_centres)
    assert written > WINDOW_BLOCKS  # the longer one: several windows a block
    record_property("peak_rss_mib", peaks)
    print(f"peak RSS: {peaks[100_000]} MiB for 10^5 frames, {peaks[1_000_000]} MiB for 10^6")
    assert peaks[1_000_000] < 1.25 * peaks[100_000], peaks


def test_threads_processes_and_a_killed_worker_give_one_result(recording, tmp_path):
    """The threaded scheduler, a LocalCluster of two worker processes, and the same cluster losing the worker that
    runs one of the tasks (``os._exit``, as a crash): the same bytes."""
    flag = tmp_path / "killed-once"

    def crashing_tfp_like(window):  # a worker dies the first time any worker runs this block
        if window.shape[1] == 20 and not flag.exists():
            flag.touch()
            os._exit(1)
        return np.repeat(np.repeat(np.uint8(window.sum(axis=0) * 6), 4, 0), 4, 1)[..., None].repeat(3, -1)

    def hr():
        return lazy.apply(lazy.windows(lazy.open_spikes(recording), every=41), crashing_tfp_like, scale=4, halo=2,
                          tile=16)  # 4 output frames of 3x4 tiles: 48 blocks

    flag.touch()  # no crash in the reference run
    with threaded():
        lazy.to_video(hr(), str(tmp_path / "threads.zarr"))
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as local, \
            Client(local):
        lazy.to_video(hr(), str(tmp_path / "processes.zarr"))
        flag.unlink()
        lazy.to_video(hr(), str(tmp_path / "killed.zarr"))
    assert flag.exists()  # a worker did die
    reference = stored(str(tmp_path / "threads.zarr"))
    for other in ("processes", "killed"):
        video, frames, attrs = stored(str(tmp_path / f"{other}.zarr"))
        assert np.array_equal(video, reference[0]) and attrs["state"] == "complete"


def test_a_failed_to_video_resumes_to_the_bytes_of_one_run(recording, tmp_path, monkeypatch):
    """Written 4 blocks a round (a block per output frame and tile: 3 rows of 4 tiles): the first round (frame 0's
    first row of tiles) is committed, the second (its second row) fails."""
    monkeypatch.setattr(lazy_written, "BLOCKS_AT_ONCE", 4)
    failing = tmp_path / "fail"

    def grey(window):  # refuses the windows of the frame's second tile row (32 rows with its halo) while flagged
        if failing.exists() and window.shape[1] == 32:
            raise RuntimeError("disk full")
        return np.repeat(np.repeat(np.uint8(window.mean(axis=0) * 255), 4, 0), 4, 1)[..., None].repeat(3, -1)

    hr = lazy.apply(lazy.windows(lazy.open_spikes(recording), every=7), grey, scale=4, halo=8, tile=16)
    with threaded():
        lazy.to_video(hr, str(tmp_path / "whole.zarr"))
        failing.touch()
        with pytest.raises(RuntimeError, match="disk full"):
            lazy.to_video(hr, str(tmp_path / "resumed.zarr"))
        assert zarr.open_group(str(tmp_path / "resumed.zarr"), mode="r").attrs["state"] == "writing"
        failing.unlink()
        counts = lazy.to_video(hr, str(tmp_path / "resumed.zarr"), resume=True)
    assert counts["tasks_skipped"] == 4 and counts["tasks_run"] == 23 * 12 - 4  # the job's tasks: a frame's tile
    assert np.array_equal(stored(str(tmp_path / "resumed.zarr"))[0], stored(str(tmp_path / "whole.zarr"))[0])
    with pytest.raises(InputError, match="other parameters"):  # another method's output is not resumed
        lazy.to_video(lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=7), tile=16),
                      str(tmp_path / "resumed.zarr"), resume=True)


def test_on_a_cluster_every_block_is_tried_and_the_failed_ones_are_named_by_their_output_frames(recording, tmp_path):
    """As the job does: a block that fails does not stop the others; the error names the output frames lost (each
    frame's second row of tiles here) and the cause once; a resume runs only those blocks, to the bytes of one run."""
    failing = tmp_path / "fail"

    def grey(window):  # refuses the windows of the frame's second tile row (32 rows with its halo) while flagged
        if failing.exists() and window.shape[1] == 32:
            raise RuntimeError("disk full")
        return np.repeat(np.repeat(np.uint8(window.mean(axis=0) * 255), 4, 0), 4, 1)[..., None].repeat(3, -1)

    def hr():
        return lazy.apply(lazy.windows(lazy.open_spikes(recording), every=20), grey, scale=4, halo=8, tile=16)

    with threaded():
        lazy.to_video(hr(), str(tmp_path / "whole.zarr"))
    out = str(tmp_path / "resumed.zarr")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as local, \
            Client(local):
        failing.touch()
        with pytest.raises(RuntimeError) as caught:
            lazy.to_video(hr(), out)
        assert str(caught.value).startswith("8 of 8 output frames failed (frames 0, 1, 2, "), caught.value
        assert str(caught.value).count("disk full") == 1 and "to_video(..., resume=True)" in str(caught.value)
        assert zarr.open_group(out, mode="r").attrs["state"] == "writing"
        failing.unlink()
        counts = lazy.to_video(hr(), out, resume=True)
    assert counts == {"frames": 8, "tasks_run": 8 * 4, "tasks_skipped": 8 * 8}  # the second row's 4 tiles
    assert np.array_equal(stored(out)[0], stored(str(tmp_path / "whole.zarr"))[0])


def test_on_a_cluster_tasks_a_scheduler_restart_drops_are_submitted_again(recording, tmp_path):
    """``to_video`` of a reconstruction read from a store runs its blocks on a cluster as the job does
    (``reconstruct_tasks.run_blocks``: the executor's bounded window): the scheduler restarted mid-call (every
    future cancelled, the worker process restarted by its nanny) drops the tasks in flight, which are submitted
    again, and the store is the bytes of one run (rounds of ``client.compute`` reported those frames lost). The
    writes are held after the third (``pipeline.compute.hold``), so the restart lands while work remains."""
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=20), tile=16)  # 8 output frames of 3x4 tiles
    with threaded():
        lazy.to_video(hr, str(tmp_path / "whole.zarr"))
    out = str(tmp_path / "restarted.zarr")
    counts, restarted = to_video_restarted(hr, out, 3, tmp_path)
    assert restarted and restarted[0] < 8 * 4 and counts["tasks_skipped"] == 0  # restarted with work remaining
    video, frames, attrs = stored(out)
    assert np.array_equal(video, stored(str(tmp_path / "whole.zarr"))[0]) and attrs["state"] == "complete"


def test_a_scheduler_restart_loses_only_the_round_in_flight_of_any_other_hr(recording, tmp_path, monkeypatch):
    """Any other ``hr`` (a selection of a store's TFP here) runs on a client in rounds (``executor.computed``), what
    later rounds read carried over (windows, the automatic exposure). A scheduler restart mid-call cancels what is
    carried: it is made again, so only the round in flight is lost (every later round was: 12 of 84 tiles
    committed), and a resume writes the bytes of one run."""
    monkeypatch.setattr(lazy_written, "BLOCKS_AT_ONCE", 8)
    hr = lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=20), tile=16).isel(t=slice(1, 8))  # 7 x 12 tiles
    with threaded():
        lazy.to_video(hr, str(tmp_path / "whole.zarr"))
    out = str(tmp_path / "restarted.zarr")
    error, restarted = to_video_restarted(hr, out, 12, tmp_path)
    assert isinstance(error, RuntimeError) and "cluster fault: the task was cancelled" in str(error)  # in flight
    assert restarted and committed_tiles(out) >= 84 - 8, (restarted, committed_tiles(out))
    with threaded():
        counts = lazy.to_video(hr, out, resume=True)
    assert counts["tasks_run"] <= 8 and counts["tasks_run"] + counts["tasks_skipped"] == 84
    assert np.array_equal(stored(out)[0], stored(str(tmp_path / "whole.zarr"))[0])


def to_video_restarted(hr, out: str, tiles: int, tmp_path):
    """``lazy.to_video(hr, out)`` on a cluster of one worker process whose scheduler is restarted once ``tiles`` tiles
    are committed (its writes held after them: ``pipeline.compute.hold``) -> (the counts, or the error it raised; the
    tiles committed when it restarted)."""
    from pipeline.compute.hold import hold_environment

    release, restarted = tmp_path / "release", []
    held = hold_environment(tiles, release)  # set by the nanny in its worker (forked from a server that started
    # before this test: the test's own environment would not reach it, and the writes ran through unheld)

    def restart_when_held(client):
        try:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and committed_tiles(out) < tiles:
                time.sleep(0.05)
            client.restart()
            restarted.append(committed_tiles(out))
        finally:  # whatever happened, the held writes go on
            release.touch()

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0", env=held) as local, \
            Client(local) as client:
        restarter = threading.Thread(target=restart_when_held, args=(client,))
        restarter.start()
        try:
            outcome = lazy.to_video(hr, out)
        except RuntimeError as error:
            outcome = error
        finally:
            restarter.join()
    return outcome, restarted


def committed_tiles(url: str) -> int:
    """Tiles committed in the video store at ``url``; 0 while it does not exist or is being created."""
    try:
        return int(np.asarray(zarr.open_group(url, mode="r")["committed"][:]).sum())
    except (FileNotFoundError, KeyError, ValueError):  # not there yet, or its metadata half written
        return 0


def test_a_users_function_between_stages_and_as_a_method_with_a_halo(recording, tmp_path):
    win = lazy.windows(lazy.open_spikes(recording), every=20)
    hr = lazy.tfp(win, tile=16)
    inverted = hr.copy(data=hr.data.map_blocks(lambda block: 255 - block))
    with threaded():
        lazy.to_video(inverted, str(tmp_path / "inverted.zarr"))
        assert np.array_equal(stored(str(tmp_path / "inverted.zarr"))[0], 255 - hr.values)

    def box_rate(window):  # a 5x5 box mean of the firing rate: needs 2 pixels of context on every side
        rate = np.pad(window.mean(axis=0), 2, mode="edge")
        box = sum(rate[dy : dy + rate.shape[0] - 4, dx : dx + rate.shape[1] - 4] for dy in range(5) for dx in range(5))
        return np.repeat(np.repeat(np.uint8(np.round(box / 25 * 255)), 4, 0), 4, 1)[..., None].repeat(3, -1)

    with threaded():
        tiled = lazy.apply(win, box_rate, scale=4, halo=2, tile=16).values
        whole = np.stack([box_rate(w) for w in win.values])
    assert np.array_equal(tiled, whole)  # the halo makes tiles agree with the whole frame
    with threaded():
        no_halo = lazy.apply(win, box_rate, scale=4, halo=0, tile=16).values
    assert not np.array_equal(no_halo, whole)  # without it, tile edges differ: the halo is what was tested


def test_the_network_runs_on_gpu_workers_only(recording, tmp_path):
    with cluster(cpu=None, gpu={GPU: 1}) as client:
        hr = lazy.reconstruct(lazy.windows(lazy.open_spikes(recording), every=100), method="cscsr", weights="lite",
                              tile=32)
        layers = [layer for layer in hr.data.__dask_graph__().layers.values() if layer.annotations]
        assert layers and all(layer.annotations == {"resources": {GPU: GPU_SHARE}} for layer in layers)
        with get_task_stream(client) as stream:
            lazy.to_video(hr, str(tmp_path / "gpu.zarr"))
        workers = names(client)
        ran = [workers[r["worker"]] for r in stream.data if key_split(r["key"]) in ("cscsr", "pass-cscsr")]
    assert ran == ["gpu"]  # a block of 2 output frames: its 2x2 tiles in one pass, read, reconstructed and written
    written = zarr.open_group(str(tmp_path / "gpu.zarr"), mode="r")
    assert written.attrs["weights"].endswith("cscsr-lite.safetensors") and written["committed"][:].all()


def test_bad_input_is_the_jobs_one_line_before_anything_is_written(recording, tmp_path):
    spikes = lazy.open_spikes(recording)
    refusals = {
        "must have dims": lambda: lazy.windows(spikes.transpose("y", "t", "x")),
        "length=301 is longer than the recording": lambda: lazy.windows(spikes, length=301),  # Python words
        "length must be a positive odd number": lambda: lazy.windows(spikes, length=40),
        r"region=0:48,0:72 is outside the recording \(48x64": lambda: lazy.windows(spikes, region="0:48,0:72"),
        "start=300 is outside the recording": lambda: lazy.windows(spikes, start=300),
        "tile must be a positive multiple of 8": lambda: lazy.tfp(lazy.windows(spikes), tile=12),
        "unknown method 'tfx'": lambda: lazy.reconstruct(lazy.windows(spikes), method="tfx"),
        "more than the windows keep": lambda: lazy.apply(lazy.windows(spikes, region="16:32,16:32", margin=0),
                                                          lambda w: w, scale=4, halo=8),
        "hr must be": lambda: lazy.to_video(spikes, str(tmp_path / "out.zarr")),
        "halo=3 is odd: the rggb colour pattern": lambda: lazy.apply(lazy.windows(spikes), lambda w: w, scale=4,
                                                                       halo=3),
    }
    for message, call in refusals.items():
        with pytest.raises(InputError, match=message) as refused:
            call()
        assert "\n" not in str(refused.value)
    with pytest.raises(InputTypeError, match="url must be"):
        lazy.open_spikes(None)
    with pytest.raises(InputTypeError, match="progress must be True or False, got 'no'"):
        lazy.to_video(lazy.tfp(lazy.windows(spikes)), str(tmp_path / "out.zarr"), progress="no")
    group = zarr.open_group(recording, mode="r+")
    group.attrs["state"] = "writing"
    try:
        with pytest.raises(InputError, match="is incomplete"):
            lazy.open_spikes(recording)
    finally:
        group.attrs["state"] = "complete"
    assert not (tmp_path / "out.zarr").exists()


def test_nothing_is_written_over_a_store_its_graph_reads_and_a_replaced_store_is_not_read(recording, tmp_path):
    """``to_video(open_video(url), url, overwrite=True)`` set the store aside, then read the new, empty one: an
    all-black video marked complete, the original gone. ``to_spikes`` over its own input, once the ``store``
    attribute was dropped, failed half-way. The stores a graph reads are found in the graph itself: refused in one
    line, nothing touched. And a video store replaced after ``open_video`` (another method at the same path) was
    read as the new pixels under the old attributes: refused when read."""
    video = str(tmp_path / "video.zarr")
    with threaded():
        lazy.to_video(lazy.tfp(lazy.windows(lazy.open_spikes(recording), every=50), tile=16), video)
        before = stored(video)
        hr = lazy.open_video(video)
        hr.attrs.clear()
        with pytest.raises(InputError, match=f"output {video} is the same as input {video}"):
            lazy.to_video(hr, video, overwrite=True)
        copy = str(tmp_path / "copy.zarr")
        shutil.copytree(recording, copy)
        spikes = lazy.open_spikes(copy)
        spikes.attrs.pop("store")
        with pytest.raises(InputError, match=f"output {copy} is the same as input {copy}"):
            lazy.to_spikes(spikes, copy, overwrite=True)
        assert sorted(os.listdir(tmp_path)) == ["copy.zarr", "video.zarr"]
        assert all(np.array_equal(a, b) for a, b in zip(stored(video)[:2], before[:2]))
        np.testing.assert_array_equal(lazy.open_spikes(copy).values, lazy.open_spikes(recording).values)
        opened = lazy.open_video(video)
        lazy.to_video(lazy.tfi(lazy.windows(lazy.open_spikes(recording), every=50), tile=16), video, overwrite=True)
        with pytest.raises(InputError, match="is not the one this graph was opened on"):
            opened.values


def test_weights_may_be_a_path_object(recording, tmp_path):
    from cscsr.weights.weights_io import default_weights

    shipped = default_weights("lite")
    win = lazy.windows(lazy.open_spikes(recording), every=100)
    hr = lazy.reconstruct(win, weights=pathlib.Path(shipped), tile=32)
    assert hr.attrs["weights"] == lazy.reconstruct(win, weights=str(shipped), tile=32).attrs["weights"]


def test_the_margin_holds_every_built_in_halo():
    from cscsr.inference.reconstructor import HALO
    from stages.reconstruction.methods import CLASSIC

    assert MARGIN >= max(HALO, *(method.halo for method in CLASSIC.values()))


def test_an_exposure_that_failed_on_a_client_is_computed_afresh_by_the_next_call(recording, tmp_path):
    """A store that records no gain is exposed by one task of a fixed key (``auto-gain``), shared by ``to_video``
    and the ``reconstruct`` job. One that failed (its spikes unreadable) was held by the error's traceback, and the
    cluster gave every later call on that client the stale error, the spikes long restored."""
    store = str(tmp_path / "recording.zarr")
    shutil.copytree(recording, store)
    assert "gain" not in zarr.open_group(store, mode="r").attrs  # exposed automatically
    chunks = os.path.join(store, SPIKES, "c")
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as local, \
            Client(local) as client:
        shutil.move(chunks, chunks + ".away")
        with pytest.raises(Exception, match="missing") as caught:  # kept, as a REPL keeps its last error
            lazy.to_video(lazy.tfp(lazy.windows(lazy.open_spikes(store), every=20)), str(tmp_path / "a.zarr"))
        with pytest.raises(Exception, match="missing") as caught_too:
            reconstruct(store, str(tmp_path / "b.zarr"), ReconstructOptions(every=20), client=client, progress=False)
        shutil.move(chunks + ".away", chunks)
        lazy.to_video(lazy.tfp(lazy.windows(lazy.open_spikes(store), every=20)), str(tmp_path / "c.zarr"))
        reconstruct(store, str(tmp_path / "d.zarr"), ReconstructOptions(every=20), client=client, progress=False)
        assert caught.value is not None and caught_too.value is not None
    assert np.array_equal(stored(str(tmp_path / "c.zarr"))[0], stored(str(tmp_path / "d.zarr"))[0])
