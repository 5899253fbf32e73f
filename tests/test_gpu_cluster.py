"""Several GPUs per machine: one worker per GPU, pinned to it and advertising ``GPU=1`` (dask-cuda's convention).

No GPU is needed: a GPU worker is a worker process whose ``CUDA_VISIBLE_DEVICES`` names its device and that
advertises the resource; the tests ask ``gpus=2`` of a CPU machine and read both back from real worker
processes (``client.run``) and from the scheduler. ``cscsr worker``'s own command line, as dask-jobqueue
writes it, runs in tests/test_deploy.py.
"""

import os
import subprocess
import sys
import threading
import time
import types

import dask
import pytest
from distributed import Client, LocalCluster, WorkerPlugin

from pipeline.compute import cluster as gpu_cluster
from pipeline.compute.cluster import (GPU, GPU_SHARE, GPU_TASKS_IN_FLIGHT, dask_client, gpu_worker_specs, serve_workers,
                              visible_gpus)
from stages.errors import InputError
from tests.test_bad_input import assert_refused


@pytest.fixture(autouse=True)
def no_visible_devices(monkeypatch):
    """The machine's own CUDA_VISIBLE_DEVICES (a CI runner's, SLURM's) would pick the workers' devices."""
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)


def device_of_each_worker(client: Client) -> dict[str, str | None]:
    """Worker name -> the CUDA_VISIBLE_DEVICES its process runs with (None: not set)."""
    names = {address: worker["name"] for address, worker in client.scheduler_info()["workers"].items()}
    seen = client.run(lambda: os.environ.get("CUDA_VISIBLE_DEVICES"))
    return {names[address]: devices for address, devices in seen.items()}


def advertised(client: Client) -> dict[str, tuple[dict, int]]:
    """Worker name -> (resources, threads), as the scheduler knows them."""
    return {worker["name"]: (worker["resources"], worker["nthreads"])
            for worker in client.scheduler_info()["workers"].values()}


# --- the specs ----------------------------------------------------------------------------

def test_a_network_task_takes_a_quarter_of_a_gpu_worker():
    assert GPU_TASKS_IN_FLIGHT == 4
    assert GPU_SHARE == 0.25 and GPU_SHARE * GPU_TASKS_IN_FLIGHT == 1  # exact in binary: four fit, not three


@pytest.mark.parametrize("workers, gpus", [(1, 0), (3, 0), (1, 1), (2, 1), (3, 2), (2, 2), (2, 4), (8, 3)])
def test_the_first_workers_are_pinned_to_one_gpu_each_the_rest_see_none(workers, gpus):
    specs = gpu_worker_specs(workers, gpus)
    pinned = min(workers, gpus)
    assert len(specs) == workers
    for i, spec in enumerate(specs[:pinned]):
        assert spec == {"env": {"CUDA_VISIBLE_DEVICES": str(i)}, "resources": {GPU: 1}, "nthreads": GPU_TASKS_IN_FLIGHT}
    for spec in specs[pinned:]:
        assert spec == {"env": {"CUDA_VISIBLE_DEVICES": ""}, "resources": {}, "nthreads": 1}


def test_the_devices_may_be_named():
    specs = gpu_worker_specs(3, 2, ["GPU-5d1c", "3"])
    assert [s["env"]["CUDA_VISIBLE_DEVICES"] for s in specs] == ["GPU-5d1c", "3", ""]
    with pytest.raises(ValueError):
        gpu_worker_specs(2, 2, ["0"])


