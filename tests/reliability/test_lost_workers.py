"""A lost worker never fails a job (#34.1): real ``dask scheduler`` and ``dask worker`` processes, the
job submitted by the ``cscsr`` command, the worker processes SIGKILLed mid-job.

Before: the job's plan was scattered to the workers once; when the workers holding it died the
scheduler lost it for good ("caused the cluster to lose scattered data, which can't be recovered")
and every task still to run failed with the reason ``None``. Each kill here lands while the job is
held part-way (``pipeline.compute.hold``), so it always finds work remaining.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zarr
from distributed import Client

from pipeline.compute.hold import hold_environment
from tests.conftest import integrate_and_fire, smooth_rate
from tests.test_simulate import chunk_files

BIN = os.path.dirname(sys.executable)
FRAMES, SIDE, EVERY = 200, 32, 2  # 80 output frames of one tile each, one task per output frame (TFP)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> str:
    folder = tmp_path_factory.mktemp("lost-workers")
    np.save(folder / "capture.npy", integrate_and_fire(smooth_rate(SIDE, SIDE), FRAMES))
    store = str(folder / "capture.zarr")
    run_cscsr("ingest", folder / "capture.npy", store, "--cfa", "RGGB", check=True)
    return store


def run_cscsr(*args, env=None, check=False, wait=True):
    command = [f"{BIN}/cscsr", *map(str, args)]
    if not wait:
        return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, **(env or {})})
    done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, **(env or {})}, timeout=600)
    assert not check or done.returncode == 0, done.stderr
    return done


class Cluster:
    """A ``dask scheduler`` on a free port and ``dask worker`` processes started on demand."""

    def __init__(self, folder, env):
        self.file, self.env, self.processes = folder / "scheduler.json", {**os.environ, **env}, []
        self._start("scheduler", "--host", "127.0.0.1", "--port", "0", "--scheduler-file", str(self.file),
                    "--dashboard-address", ":0", "--no-show")
        deadline = time.time() + 60
        while not self.file.exists() or not self.file.read_text().strip():
            assert time.time() < deadline, "the scheduler never started"
            time.sleep(0.1)
        self.address = json.loads(self.file.read_text())["address"]
        self.client = Client(self.address, timeout=30)

    def _start(self, *args):
        self.processes.append(subprocess.Popen([f"{BIN}/dask", *args], stdout=subprocess.DEVNULL,
                                               stderr=subprocess.DEVNULL, env=self.env))

    def add_workers(self, count: int, *, nanny: bool) -> None:
        before = len(self.client.scheduler_info()["workers"])
        for _ in range(count):
            self._start("worker", "--scheduler-file", str(self.file), "--nworkers", "1", "--nthreads", "1",
                        "--no-dashboard", *([] if nanny else ["--no-nanny"]))
        self.client.wait_for_workers(before + count, timeout=120)

    def kill_workers(self) -> None:
        """SIGKILL every worker process (with a nanny, the worker is its child; the nanny lives on)."""
        pids = self.client.run(os.getpid)
        for pid in pids.values():
            os.kill(pid, signal.SIGKILL)
        wait_for(lambda: not set(pids) & set(self.client.scheduler_info()["workers"]),
                 "the scheduler never noticed its workers died", timeout=60)

    def close(self):  # the workers first, while their scheduler answers (else each waits on it for seconds), then it
        self.client.close()
        for group in (self.processes[1:], self.processes[:1]):
            for process in group:
                process.terminate()
            for process in group:
                process.wait(timeout=30)


def committed(url: str) -> int:
    try:
        return int(zarr.open_group(url, mode="r")["committed"][:].sum())
    except Exception:  # not created yet
        return 0


def wait_for(condition, what: str, timeout: float = 180) -> None:
    deadline = time.time() + timeout
    while not condition():
        assert time.time() < deadline, what
        time.sleep(0.05)


@pytest.fixture(scope="module")
def clean(recording, tmp_path_factory) -> dict:
    """The job's bytes on an undisturbed local cluster."""
    out = tmp_path_factory.mktemp("clean") / "clean.zarr"
    run_cscsr("reconstruct", recording, out, "--method", "tfp", "--every", EVERY, "--workers", 1, check=True)
    return chunk_files(str(out))


