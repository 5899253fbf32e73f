"""Parallel, resumable ingest and its dry run (#36): the same bytes as the one-process ingest whatever the
workers, a killed ingest resumed to the bytes of an uninterrupted one, another capture refused on resume,
a plan that creates nothing, and bad input refused in one line."""

import json
import os
import shutil
import signal
import time

import numpy as np
import pytest

from cscsr import ingest as api_ingest
from pipeline.stores import spike_store
from pipeline.compute.hold import hold_environment
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.stores.spike_store import open_spike_store
from stages.errors import InputError, InputTypeError
from tests.conftest import CSCSR, committed_tasks, kill_mid_job, write_dat


def store_files(path) -> dict[str, bytes]:
    """Every file of a store by its path inside it: chunks, metadata, the commit record."""
    return {os.path.relpath(os.path.join(folder, name), path): open(os.path.join(folder, name), "rb").read()
            for folder, _, names in os.walk(path) for name in names}


def tree(path) -> dict[str, bytes]:
    """Every file under ``path`` (what a refused command must leave as it was)."""
    return store_files(path)


def capture(path, frames: int, height: int, stored_width: int, *, flip: bool, seed: int = 0) -> np.ndarray:
    """A .dat of random sparse spikes, rows ``stored_width`` wide (image and header columns); -> the bits."""
    bits = (np.random.default_rng(seed).random((frames, height, stored_width)) < 0.15).astype(np.uint8)
    write_dat(path, bits, flip=flip)
    return bits


def random_dat(path, frames: int, frame_bytes: int, seed: int = 0) -> None:
    """A large .dat quickly: random bytes, one bit in eight set on average."""
    rng = np.random.default_rng(seed)
    draw = lambda: rng.integers(0, 256, frames * frame_bytes, dtype=np.uint8)  # noqa: E731
    (draw() & draw() & draw()).tofile(path)


@pytest.fixture
def small_chunks(monkeypatch):
    """Chunks of 160 packed bytes (5 frames of 16x16) for the small captures here: the store is laid out by
    the job's own process, whatever the workers."""
    monkeypatch.setattr(spike_store, "TARGET_CHUNK_BYTES", 160)


@pytest.mark.parametrize("width,head,flip", [(40, 8, True), (20, 4, True), (48, 0, False)])
def test_parallel_ingest_equals_one_process(client, tmp_path, small_chunks, width, head, flip):
    """``.dat`` with header columns (byte-aligned and not) and flip: every file of the store (chunks, the commit
    record, metadata and attributes) identical, on a 2-worker cluster."""
    bits = capture(tmp_path / "c.dat", 203, 16, width + head, flip=flip)
    options = IngestOptions(16, width, cfa="rggb", flip=flip, head_columns=head, task_frames=12)  # 3 chunks a task
    one = ingest(str(tmp_path / "c.dat"), str(tmp_path / "one.zarr"), options, progress=False)
    two = ingest(str(tmp_path / "c.dat"), str(tmp_path / "two.zarr"), options, progress=False, client=client)
    assert one == two and one["state"] == "complete" and one["spike_count"] == int(bits[:, :, :width].sum())
    store = open_spike_store(str(tmp_path / "two.zarr"))
    assert store.spikes.chunks[0] < 12 and store.group["committed"].shape == (17,)  # 203 frames, 12 a task
    assert store.group["committed"][:].sum() == one["spike_count"]
    assert store_files(tmp_path / "one.zarr") == store_files(tmp_path / "two.zarr")


