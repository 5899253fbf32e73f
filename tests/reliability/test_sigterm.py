"""SIGTERM (``docker stop``, systemd, Kubernetes, ``kill``) during a command (issue #48, item 4).

It ended the process at once: a PNG export left a folder of a few frames that a rerun called "already exists",
the mp4 encoder kept running orphaned, and its temporary mp4 was left behind. SIGTERM now does what Ctrl-C does
(``pipeline.compute.stopping``): the clean-up runs, the command says ``error: terminated (SIGTERM)`` and exits 143.

Each test starts ``cscsr`` as a user does, with a ``TMPDIR`` of its own, waits until it is working (its output
appearing), sends SIGTERM once and checks: the process ends within seconds, non-zero, with that one line; no
process it started (recorded from the process table while it ran) is left; ``TMPDIR`` holds nothing but Dask's
shared lock files (what a finished run leaves too); beside OUT nothing reads as complete, and the same command
run again without ``--overwrite`` succeeds (``--resume`` for ``reconstruct``, whose unfinished store is kept for
it).
"""

import os
import signal
import subprocess
import time

import numpy as np
import psutil
import pytest
import zarr

from tests.conftest import CSCSR, committed_tasks

STOP_SECONDS = 20  # from SIGTERM to the exit
DASK_LOCKS = {"dask-scratch-space", "dask-scratch-space/global.lock", "dask-scratch-space/purge.lock"}


Stopped = tuple[subprocess.CompletedProcess, float]  # the command's result, seconds from the signal to its exit