HELD_AFTER = 20  # tasks each worker process runs before the job holds (two workers: half the job)


def run_killed_job(recording, tmp_path, *, workers: int, nanny: bool, late_workers: int = 0) -> dict:
    """Hold the job after HELD_AFTER tasks per worker, SIGKILL all its workers, release, (add late ones), finish."""
    release = tmp_path / "release"
    cluster = Cluster(tmp_path, hold_environment(HELD_AFTER, release))
    try:
        cluster.add_workers(workers, nanny=nanny)
        out = tmp_path / "killed.zarr"
        job = run_cscsr("reconstruct", recording, out, "--method", "tfp", "--every", EVERY,
                        "--scheduler", cluster.address, wait=False)
        wait_for(lambda: committed(str(out)) >= HELD_AFTER * workers or job.poll() is not None,
                 "the job never reached its hold point")
        assert job.poll() is None, job.communicate()
        cluster.kill_workers()
        release.touch()  # workers that start from now on never hold
        if late_workers:
            cluster.add_workers(late_workers, nanny=True)
        stdout, stderr = job.communicate(timeout=600)
        assert job.returncode == 0, stderr
        assert zarr.open_group(str(out), mode="r").attrs["state"] == "complete"
        return chunk_files(str(out))
    finally:
        cluster.close()


def test_the_only_worker_killed_and_restarted_by_its_nanny(recording, clean, tmp_path):
    """The issue's reproduction: one ``dask worker`` (with its nanny), its worker process SIGKILLed."""
    assert run_killed_job(recording, tmp_path, workers=1, nanny=True) == clean


def test_two_workers_lost_for_good_and_one_joining_later(recording, clean, tmp_path):
    """Two workers without a nanny (pre-empted nodes) both SIGKILLed: no worker is left; one that joins
    later finishes the job."""
    assert run_killed_job(recording, tmp_path, workers=2, nanny=False, late_workers=1) == clean


