"""The HPC and Kubernetes routes (deploy/) and the constraints file host and image share.

No SLURM, Kubernetes or Docker runs here: the SLURM route is checked on the job script
dask-jobqueue would submit, the Kubernetes manifest on its parsed YAML against
docker-compose.yml, and constraints.txt against the Makefile, the Dockerfile and .venv.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
CONSTRAINTS = ROOT / "constraints.txt"
MANIFEST = ROOT / "deploy" / "kubernetes" / "daskcluster.yaml"
SLURM_SCRIPT = ROOT / "deploy" / "slurm.py"


def _compose_service(name: str) -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"][name]


def _worker_options(command: list[str]) -> dict[str, str]:
    """`--flag value` pairs of a dask worker command line (flags without a value map to "")."""
    options, i = {}, 0
    while i < len(command):
        if command[i].startswith("--"):
            has_value = i + 1 < len(command) and not command[i + 1].startswith("--")
            options[command[i]] = command[i + 1] if has_value else ""
            i += 2 if has_value else 1
        else:
            i += 1
    return options


# --- SLURM (dask-jobqueue) --------------------------------------------------------------

@pytest.fixture(scope="module")
def slurm():
    pytest.importorskip("dask_jobqueue")
    spec = importlib.util.spec_from_file_location("cscsr_deploy_slurm", SLURM_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _job_script(slurm, **kwargs) -> tuple[str, str]:
    with slurm.make_cluster(scheduler_options={"host": "127.0.0.1"}, **kwargs) as cluster:
        return cluster.job_script(), cluster.scheduler_address


def _worker_line(script: str, command: str = "distributed.cli.dask_worker") -> list[str]:
    lines = [line for line in script.splitlines() if f" -m {command} " in line]
    assert len(lines) == 1, script
    return shlex.split(lines[0])


def test_slurm_cpu_job_script(slurm):
    script, address = _job_script(slurm, partition="compute", account="proj42", walltime="02:00:00")
    directives = [line for line in script.splitlines() if line.startswith("#SBATCH")]
    assert "#SBATCH -J cscsr" in directives
    assert "#SBATCH -p compute" in directives
    assert "#SBATCH -A proj42" in directives
    assert "#SBATCH -t 02:00:00" in directives
    assert "#SBATCH --cpus-per-task=1" in directives
    assert "#SBATCH --mem=4G" in directives
    assert not any("gres" in line for line in directives)
    assert "export OMP_NUM_THREADS=1" in script.splitlines()

    command = _worker_line(script)
    # The jobs run this very interpreter, the one cscsr is installed in.
    assert command[:3] == [sys.executable, "-m", "distributed.cli.dask_worker"]
    assert command[3] == address
    options = _worker_options(command)
    assert options["--nthreads"] == "1"
    assert options["--memory-limit"] in {"4GiB", "4.00GiB"}
    assert "--resources" not in options


@pytest.mark.parametrize("gpus", [1, 3])
def test_slurm_gpu_job_script_matches_the_compose_gpu_worker(slurm, gpus):
    from pipeline.compute.cluster import GPU_TASKS_IN_FLIGHT

    script, address = _job_script(slurm, gpu=True, gpus_per_job=gpus)
    directives = [line for line in script.splitlines() if line.startswith("#SBATCH")]
    assert f"#SBATCH --gres=gpu:{gpus}" in directives
    assert "#SBATCH -J cscsr-gpu" in directives
    assert f"#SBATCH --cpus-per-task={GPU_TASKS_IN_FLIGHT * gpus}" in directives
    assert f"#SBATCH --mem={4 * gpus}G" in directives
    # `cscsr worker` (the compose gpu-worker's command): one pinned GPU=1 worker per GPU of the job,
    # each with the compose worker's memory and GPU_TASKS_IN_FLIGHT threads.
    command = _worker_line(script, "pipeline.cli worker")
    assert command[:5] == [sys.executable, "-m", "pipeline.cli", "worker", address]
    options = _worker_options(command)
    compose = _compose_service("gpu-worker")["command"]
    assert shlex.split(compose)[:2] == ["cscsr", "worker"]
    assert options["--memory-limit"] in {"4GiB", "4.00GiB"}
    assert _worker_options(shlex.split(compose))["--memory-limit"] == "4GiB"
    assert options["--nthreads"] == str(GPU_TASKS_IN_FLIGHT)
    assert options["--gpus"] == str(gpus)
    assert "--resources" not in options and "--nworkers" not in options


def test_slurm_gpu_job_runs_its_worker_line(slurm, monkeypatch):
    """The very command line dask-jobqueue writes for a 2-GPU job, run against that cluster's own scheduler:
    `cscsr worker` takes every option it is given, and starts two pinned workers named as dask-jobqueue
    expects; SIGTERM ends it."""
    import os
    import signal
    import time

    from distributed import Client

    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    with slurm.make_cluster(gpu=True, gpus_per_job=2, scheduler_options={"host": "127.0.0.1"},
                            interface="lo") as cluster, Client(cluster) as client:
        command = _worker_line(cluster.job_script(), "pipeline.cli worker")
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            client.wait_for_workers(2, timeout=60)
            workers = client.scheduler_info()["workers"].values()
            assert sorted(w["name"] for w in workers) == ["dummy-name-0", "dummy-name-1"]
            assert all(w["resources"] == {"GPU": 1} and w["nthreads"] == 4 for w in workers)
            assert sorted(client.run(lambda: os.environ["CUDA_VISIBLE_DEVICES"]).values()) == ["0", "1"]
            time.sleep(0.5)  # the nannies finish registering
        finally:
            process.send_signal(signal.SIGTERM)
            _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0, stderr
        assert "2 GPU workers (CUDA devices 0, 1)" in stderr


def test_slurm_script_prints_its_job_script_and_needs_a_command():
    pytest.importorskip("dask_jobqueue")
    done = subprocess.run([sys.executable, str(SLURM_SCRIPT), "--gpu", "--print-job-script"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("#!/usr/bin/env bash")
    assert " -m pipeline.cli worker " in done.stdout and "--gres=gpu:1" in done.stdout

    done = subprocess.run([sys.executable, str(SLURM_SCRIPT), "--jobs", "2"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "after `--`" in done.stderr


@pytest.mark.parametrize("sbatch", ["refuses", "takes"])
def test_slurm_script_runs_the_command_only_once_its_jobs_are_submitted(tmp_path, sbatch):
    """An ``sbatch`` that refused the jobs (a partition SLURM lacks) was only logged by dask-jobqueue: the command
    ran all the same, waited for workers never asked for, and the script ended in a traceback. Now one line,
    status 1, the command not run; with an ``sbatch`` that takes them, the command runs on their scheduler."""
    pytest.importorskip("dask_jobqueue")
    bin_folder = tmp_path / "bin"
    bin_folder.mkdir()
    said = ('echo "sbatch: error: invalid partition specified: gpux" >&2; exit 1' if sbatch == "refuses"
            else 'echo "Submitted batch job 42"')
    for name, body in (("sbatch", f"cat > /dev/null\n{said}"), ("scancel", "exit 0")):
        (bin_folder / name).write_text(f"#!/bin/sh\n{body}\n")
        (bin_folder / name).chmod(0o755)
    done = subprocess.run([sys.executable, str(SLURM_SCRIPT), "--jobs", "2", "--partition", "gpux", "--",
                           sys.executable, "-c", "import os; print('ran on', os.environ['DASK_SCHEDULER_ADDRESS'])"],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PATH": f"{bin_folder}{os.pathsep}{os.environ['PATH']}"})
    if sbatch == "refuses":
        assert done.returncode == 1 and "ran on" not in done.stdout, done.stdout
        assert done.stderr.strip().splitlines()[-1] == ("error: sbatch refuses the worker job (sbatch: error: invalid "
                                                        "partition specified: gpux): the command was not run")
    else:
        assert done.returncode == 0 and done.stdout.startswith("ran on tcp://"), done.stderr[-2000:]


# --- Kubernetes (Dask operator) ---------------------------------------------------------

@pytest.fixture(scope="module")
def manifest() -> dict[str, dict]:
    documents = list(yaml.safe_load_all(MANIFEST.read_text()))
    assert [d["kind"] for d in documents] == ["DaskCluster", "DaskWorkerGroup"]
    assert all(d["apiVersion"] == "kubernetes.dask.org/v1" for d in documents)
    return {d["kind"]: d for d in documents}


def _container(pod_spec: dict) -> dict:
    (container,) = pod_spec["containers"]
    return container


def test_kubernetes_scheduler_matches_compose(manifest):
    cluster = manifest["DaskCluster"]
    scheduler = _container(cluster["spec"]["scheduler"]["spec"])
    compose = _compose_service("scheduler")
    assert scheduler["image"] == compose["image"] == "cscsr:latest"
    assert scheduler["args"] == shlex.split(compose["command"])
    ports = {p["name"]: p["containerPort"] for p in scheduler["ports"]}
    assert ports == {"tcp-comm": 8786, "http-dashboard": 8787}
    service = cluster["spec"]["scheduler"]["service"]
    assert service["type"] == "ClusterIP"  # not exposed beyond the cluster, as compose keeps it on loopback
    assert service["selector"]["dask.org/cluster-name"] == cluster["metadata"]["name"]
    assert {p["targetPort"] for p in service["ports"]} == set(ports)


@pytest.mark.parametrize("group, service", [("DaskCluster", "worker"), ("DaskWorkerGroup", "gpu-worker")])
def test_kubernetes_workers_match_compose(manifest, group, service):
    worker_spec = manifest[group]["spec"]["worker"]
    container = _container(worker_spec["spec"])
    compose = _compose_service(service)
    assert container["image"] == compose["image"]
    args = container["args"]
    assert args[:2] == shlex.split(compose["command"])[:2]  # dask worker; cscsr worker for the GPU workers
    # The operator gives the scheduler's address in DASK_SCHEDULER_ADDRESS; every compose
    # option but the address is here with the same value.
    options, compose_options = _worker_options(args), _worker_options(shlex.split(compose["command"]))
    assert {k: options.get(k) for k in compose_options} == compose_options
    env = {e["name"]: e["value"] for e in container["env"]}
    assert env["OMP_NUM_THREADS"] == compose["environment"]["OMP_NUM_THREADS"]
    assert worker_spec["replicas"] >= 1
    # Data on an object store: the S3 credentials come from a Secret, nothing is mounted.
    assert "volumeMounts" not in container
    assert any(s["secretRef"]["name"] == "cscsr-s3" for s in container["envFrom"])


def test_kubernetes_gpu_group(manifest):
    group = manifest["DaskWorkerGroup"]
    assert group["spec"]["cluster"] == manifest["DaskCluster"]["metadata"]["name"]
    gpu = _container(group["spec"]["worker"]["spec"])
    assert gpu["resources"]["limits"]["nvidia.com/gpu"] == 1
    # `cscsr worker`: one pinned GPU=1 worker per GPU of the pod, the scheduler from DASK_SCHEDULER_ADDRESS
    assert gpu["args"][:2] == ["cscsr", "worker"] and not gpu["args"][2].startswith("tcp://")
    assert "--resources" not in gpu["args"] and "--gpus" not in gpu["args"]
    cpu = _container(manifest["DaskCluster"]["spec"]["worker"]["spec"])
    assert "nvidia.com/gpu" not in cpu["resources"]["limits"]
    assert "--resources" not in cpu["args"]


# --- constraints.txt: the image pins what the host pins ---------------------------------

def _pins() -> dict[str, str]:
    pins = {}
    for line in CONSTRAINTS.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, version = re.fullmatch(r"([A-Za-z0-9._-]+)==(\S+)", line).groups()
            pins[re.sub(r"[-_.]+", "-", name).lower()] = version
    return pins


def test_constraints_are_exact_pins_without_the_project():
    pins = _pins()
    assert "cscsr" not in pins
    assert "+" not in pins["torch"]  # no local label: the CPU and the CUDA wheels both match


@pytest.mark.parametrize("package", ["dask", "distributed", "zarr", "numcodecs", "torch"])
def test_constraints_match_the_venv(package):
    installed = importlib.metadata.version(package).split("+")[0]
    assert _pins()[package] == installed, f"constraints.txt and this environment disagree on {package}"


def test_makefile_and_dockerfile_install_with_the_constraints():
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^CONSTRAINTS := constraints\.txt$", makefile, re.M)
    assert re.search(r"^\$\(STAMP\):.*\$\(CONSTRAINTS\)", makefile, re.M)  # a new pin reinstalls
    installs = [line.strip() for line in makefile.splitlines() if "pip install" in line and "--upgrade pip" not in line]
    assert installs and all("-c $(CONSTRAINTS)" in line for line in installs)

    dockerfile = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    copied = re.search(r"^COPY constraints\.txt (\S+)$", dockerfile, re.M)
    assert copied, "the Dockerfile does not copy constraints.txt"
    runs = [line for line in dockerfile.splitlines() if line.startswith("RUN") and "pip install" in line]
    assert runs and all(f"-c {copied.group(1)}" in line for line in runs)
    assert dockerfile.index("COPY constraints.txt") < dockerfile.index(runs[0])

    torch = _pins()["torch"]
    assert f"torch=={torch}" in makefile and f"torch=={torch}" in runs[0]