def terminated_mid_work(args: list, ready, *, cwd, tmpdir, ctrl_c: bool = False) -> Stopped:
    """Run ``cscsr -q ARGS`` in ``cwd`` with ``TMPDIR=tmpdir``, SIGTERM it once ``ready()`` holds (``ctrl_c``: SIGINT
    to its whole process group, as a terminal's Ctrl-C); -> (its result, seconds from the signal to its exit), once
    every process it started (its descendants, sampled while it ran) is gone."""
    process = subprocess.Popen([CSCSR, "-q", *map(str, args)], cwd=cwd, env={**os.environ, "TMPDIR": str(tmpdir)},
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        started, descendants = psutil.Process(process.pid), set()
        deadline = time.monotonic() + 120
        while not ready():
            assert process.poll() is None, f"it ended before it was stopped: {process.communicate()}"
            assert time.monotonic() < deadline, "it never got going"
            descendants |= set(_descendants(started))
            time.sleep(0.05)
        descendants |= set(_descendants(started))
        if ctrl_c:
            os.killpg(process.pid, signal.SIGINT)
        else:
            process.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        stdout, stderr = process.communicate(timeout=60)
        seconds = time.monotonic() - sent
    finally:  # a failed test leaves nothing running
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert_all_gone(descendants)
    return subprocess.CompletedProcess(args, process.returncode, stdout, stderr), seconds


def _descendants(process: psutil.Process) -> list[psutil.Process]:
    try:
        return process.children(recursive=True)
    except psutil.Error:  # it is exiting
        return []


def assert_all_gone(processes, seconds: float = 10) -> None:
    """None of ``processes`` is alive (a zombie is dead, waiting to be reaped) within ``seconds``."""
    def alive() -> list[str]:
        found = []
        for process in processes:
            try:
                if process.is_running() and process.status() != psutil.STATUS_ZOMBIE:
                    found.append(f"{process.pid} {' '.join(process.cmdline())[:200]}")
            except psutil.Error:
                pass
        return found

    deadline = time.monotonic() + seconds
    while (left := alive()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not left, f"processes it started are still running: {left}"


def assert_stopped(result, seconds: float, *, status: int = 143, line: str = "error: terminated (SIGTERM)") -> None:
    assert result.returncode == status, (result.returncode, result.stderr[-3000:])
    assert result.stderr.strip() == line, result.stderr[-3000:]
    assert seconds < STOP_SECONDS, seconds


def temporary_files(tmpdir) -> set[str]:
    """What is under ``tmpdir``, relative paths, but Dask's shared lock files."""
    found = {os.path.relpath(os.path.join(folder, name), tmpdir)
             for folder, folders, files in os.walk(tmpdir) for name in folders + files}
    return found - DASK_LOCKS


@pytest.fixture
def tmpdir_of_its_own(tmp_path):
    folder = tmp_path / "tmp"
    folder.mkdir()
    return folder


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> str:
    """A complete video store of 120 frames of 256x256 noise: a few seconds to export."""
    from pipeline.stores.video_store import TileWriter, create_video_store

    path = str(tmp_path_factory.mktemp("sigterm") / "v.zarr")
    create_video_store(path, centres=list(range(20, 1220, 10)), hr_size=(256, 256), tile_hr=(256, 256), tiles=(1, 1),
                       attrs={"method": "tfp", "every": 10, "window": 41}, fps=2000.0)
    writer, rng = TileWriter(path), np.random.default_rng(0)
    for index in range(120):
        writer.write(index, (0, 0), (0, 0), rng.integers(0, 256, (256, 256, 3), np.uint8))
    zarr.open_group(path, mode="r+").attrs["state"] = "complete"
    return path


@pytest.fixture(scope="module")
def spikes(tmp_path_factory) -> str:
    """A 1000-frame 64x64 RGGB spike store: about 200 reconstruction tasks at --every 5."""
    from typer.testing import CliRunner

    from pipeline.cli import app

    folder = tmp_path_factory.mktemp("sigterm-spikes")
    np.save(folder / "c.npy", (np.random.default_rng(0).random((1000, 64, 64)) < 0.2).astype(np.uint8))
    result = CliRunner().invoke(app, ["ingest", str(folder / "c.npy"), str(folder / "s.zarr"), "--cfa", "rggb"])
    assert result.exit_code == 0, result.output
    return str(folder / "s.zarr")


def png_count(folder) -> int:
    return len([name for name in os.listdir(folder) if name.endswith(".png")]) if os.path.isdir(folder) else 0


@pytest.mark.parametrize("dest", ["out.mp4", "frames"])
def test_sigterm_during_export_leaves_no_encoder_no_temporary_mp4_and_no_partial_output(video, tmp_path,
                                                                                      tmpdir_of_its_own, dest):
    work = tmp_path / "work"
    work.mkdir()
    if dest == "frames":  # a few frames written
        ready = lambda: png_count(work / dest) >= 3  # noqa: E731
    else:  # the encoder is writing its temporary mp4
        ready = lambda: any("video.mp4" in name for name in temporary_files(tmpdir_of_its_own))  # noqa: E731
    result, seconds = terminated_mid_work(["export", video, dest], ready, cwd=work, tmpdir=tmpdir_of_its_own)
    assert_stopped(result, seconds)
    assert os.listdir(work) == []  # no output, no hidden claim or copy beside it
    assert temporary_files(tmpdir_of_its_own) == set()

    again = subprocess.run([CSCSR, "-q", "export", video, dest], cwd=work, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr  # not "already exists"
    assert png_count(work / dest) == 120 if dest == "frames" else os.path.getsize(work / dest) > 0


@pytest.mark.parametrize("ctrl_c", [False, True], ids=["sigterm", "ctrl-c"])
def test_sigterm_during_reconstruct_stops_its_segment_and_cluster_and_resume_finishes(spikes, tmp_path,
                                                                                      tmpdir_of_its_own, ctrl_c):
    """Ctrl-C too: every process of the job gets SIGINT, and the workers leave their stopping to their cluster
    (each printed a traceback of its own)."""
    out = tmp_path / "out.zarr"
    args = ["reconstruct", spikes, out, "--workers", 2, "--every", 5]
    result, seconds = terminated_mid_work(args, lambda: committed_tasks(out) >= 3, cwd=tmp_path,
                                          tmpdir=tmpdir_of_its_own, ctrl_c=ctrl_c)
    if ctrl_c:
        assert_stopped(result, seconds, status=130, line="error: interrupted")
    else:
        assert_stopped(result, seconds)
    assert zarr.open_group(str(out), mode="r").attrs["state"] == "writing"  # kept for --resume, never "complete"
    assert sorted(os.listdir(tmp_path)) == ["out.zarr", "tmp"]  # no claim left beside it
    assert temporary_files(tmpdir_of_its_own) == set()  # the workers' folders went with them

    again = subprocess.run([CSCSR, "-q", *map(str, args), "--resume"], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert zarr.open_group(str(out), mode="r").attrs["state"] == "complete"


def test_sigterm_during_simulate_closes_its_cluster_and_removes_the_store(tmp_path, tmpdir_of_its_own):
    import imageio.v3 as iio

    still = tmp_path / "still.png"
    iio.imwrite(still, np.random.default_rng(0).integers(0, 256, (64, 64, 3), np.uint8))
    work = tmp_path / "work"
    work.mkdir()
    args = ["simulate", still, "sim.zarr", "--motion", "random", "--frames", 2000, "--chunk-frames", 50, "--workers", 2]

    def chunks_written() -> int:
        return sum(len(files) for _, _, files in os.walk(work / "sim.zarr" / "spikes"))

    result, seconds = terminated_mid_work(args, lambda: chunks_written() >= 3, cwd=work, tmpdir=tmpdir_of_its_own)
    assert_stopped(result, seconds)
    assert os.listdir(work) == []  # the unfinished store removed, as on Ctrl-C
    assert temporary_files(tmpdir_of_its_own) == set()

    again = subprocess.run([CSCSR, "-q", *map(str, args)], cwd=work, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