def test_a_task_every_worker_died_running_is_reported_as_a_cluster_fault(recording, tmp_path):
    """Dask gives up on a task after ``allowed-failures`` worker deaths (here 0: the first): the job ends
    with one line that says the cluster failed those frames (the reason was ``None``), the rest committed."""
    release = tmp_path / "release"
    cluster = Cluster(tmp_path, {**hold_environment(HELD_AFTER, release),
                                 "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "0"})
    try:
        cluster.add_workers(1, nanny=True)
        out = tmp_path / "out.zarr"
        job = run_cscsr("reconstruct", recording, out, "--method", "tfp", "--every", EVERY,
                        "--scheduler", cluster.address, wait=False)
        wait_for(lambda: committed(str(out)) >= HELD_AFTER or job.poll() is not None, "the job never got going")
        cluster.kill_workers()
        release.touch()
        _, stderr = job.communicate(timeout=600)
    finally:
        cluster.close()
    assert job.returncode == 1
    line = stderr.strip().splitlines()[-1]
    # the held task and the one the scheduler had already queued on that worker (Dask's worker-saturation)
    found = re.match(r"error: JobIncomplete: ([12]) of 80 output frames failed \(frames (\d+)", line)
    assert found, stderr
    assert int(found[2]) == HELD_AFTER
    assert f"frame {HELD_AFTER}: tile (0, 0): cluster fault: every worker that ran this task died" in line
    assert committed(str(out)) == 80 - int(found[1])


def test_a_task_the_cluster_drops_is_submitted_again(tmp_path):
    """A future cancelled under the job (a scheduler restart, a dropped task) is submitted again when the
    task is idempotent, and otherwise reported as a cluster fault, never as ``None``."""
    from distributed import LocalCluster

    from pipeline.compute.executor import failure, submitted

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as local, \
            Client(local) as client:
        for idempotent in (True, False):
            cancelled = []

            def submit(task):
                future = client.submit(time.sleep, 0.2 if task == 0 else 0, pure=False)
                if task == 0 and not cancelled:  # its first submission is dropped by the cluster
                    cancelled.append(future)
                    future.cancel()
                return future

            reasons = {task: failure(future) for task, future in submitted(client, range(4), submit,
                                                                             idempotent=idempotent)}
            assert len(cancelled) == 1
            assert reasons[1] is reasons[2] is reasons[3] is None
            if idempotent:
                assert reasons[0] is None
            else:
                assert reasons[0].startswith("cluster fault: the task was cancelled by the cluster")


def test_simulate_survives_its_only_worker(tmp_path):
    """``simulate`` hands workers a chain of futures (the sensor's draws, the integrator's state): all of it
    dies with the only worker, and Dask recomputes it from the chain, to the bytes of a clean run."""
    import imageio.v3 as iio

    from tests.test_simulate import picture

    iio.imwrite(tmp_path / "scene.png", picture("rocket", 64))
    options = ("--frames", 200, "--chunk-frames", 20, "--motion", "random", "--scale", 2, "--noise", "realistic")
    clean = tmp_path / "clean.zarr"
    run_cscsr("simulate", tmp_path / "scene.png", clean, *options, "--workers", 1, check=True)
    release = tmp_path / "release"
    cluster = Cluster(tmp_path, hold_environment(5, release))
    try:
        cluster.add_workers(1, nanny=True)
        out = tmp_path / "killed.zarr"
        job = run_cscsr("simulate", tmp_path / "scene.png", out, *options, "--scheduler", cluster.address, wait=False)
        wait_for(lambda: len(list(out.glob("spikes/c/*/*/*"))) >= 5 or job.poll() is not None,
                 "the job never reached its hold point")
        assert job.poll() is None, job.communicate()
        cluster.kill_workers()
        release.touch()
        _, stderr = job.communicate(timeout=600)
        assert job.returncode == 0, stderr
    finally:
        cluster.close()
    a, b = chunk_files(str(out)), chunk_files(str(clean))
    assert a.keys() == b.keys()
    assert all(a[name] == b[name] for name in a if name != "zarr.json")  # the root's attrs name the source path


def _slow_off(worker: str, x: int) -> int:
    """x + 1, slowly on any worker but ``worker``: a rerun elsewhere takes long enough to be seen pending."""
    from distributed import get_worker

    if get_worker().address != worker:
        time.sleep(1.0)
    return x + 1


def test_a_finished_task_whose_result_died_with_its_worker_is_waited_for():
    """Tasks that finished on a worker which then died, before the job read them, come back ``lost`` while
    Dask reruns them: the job waits for the rerun instead of calling them failed."""
    from distributed import LocalCluster, wait

    from pipeline.compute.executor import failure, submitted

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as local, \
            Client(local) as client:
        doomed = sorted(client.scheduler_info()["workers"])[0]
        futures = []

        def submit(task):
            futures.append(client.submit(_slow_off, doomed, task, pure=False, workers=[doomed],
                                         allow_other_workers=True))
            return futures[-1]

        results = submitted(client, range(4), submit)
        first_task, first = next(results)  # all four submitted (the window holds 12)
        outcomes = {first_task: failure(first)}  # read as the job reads it, when it is yielded
        wait(futures)  # all finished on the doomed worker; three not read yet
        os.kill(client.run(os.getpid, workers=[doomed])[doomed], signal.SIGKILL)
        wait_for(lambda: any(f.status != "finished" for f in futures), "the client never heard of the loss", 60)
        outcomes |= {task: failure(future) for task, future in results}
        assert outcomes == {0: None, 1: None, 2: None, 3: None}
        assert [f.result() for f in futures] == [1, 2, 3, 4]