def test_dask_scheduler_address_alone_runs_the_ingest_on_that_cluster(cli, client, tmp_path, small_chunks, monkeypatch):
    """As every other job: a scheduler named only by ``DASK_SCHEDULER_ADDRESS`` (what ``deploy/slurm.py`` sets) runs
    the ingest's tasks on its cluster, with the bytes of a one-process ingest."""
    capture(tmp_path / "c.dat", 100, 16, 16, flip=False)
    args = ["--height", "16", "--width", "16", "--task-frames", "12"]
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    assert cli("-q", "ingest", tmp_path / "c.dat", tmp_path / "one.zarr", *args).exit_code == 0

    def ingest_tasks(dask_scheduler) -> float:  # the seconds its ingest tasks ran (a prefix outlives its tasks)
        return sum(sum(prefix.all_durations.values()) for name, prefix in dask_scheduler.task_prefixes.items()
                   if name == "to-spikes")  # the name of lazy.to_spikes's writes, which ingest's tasks share

    before = client.run_on_scheduler(ingest_tasks)
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", client.scheduler.address)
    plan = json.loads(cli("ingest", tmp_path / "c.dat", tmp_path / "two.zarr", *args, "--dry-run", "--json").stdout)
    assert plan["runs_on"] == f"scheduler {client.scheduler.address}"
    assert cli("-q", "ingest", tmp_path / "c.dat", tmp_path / "two.zarr", *args).exit_code == 0
    assert client.run_on_scheduler(ingest_tasks) > before, "no ingest task ran on the cluster"
    assert store_files(tmp_path / "one.zarr") == store_files(tmp_path / "two.zarr")


def test_parallel_ingest_of_a_npy_on_a_local_cluster(cli, tmp_path, small_chunks):
    """``--workers 2`` (a local cluster of its own) on a ``.npy``: the one-process bytes."""
    bits = (np.random.default_rng(5).random((97, 16, 24)) < 0.2).astype(np.uint8)
    np.save(tmp_path / "c.npy", bits)
    args = ("--cfa", "rggb", "--flip", "--task-frames", "10")
    assert cli("-q", "ingest", tmp_path / "c.npy", tmp_path / "one.zarr", *args).exit_code == 0
    result = cli("-q", "ingest", tmp_path / "c.npy", tmp_path / "two.zarr", *args, "--workers", "2")
    assert result.exit_code == 0, result.stderr
    assert "(9 tasks run, 0 already committed)" in result.stdout  # chunks of 3 frames, tasks of 12
    assert store_files(tmp_path / "one.zarr") == store_files(tmp_path / "two.zarr")