def test_pinned_workers_take_the_devices_this_process_was_given(monkeypatch):
    """SLURM and container runtimes give a job its GPUs in CUDA_VISIBLE_DEVICES: worker i takes the i-th (as
    dask-cuda does), not the machine's device i."""
    assert gpu_cluster._devices(2) == ["0", "1"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,5")
    assert gpu_cluster._devices(2) == ["2", "5"]
    assert gpu_cluster._devices(1) == ["2"]
    with pytest.raises(InputError, match="shows only 2 GPUs"):
        gpu_cluster._devices(3)


def test_visible_gpus(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert visible_gpus() == 0  # every device hidden: torch is not even asked
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    fake = types.SimpleNamespace(cuda=types.SimpleNamespace(device_count=lambda: 3))
    monkeypatch.setitem(sys.modules, "torch", fake)
    assert visible_gpus() == 3
    fake.cuda.device_count = lambda: 1 / 0  # a broken CUDA install is no GPU
    assert visible_gpus() == 0


def test_visible_gpus_of_a_cpu_torch_imports_nothing():
    """A CPU build of torch (this project's default) is answered from its version, without a 1.5 s import."""
    import importlib.metadata
    import subprocess

    if not importlib.metadata.version("torch").endswith("+cpu"):
        pytest.skip("torch here is not a CPU build")
    code = "import sys; from pipeline.compute.cluster import visible_gpus; print(visible_gpus(), 'torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.stdout.split() == ["0", "False"], done.stderr


# --- a local cluster ----------------------------------------------------------------------

def test_a_local_cluster_on_two_gpus_has_two_pinned_gpu_workers_and_a_cpu_worker():
    with dask_client(workers=3, gpus=2) as client:
        assert device_of_each_worker(client) == {0: "0", 1: "1", 2: ""}
        assert advertised(client) == {0: ({GPU: 1}, GPU_TASKS_IN_FLIGHT), 1: ({GPU: 1}, GPU_TASKS_IN_FLIGHT),
                                      2: ({}, 1)}
        # What every local worker has, GPU or not: loopback, one process each, the thread and malloc settings.
        workers = client.scheduler_info()["workers"]
        assert all(address.startswith("tcp://127.0.0.1:") for address in workers)
        assert len(set(client.run(os.getpid).values())) == 3
        threads = str(max(1, (os.cpu_count() or 1) // 3))
        settings = client.run(lambda: (os.environ.get("OMP_NUM_THREADS"), os.environ.get("MALLOC_MMAP_THRESHOLD_")))
        assert set(settings.values()) == {(threads, str(64 * 2**20))}
        assert len({worker["memory_limit"] for worker in workers.values()}) == 1  # the machine's, shared alike
        assert client.submit(lambda x: x + 1, 1, resources={GPU: GPU_SHARE}).result() == 2


def test_without_gpus_a_local_cluster_is_as_it_was():
    with dask_client(workers=2, gpus=0) as client:
        assert advertised(client) == {0: ({}, 1), 1: ({}, 1)}
        assert device_of_each_worker(client) == {0: None, 1: None}  # not touched


def test_workers_2_on_a_one_gpu_machine_is_a_gpu_worker_and_a_cpu_worker(monkeypatch):
    monkeypatch.setattr(gpu_cluster, "visible_gpus", lambda: 1)  # the default: the GPUs this machine has
    with dask_client(workers=2) as client:
        assert advertised(client) == {0: ({GPU: 1}, GPU_TASKS_IN_FLIGHT), 1: ({}, 1)}
        assert device_of_each_worker(client) == {0: "0", 1: ""}


class SlowToExit(WorkerPlugin):
    """A worker plugin whose teardown takes ``seconds`` (as a GPU worker's CUDA context and compile workers
    did on the H200) and then writes ``marker``: written only if the worker was let finish its exit."""

    def __init__(self, seconds: float, marker: str):
        self.seconds, self.marker = seconds, marker

    def setup(self, worker):
        pass

    def teardown(self, worker):
        time.sleep(self.seconds)
        with open(self.marker, "w") as f:
            f.write(str(worker.name))


def test_a_gpu_worker_slow_to_exit_is_let_finish_when_its_cluster_closes(tmp_path):
    """Dask's nanny kills a worker that has not exited 4 s after being asked; a GPU worker is given
    GPU_WORKER_EXIT_S, so the cluster of a finished --fast-gpu job closes without an error."""
    assert gpu_cluster.GPU_WORKER_EXIT_S >= 30
    marker = tmp_path / "exited"
    with dask_client(workers=1, gpus=1) as client:
        client.register_plugin(SlowToExit(6, str(marker)), name="slow-to-exit")
    assert marker.read_text() == "0"


def test_a_negative_gpu_count_is_refused():
    with pytest.raises(InputError, match="--gpus must be >= 0"), dask_client(workers=1, gpus=-1):
        pass


# --- a cluster node: serve_workers (cscsr worker) -----------------------------------------

@pytest.fixture
def scheduler():
    """A scheduler without workers, and a client of it. Dask's ``scheduler`` setting is put back afterwards: a
    client closed inside the test (its scheduler going away) and then again on exit leaves it at
    ``dask.distributed``, and every later ``.compute()`` in this process would ask for a client."""
    with dask.config.set(scheduler=None), \
            LocalCluster(n_workers=0, host="127.0.0.1", dashboard_address=":0") as cluster, Client(cluster) as client:
        yield cluster, client


def serving(address: str, **options) -> tuple[threading.Thread, threading.Event, list]:
    stop, failures = threading.Event(), []

    def run() -> None:
        try:
            serve_workers(address, stop=stop, **options)
        except BaseException as error:  # noqa: BLE001 - the test reads it
            failures.append(error)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, stop, failures


def test_a_node_with_two_gpus_serves_two_pinned_workers_until_stopped(scheduler, caplog, monkeypatch):
    cluster, client = scheduler
    monkeypatch.setattr("pipeline.compute.cluster.visible_gpus", lambda: 0)  # this machine's CPU torch, for sure
    thread, stop, failures = serving(cluster.scheduler_address, gpus=2, name_prefix="node")
    client.wait_for_workers(2, timeout=60)
    # more GPUs than torch sees: served (a node's environment may hide them from here), and said
    assert "--gpus 2, but torch sees 0 CUDA devices here: these workers advertise GPUs they do not have" in caplog.text
    assert advertised(client) == {"node-0": ({GPU: 1}, GPU_TASKS_IN_FLIGHT), "node-1": ({GPU: 1}, GPU_TASKS_IN_FLIGHT)}
    assert device_of_each_worker(client) == {"node-0": "0", "node-1": "1"}
    assert {w["memory_limit"] for w in client.scheduler_info()["workers"].values()} == {4 * 2**30}
    time.sleep(0.5)  # the nannies finish registering

    stop.set()
    thread.join(30)
    assert not thread.is_alive() and not failures
    deadline = time.time() + 10
    while client.scheduler_info()["workers"] and time.time() < deadline:
        time.sleep(0.1)
    assert not client.scheduler_info()["workers"]  # closed, not left to time out


def test_a_node_without_a_gpu_serves_one_cpu_worker_until_its_scheduler_goes_away(scheduler):
    cluster, client = scheduler
    thread, _, failures = serving(cluster.scheduler_address, gpus=0, name_prefix="node", memory_limit="1GiB")
    client.wait_for_workers(1, timeout=60)
    assert advertised(client) == {"node": ({}, 1)}
    assert {w["memory_limit"] for w in client.scheduler_info()["workers"].values()} == {2**30}
    time.sleep(0.5)

    client.close()
    cluster.close()
    thread.join(30)
    assert not thread.is_alive() and not failures


def test_a_node_refuses_bad_options_before_it_starts_anything():
    with pytest.raises(InputError, match="--memory-limit"):
        serve_workers("tcp://127.0.0.1:1", memory_limit="lots", gpus=0)
    with pytest.raises(InputError, match="--gpus"):
        serve_workers("tcp://127.0.0.1:1", gpus=1.5)
    with pytest.raises(InputError, match="--nthreads"):
        serve_workers("tcp://127.0.0.1:1", gpus=0, nthreads=0)


# --- the command line ---------------------------------------------------------------------

def test_cscsr_worker_with_a_bad_scheduler_address_is_one_line(cli):
    assert_refused(cli("worker", "nonsense://somewhere:8786"), "cannot use Dask scheduler address",
                   "nonsense://somewhere:8786")


def test_cscsr_worker_without_a_scheduler_is_one_line(cli, monkeypatch):
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    assert_refused(cli("worker"), "DASK_SCHEDULER_ADDRESS")
    assert_refused(cli("worker", "tcp://127.0.0.1:8786", "--memory-limit", "lots"), "--memory-limit", "lots")
    assert_refused(cli("worker", "tcp://127.0.0.1:8786", "--gpus", "-1"), "--gpus must be >= 0")


def test_a_cpu_local_cluster_forks_its_workers_from_one_server_with_the_spawned_environment():
    """A local CPU cluster's workers are forks of one server process that imported Dask and Zarr once (spawned,
    each worker imported them again at every cluster start); the next cluster forks from the same server, and a
    worker starts with what a spawned one had: the malloc settings and Dask's hash seed."""
    import psutil

    servers = set()
    for _ in range(2):
        with dask_client(workers=2, gpus=0) as client:
            seen = client.run(lambda: (psutil.Process().ppid(), "zarr" in sys.modules, os.environ.get(
                "MALLOC_MMAP_THRESHOLD_"), os.environ.get("PYTHONHASHSEED")))
            assert {facts[1:] for facts in seen.values()} == {(True, str(64 * 2**20), "6640")}
            servers |= {facts[0] for facts in seen.values()}
    (server,) = servers
    assert server != os.getpid() and "multiprocessing.forkserver" in " ".join(psutil.Process(server).cmdline())


def test_a_network_job_s_workers_find_torch_imported_by_their_server_and_a_tfp_job_s_never_import_it():
    """``dask_client(preload=NETWORK_PRELOAD)`` (a network job's, in each of its segments) starts the process's fork
    server with torch and the reconstructor imported, so no worker imports them again (2.5 core-s each); without it
    (a TFP job) its workers never import torch. Fresh processes, as a command and its segments are: the server is the
    first cluster's of a process."""
    script = ("import sys\n"
              "from pipeline.compute.cluster import dask_client\n"
              "from pipeline.compute.worker_start import NETWORK_PRELOAD\n"
              "with dask_client(workers=1, gpus=0, preload=NETWORK_PRELOAD if sys.argv[1] == 'network' else ()) as c:\n"
              "    print(*c.run(lambda: [name in sys.modules for name in NETWORK_PRELOAD]).values())\n")
    for job, imported in (("network", "[True, True]"), ("tfp", "[False, False]")):
        done = subprocess.run([sys.executable, "-c", script, job], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0 and done.stdout.strip() == imported, done.stderr[-2000:]


def test_a_local_cluster_starts_under_a_temporary_folder_too_long_for_a_socket(tmp_path):
    """The fork server listens on a Unix socket in ``$TMPDIR/pymp-*/``; with a ``TMPDIR`` too long for a socket's
    path (107 bytes) every job failed ("AF_UNIX path too long"). A fresh process, as a command is."""
    folder = tmp_path / ("t" * max(1, 110 - len(str(tmp_path))))  # over 107 bytes wherever tmp_path is
    folder.mkdir()
    script = ("from pipeline.compute.cluster import dask_client\n"
              "with dask_client(workers=1, gpus=0) as client:\n"
              "    print(sum(client.run(lambda: 1).values()))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "TMPDIR": str(folder)})
    assert done.returncode == 0 and done.stdout.split() == ["1"], done.stderr[-2000:]
    assert len(str(folder)) > 107 and not [p for p in folder.iterdir() if p.name.startswith("pymp-")]
