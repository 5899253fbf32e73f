"""The commands the compose file runs, for real: ``dask scheduler`` and two ``dask worker`` processes on
127.0.0.1, with ``cscsr reconstruct --scheduler`` and ``cscsr watch --once --scheduler`` submitting to them."""

import os
import re
import subprocess
import sys
import time

import imageio.v3 as iio
import pytest
import zarr

from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from pipeline.jobs.simulate import SimulateOptions, simulate
from tests.test_simulate import chunk_files, picture
from tests.test_watch import settled

BIN = os.path.dirname(sys.executable)


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """tcp://127.0.0.1:PORT of a scheduler with two single-threaded workers, as in docker-compose.yml.

    The scheduler picks its own free port (``--port 0``) and writes its address to a scheduler
    file that the workers and the test read: no port is chosen ahead and then lost to a race.
    """
    import json

    from distributed import Client

    address_file = tmp_path_factory.mktemp("scheduler") / "scheduler.json"
    elsewhere = tmp_path_factory.mktemp("workers")  # the workers' working folder is not the client's
    processes = [subprocess.Popen([f"{BIN}/dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                                   "--scheduler-file", str(address_file), "--dashboard-address", ":0", "--no-show"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    processes += [subprocess.Popen([f"{BIN}/dask", "worker", "--scheduler-file", str(address_file), "--nworkers", "1",
                                    "--nthreads", "1", "--no-dashboard"], stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL, cwd=elsewhere)
                  for _ in range(2)]
    try:
        deadline = time.time() + 120
        while True:
            try:
                address = json.loads(address_file.read_text())["address"]
                with Client(address, timeout=5) as client:
                    client.wait_for_workers(2, timeout=max(deadline - time.time(), 1))
                    break
            except (OSError, TimeoutError, ValueError, KeyError):
                if time.time() > deadline:
                    raise
                time.sleep(0.5)
        yield address
    finally:  # the workers first, while their scheduler answers (else each waits on it for seconds), then it
        for group in (processes[1:], processes[:1]):
            for process in group:
                process.terminate()
            for process in group:
                process.wait(timeout=30)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> str:
    folder = tmp_path_factory.mktemp("cluster")
    iio.imwrite(folder / "scene.png", picture("chelsea", 128))
    store = str(folder / "inbox" / "scene.zarr")
    simulate(str(folder / "scene.png"), store, SimulateOptions(scale=4, frames=130, motion="random"), workers=1,
             progress=False)
    settled(folder / "inbox")
    return store


def test_reconstruct_and_watch_on_a_real_scheduler(scheduler, recording, tmp_path):
    local = str(tmp_path / "local.zarr")
    reconstruct(recording, local, ReconstructOptions(method="tfi", every=10, tile=16), workers=1, progress=False)

    # in segments of 12 tasks (of 36), each on its own fresh process and cluster: the same bytes
    segmented = str(tmp_path / "segmented.zarr")
    counts = reconstruct(recording, segmented, ReconstructOptions(method="tfi", every=10, tile=16, segment_tasks=12),
                         workers=1, progress=False)
    assert counts["tasks_run"] == 36 and chunk_files(segmented) == chunk_files(local)

    # paths relative to the client's folder: the workers, started in another, read and write where they point
    remote = str(tmp_path / "remote.zarr")
    run = subprocess.run([f"{BIN}/cscsr", "reconstruct", os.path.relpath(recording, tmp_path), "remote.zarr",
                          "--method", "tfi", "--every", "10", "--tile", "16", "--scheduler", scheduler],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert chunk_files(remote) == chunk_files(local)  # the same bytes as on a local cluster
    assert "dashboard" not in run.stdout and re.search(r"^dashboard: http://\S+/status$", run.stderr, re.MULTILINE)
    scene = os.path.join(os.path.dirname(os.path.dirname(recording)), "scene.png")
    run = subprocess.run([f"{BIN}/cscsr", "simulate", os.path.relpath(scene, tmp_path), "again.zarr", "--scale", "4",
                          "--frames", "130", "--motion", "random", "--scheduler", scheduler],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert chunk_files(str(tmp_path / "again.zarr")) == chunk_files(recording)  # the same spikes and truth

    outbox = tmp_path / "outbox"
    inbox = os.path.dirname(recording)
    run = subprocess.run([f"{BIN}/cscsr", "watch", inbox, str(outbox), "--once", "--method", "tfi", "--every", "10",
                          "--tile", "16", "--scheduler", scheduler], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "INFO cscsr.watch: scene: done in" in run.stderr  # log lines go to stderr
    video = zarr.open_group(str(outbox / "scene.zarr"), mode="r")
    assert video.attrs["state"] == "complete" and video["video"].shape == (9, 128, 128, 3)
    assert chunk_files(str(outbox / "scene.zarr")) == chunk_files(local)
    assert (outbox / "scene.mp4").stat().st_size > 1000


def test_the_lazy_graphs_on_a_real_scheduler_read_and_write_relative_paths_where_the_client_means(
        scheduler, recording, tmp_path, monkeypatch):
    """A lazy graph's tasks open its stores in the workers, started in another folder: a path relative to the
    client's folder is made absolute as the graph is built, so they read and write there (they used to look in
    their own folder: no group found), and the video is the job's."""
    from distributed import Client

    from cscsr import lazy

    local = str(tmp_path / "local.zarr")
    reconstruct(recording, local, ReconstructOptions(method="tfi", every=10, tile=16), workers=1, progress=False)
    monkeypatch.chdir(tmp_path)
    with Client(scheduler, timeout=30):
        hr = lazy.reconstruct(lazy.windows(lazy.open_spikes(os.path.relpath(recording, tmp_path)), every=10),
                              method="tfi", tile=16)
        lazy.to_video(hr, "lazy.zarr")
    video = zarr.open_group(str(tmp_path / "lazy.zarr"), mode="r")["video"][:]
    assert (video == zarr.open_group(local, mode="r")["video"][:]).all() and video.shape == (9, 128, 128, 3)
