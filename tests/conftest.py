"""Shared fixtures: the bundled samples, a CLI runner, and small synthetic captures."""

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass

# The suite runs three processes on two cores (make test): OpenMP and BLAS thread pools of two threads each then
# spin for cores they do not get (a third of the torch-heavy tests' time). One thread each, before torch or numpy
# is imported; the processes the tests start inherit it (a local cluster's workers get their own, _thread_env).
for _pool in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_pool, "1")
# The suite's clusters are idle most of their lives (a module's client waits while its tests run commands), and an
# idle two-worker cluster spent a fifth of a core on Dask's housekeeping: the workers' statistical profiler (a stack
# sample every 10 ms, for the dashboard's Profile page), the event-loop tick (every 20 ms) and the system monitor
# (every 0.5 s). Without the profiler and at a slower tick and monitor, it spends a twentieth; a job's tasks, worker
# loss (heartbeats, the nanny) and memory limits (the memory monitor) run as before. Set before dask is imported, so
# the commands, clusters and workers the tests start inherit them.
for _setting, _value in (("DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED", "False"),
                         ("DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL", "1s"),
                         ("DASK_DISTRIBUTED__ADMIN__SYSTEM_MONITOR__INTERVAL", "5s")):
    os.environ.setdefault(_setting, _value)

import dask
import fsspec
import numpy as np
import pytest
from typer.testing import CliRunner

from cscsr import samples
from pipeline.cli import app
from pipeline.compute.worker_start import NETWORK_PRELOAD, forked_workers


CSCSR = os.path.join(os.path.dirname(sys.executable), "cscsr")  # the installed command, as a user runs it


def committed_tasks(url) -> int:
    """Tasks a job has committed to the store at ``url`` so far (0 before it exists): each writes one chunk
    file of ``committed`` (cheap to count). Zarr writes a chunk to a temporary file and renames it, so a
    write cut off by a kill leaves such a file: only chunk names (digits) count."""
    return sum(name.isdigit() for _, _, files in os.walk(os.path.join(url, "committed", "c")) for name in files)


def kill_mid_job(command: list, ready, *, env: dict | None = None, timeout: float = 300) -> None:
    """Run ``command`` in a process group of its own and SIGKILL the whole group (the job, its segment and
    its cluster) once ``ready()`` holds; fails if the job ends first or ``timeout`` seconds pass."""
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, env=env)
    deadline = time.time() + timeout
    while not ready():
        assert time.time() < deadline and process.poll() is None, "the job never got going"
        time.sleep(0.02)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()


@dataclass
class CliResult:
    exit_code: int
    stdout: str
    stderr: str


@pytest.fixture
def cli():
    """Run ``cscsr ARGS`` in-process (Typer's runner) and return exit code and both streams."""
    runner = CliRunner()

    def run(*args) -> CliResult:
        result = runner.invoke(app, [str(a) for a in args])
        if result.exception and not isinstance(result.exception, SystemExit):
            raise result.exception
        return CliResult(result.exit_code, result.stdout, result.stderr)

    return run


@pytest.fixture
def cli_process():
    """Run the installed ``cscsr`` console command as a real process."""

    def run(*args, env=None) -> subprocess.CompletedProcess:
        command = [os.path.join(os.path.dirname(sys.executable), "cscsr"), *map(str, args)]
        return subprocess.run(command, capture_output=True, text=True, env={**os.environ, **(env or {})}, timeout=300)

    return run


@pytest.fixture
def reds_dat() -> str:
    return samples.path(samples.REDS_DAT)


@pytest.fixture
def helicopter_npz() -> str:
    return samples.path(samples.HELICOPTER_NPZ)


def integrate_and_fire(rate: np.ndarray, frames: int, seed: int = 0) -> np.ndarray:
    """(frames, H, W) uint8 0/1 spikes of a static scene firing at ``rate`` (subtract reset)."""
    rng = np.random.default_rng(seed)
    accumulator = rng.random(rate.shape)
    spikes = np.empty((frames, *rate.shape), np.uint8)
    for t in range(frames):
        accumulator += rate
        spikes[t] = accumulator >= 1
        accumulator -= spikes[t]
    return spikes


def smooth_rate(height: int, width: int, low: float = 0.05, high: float = 0.3, seed: int = 0) -> np.ndarray:
    """A smooth random intensity pattern mapped to firing rates in [low, high]."""
    import cv2

    noise = np.random.default_rng(seed).random((max(height // 16, 2), max(width // 16, 2)))
    pattern = cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)
    pattern = (pattern - pattern.min()) / (np.ptp(pattern) or 1)
    return low + (high - low) * pattern


def write_dat(path, bits: np.ndarray, *, flip: bool = False) -> bytes:
    """Write (T, H, W) 0/1 spikes as a raw .dat (row-major bits, LSB first); return its bytes."""
    frames = bits[:, ::-1] if flip else bits
    data = np.packbits(frames.reshape(frames.shape[0], -1), axis=-1, bitorder="little").tobytes()
    with open(path, "wb") as handle:
        handle.write(data)
    return data


@pytest.fixture(scope="session", autouse=True)
def onnx_exports_kept_apart(tmp_path_factory):
    """ONNX Runtime's exports (``cscsr.inference.onnx_runtime``) kept in the session's own folder, never the user's
    cache: set before any worker's server starts, whose environment every forked worker has."""
    os.environ.setdefault("CSCSR_ONNX_CACHE", str(tmp_path_factory.mktemp("onnx-exports")))


@pytest.fixture(scope="session", autouse=True)
def workers_forked_as_the_jobs_fork_them(onnx_exports_kept_apart):
    """The tests' own local clusters start their workers as the jobs' clusters do, as a network job's, whose workers
    find torch imported (most of the suite's clusters run the network; a fixture, not at import: a process that
    multiprocessing spawns imports this module too, and may not start processes while it does)."""
    dask.config.set(forked_workers(NETWORK_PRELOAD))


@pytest.fixture(scope="module")
def client():
    """A real LocalCluster of two single-threaded worker processes, shared by a test module."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as connected:
        yield connected


def with_random_heads(model):
    """Untrained CSCSR heads give a zero residual (the output is the base image): make the network's part
    show, with the small random heads the network had before they started at zero."""
    import torch

    for head in model.integration.heads:
        torch.nn.init.normal_(head.weight, std=1e-3)
    return model


@pytest.fixture(scope="session")
def s3_endpoint():
    """A moto S3 server on 127.0.0.1 with one bucket; the AWS variables point boto at it. One per session:
    moto's buckets and fsspec's cached filesystems live as long as the process, so two servers would
    disagree with them."""
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)  # the OS picks a free port
    server.start()
    endpoint = "http://127.0.0.1:%d" % server.get_host_and_port()[1]
    saved = {k: os.environ.get(k) for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION", "AWS_ENDPOINT_URL")}
    os.environ.update(AWS_ACCESS_KEY_ID="testing", AWS_SECRET_ACCESS_KEY="testing", AWS_DEFAULT_REGION="us-east-1",
                      AWS_ENDPOINT_URL=endpoint)
    s3 = fsspec.filesystem("s3", skip_instance_cache=True)
    if not s3.exists("spikes-bucket"):  # moto's state is the process's: another module's server may have made it
        s3.mkdir("spikes-bucket")
    yield endpoint
    server.stop()
    for key, value in saved.items():
        os.environ.pop(key, None) if value is None else os.environ.__setitem__(key, value)