def test_the_api_and_the_cli_write_the_same_bytes(cli, tmp_path):
    """``fps=20000`` from Python and ``--fps 20000`` on the command line record the same store, byte for byte
    (the rehearsal found the integer recorded as 20000 and the CLI's float as 20000.0, and different identities)."""
    src = tmp_path / "c.dat"
    random_dat(src, 64, 16 * 16 // 8)
    ingest(str(src), str(tmp_path / "api.zarr"), IngestOptions(16, 16, fps=20000, cfa="rggb"), progress=False)
    assert cli("-q", "ingest", src, tmp_path / "cli.zarr", "--height", "16", "--width", "16", "--fps", "20000",
               "--cfa", "rggb").exit_code == 0
    assert store_files(tmp_path / "api.zarr") == store_files(tmp_path / "cli.zarr")


def killed_ingest(src, store, args, *, workers: bool, tmp_path) -> None:
    """``cscsr ingest`` (on a local cluster of one worker, or in its own process) killed outright once 3 tasks are
    committed: its tasks hold after the 3rd (pipeline.compute.hold), so the kill lands mid-job on any machine."""
    command = [CSCSR, "-q", "ingest", str(src), str(store), *args, *(["--workers", "1"] if workers else [])]
    kill_mid_job(command, lambda: committed_tasks(store) >= 3, timeout=120,
                 env={**os.environ, **hold_environment(3, tmp_path / "never")})
    assert 3 <= committed_tasks(store) < 8
    assert open_spike_store(str(store), allow_incomplete=True).attrs["state"] == "writing"  # not passing for complete


def test_resume_after_a_killed_ingest_equals_an_uninterrupted_one(client, cli, tmp_path):
    """``cscsr ingest --workers 1`` killed mid-job, then finished with ``--resume`` in this process and, from a
    copy, on a cluster; a one-process ingest killed and resumed: all byte-identical to an uninterrupted ingest.
    128x112 frames (head columns, flipped) of 1792 packed bytes: 4 MiB chunks of 2340 frames, 8 tasks of one."""
    src, killed = tmp_path / "c.dat", tmp_path / "killed.zarr"
    random_dat(src, 16384, 128 * 128 // 8, seed=1)
    args = ["--height", "128", "--width", "112", "--head-columns", "16", "--flip", "--cfa", "gbrg",
            "--task-frames", "2340"]
    assert cli("-q", "ingest", src, tmp_path / "clean.zarr", *args).exit_code == 0
    killed_ingest(src, killed, args, workers=True, tmp_path=tmp_path)
    shutil.copytree(killed, tmp_path / "copy.zarr")

    result = cli("-q", "ingest", src, killed, *args, "--resume")  # in this process
    assert result.exit_code == 0, result.stderr
    assert "5 tasks run, 3 already committed" in result.stdout
    clean = store_files(tmp_path / "clean.zarr")
    assert store_files(killed) == clean
    options = IngestOptions(128, 112, cfa="gbrg", flip=True, head_columns=16, task_frames=2340, resume=True)
    ingest(str(src), str(tmp_path / "copy.zarr"), options, progress=False, client=client)  # on the cluster
    assert store_files(tmp_path / "copy.zarr") == clean

    alone = tmp_path / "alone.zarr"
    killed_ingest(src, alone, args, workers=False, tmp_path=tmp_path)
    assert cli("-q", "ingest", src, alone, *args, "--resume").exit_code == 0
    assert store_files(alone) == clean


def _half_done(tmp_path, small_chunks) -> str:
    """A parallel-looking interrupted store: a full ingest with the record of all but two tasks taken back."""
    capture(tmp_path / "c.dat", 100, 16, 16, flip=False, seed=2)
    store = str(tmp_path / "s.zarr")
    ingest(str(tmp_path / "c.dat"), store, IngestOptions(16, 16, task_frames=10), progress=False)
    import zarr

    group = zarr.open_group(store, mode="r+", use_consolidated=False)
    group.attrs["state"] = "writing"
    group["committed"][5:] = -1
    return store


def test_resume_refuses_another_capture_and_other_options(cli, tmp_path, small_chunks):
    store = _half_done(tmp_path, small_chunks)
    other = tmp_path / "other.dat"
    data = bytearray((tmp_path / "c.dat").read_bytes())
    data[0] ^= 1  # same size, one bit of the first MiB
    other.write_bytes(bytes(data))
    shorter = tmp_path / "shorter.dat"
    shorter.write_bytes(bytes(data[: 32 * 90]))
    before = tree(tmp_path)
    cases = [(other, [], "is not the capture it was ingested from (the same size, but its first or last MiB differ)"),
             (shorter, [], "3200 bytes -> 2880 bytes"),
             (tmp_path / "c.dat", ["--cfa", "rggb"], "other options (cfa 'mono' -> 'rggb')"),
             (tmp_path / "c.dat", ["--task-frames", "20"], "task_frames 10 -> 20"),
             (tmp_path / "c.dat", ["--fps", "1000"], "fps 20000.0 -> 1000.0")]
    for src, extra, fragment in cases:
        result = cli("ingest", src, store, "--height", 16, "--width", 16, "--resume", *extra)
        lines = result.stderr.strip().splitlines()
        assert result.exit_code == 1 and len(lines) == 1 and fragment in lines[0], result.stderr
        assert tree(tmp_path) == before  # nothing changed, nothing created
    result = cli("-q", "ingest", tmp_path / "c.dat", store, "--height", 16, "--width", 16, "--resume", "--workers", 2)
    assert result.exit_code == 0 and "(5 tasks run, 5 already committed)" in result.stdout, result.stderr
    again = cli("-q", "ingest", tmp_path / "c.dat", store, "--height", 16, "--width", 16, "--resume")
    assert again.exit_code == 0 and "(0 tasks run, 10 already committed)" in again.stdout  # complete: nothing to do
    ingest(str(tmp_path / "c.dat"), str(tmp_path / "ref.zarr"), IngestOptions(16, 16, task_frames=10), progress=False)
    assert store_files(store) == store_files(tmp_path / "ref.zarr")


def test_dry_run_creates_nothing_and_prints_the_plan(cli, tmp_path, small_chunks):
    capture(tmp_path / "c.dat", 100, 16, 16, flip=False, seed=3)
    before = tree(tmp_path)
    result = cli("ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--height", 16, "--width", 16, "--task-frames", 20,
                 "--workers", 2, "--dry-run", "--json")
    assert result.exit_code == 0, result.stderr
    plan = json.loads(result.stdout)
    assert tree(tmp_path) == before and not (tmp_path / "s.zarr").exists()
    assert {k: plan[k] for k in ("frames", "capture_bytes", "chunk_frames", "chunks", "task_frames", "tasks",
                                  "tasks_to_run", "height", "width")} == \
        {"frames": 100, "capture_bytes": 3200, "chunk_frames": 5, "chunks": 20, "task_frames": 20, "tasks": 5,
         "tasks_to_run": 5, "height": 16, "width": 16}
    assert plan["store_bytes_estimate"] > 0 and 0 < plan["bits_per_pixel_estimate"] < 8
    assert plan["seconds_per_task"] > 0 and set(plan["hours"]) == {"1", "8", "64"}
    assert plan["hours"]["1"] >= plan["hours"]["8"] >= plan["hours"]["64"] > 0
    table = cli("ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--height", 16, "--width", 16, "--dry-run")
    assert table.exit_code == 0 and "time on 64 workers" in table.stdout and "store_bytes_estimate" in table.stdout
    assert tree(tmp_path) == before
    written = api_ingest(str(tmp_path / "c.dat"), str(tmp_path / "s.zarr"), height=16, width=16, dry_run=True)
    assert written.counts["tasks"] == 1 and tree(tmp_path) == before
    # a resume's plan: what is left
    store = _half_done(tmp_path, small_chunks)
    result = cli("ingest", tmp_path / "c.dat", store, "--height", 16, "--width", 16, "--resume", "--dry-run", "--json")
    assert result.exit_code == 0 and json.loads(result.stdout)["tasks_to_run"] == 5


def test_bad_input_is_one_line_and_creates_nothing(cli, tmp_path, small_chunks):
    capture(tmp_path / "c.dat", 100, 16, 16, flip=False, seed=4)
    np.savez(tmp_path / "c.npz", spk=np.zeros((10, 8, 8), np.uint8))
    out = tmp_path / "s.zarr"
    dat = (tmp_path / "c.dat", out, "--height", 16, "--width", 16)
    before = tree(tmp_path)
    cases = [((*dat, "--resume"), "cannot resume: ", "does not exist"),
             ((*dat, "--resume", "--overwrite"), "--resume and --overwrite contradict each other"),
             ((*dat, "--workers", 0), "--workers must be >= 1"),
             ((*dat, "--task-frames", 0), "--task-frames must be >= 1"),
             ((*dat, "--json"), "--json is for --dry-run"),
             ((*dat, "--dry-run", "--workers", 0), "--workers must be >= 1"),
             ((tmp_path / "c.npz", out, "--workers", 2), "a .npz is read as one stream"),
             ((*dat, "--scheduler", "tcp://127.0.0.1:1"), "cannot reach Dask scheduler tcp://127.0.0.1:1")]
    for args, *fragments in cases:
        result = cli("ingest", *args)
        lines = result.stderr.strip().splitlines()
        assert result.exit_code == 1 and len(lines) == 1 and lines[0].startswith("error: "), (args, result.stderr)
        assert all(f in lines[0] for f in fragments), lines[0]
        assert tree(tmp_path) == before
    # the Python API checks as strictly
    for kwargs, kind in [({"workers": 0}, InputError), ({"resume": "yes"}, InputTypeError),
                         ({"dry_run": "no"}, InputTypeError), ({"task_frames": 2.5}, InputTypeError),
                         ({"resume": True, "overwrite": True}, InputError), ({"resume": True}, InputError)]:
        with pytest.raises(kind):
            api_ingest(str(tmp_path / "c.dat"), str(out), height=16, width=16, **kwargs)
        assert tree(tmp_path) == before
    # a store that holds no record of its tasks (a simulated one, or one from before) is not resumed
    ingest(str(tmp_path / "c.dat"), str(out), IngestOptions(16, 16), progress=False)
    shutil.rmtree(out / "committed")
    result = cli("ingest", *dat, "--resume")
    assert result.exit_code == 1 and "holds no record of ingest tasks" in result.stderr


def test_a_lost_worker_does_not_fail_the_ingest(tmp_path, small_chunks):
    """Both workers SIGKILLed while they hold their third task: Dask runs their tasks again on the workers their
    nannies start, and the store is the one-process ingest's, byte for byte."""
    import threading

    from distributed import Client, LocalCluster

    bits = capture(tmp_path / "c.dat", 200, 16, 16, flip=True, seed=6)
    options = IngestOptions(16, 16, cfa="rggb", flip=True, task_frames=10)  # 20 tasks
    ingest(str(tmp_path / "c.dat"), str(tmp_path / "one.zarr"), options, progress=False)
    release, store = tmp_path / "release", tmp_path / "two.zarr"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      env=hold_environment(2, release)) as cluster, Client(cluster) as client:
        outcome = {}
        job = threading.Thread(target=lambda: outcome.update(
            attrs=ingest(str(tmp_path / "c.dat"), str(store), options, progress=False, client=client)))
        job.start()
        deadline = time.time() + 60
        while committed_tasks(store) < 4:  # two tasks each, then both hold
            assert time.time() < deadline and job.is_alive(), "the job never got going"
            time.sleep(0.02)
        pids = client.run(os.getpid)
        for pid in pids.values():
            os.kill(pid, signal.SIGKILL)
        release.touch()  # the workers that replace them run on
        job.join(120)
        assert not job.is_alive() and outcome["attrs"]["spike_count"] == int(bits.sum())
    assert store_files(store) == store_files(tmp_path / "one.zarr")


def test_a_store_of_one_task_recorded_larger_than_its_capture_is_resumed(cli, tmp_path, small_chunks):
    """A capture smaller than a task is one task; a store that records that task by the size asked (as ingest did
    before its writes were ``lazy.to_spikes``'s: whole chunks, more frames than the capture) has the same cut, and
    ``--resume`` finishes it to the spikes of an uninterrupted ingest."""
    import zarr

    capture(tmp_path / "c.dat", 100, 16, 16, flip=False, seed=5)
    store, reference = str(tmp_path / "s.zarr"), str(tmp_path / "ref.zarr")
    for url in (store, reference):
        ingest(str(tmp_path / "c.dat"), url, IngestOptions(16, 16), progress=False)
    group = zarr.open_group(store, mode="r+", use_consolidated=False)
    chunk = group["spikes"].chunks[0]
    assert group["committed"].shape == (1,) and group["committed"].attrs["task_frames"] < 100 + chunk
    group["committed"].attrs["task_frames"] = 50 * chunk  # one task, as asked
    group["committed"][:] = -1
    group.attrs["state"] = "writing"
    result = cli("-q", "ingest", tmp_path / "c.dat", store, "--height", 16, "--width", 16, "--resume")
    assert result.exit_code == 0 and "(1 task run, 0 already committed)" in result.stdout, result.stderr
    assert (zarr.open_array(store, path="spikes")[:] == zarr.open_array(reference, path="spikes")[:]).all()
