"""A job sent to a scheduler that has no workers (issue #48, rough edges): it waited silently for ever.

Now it waits as Dask's ``client.wait_for_workers(1, timeout)`` does: after a short while it says "waiting for
workers (0 connected)" on standard error, and at Dask's setting ``cscsr.wait-for-workers`` (default 60 s;
``DASK_CSCSR__WAIT_FOR_WORKERS``) it gives up in one line, exit 1, leaving nothing at OUT (no output, no claim).
A worker that joins while it waits is used.
"""

import logging
import os
import subprocess
import threading
import time

import dask
import imageio.v3 as iio
import numpy as np
import pytest
from distributed import LocalCluster

from pipeline.compute.cluster import QUIET_WAIT, dask_client, workers_timeout
from stages.errors import InputError
from tests.conftest import CSCSR
from tests.reliability.test_silent_servers_and_api import store  # noqa: F401 - a fixture

WAIT = "2s"  # the tests' cscsr.wait-for-workers


@pytest.fixture(scope="module")
def no_workers():
    """The TCP address of a Dask scheduler without a single worker."""
    with LocalCluster(n_workers=0, host="127.0.0.1", dashboard_address=None) as cluster:
        yield cluster.scheduler_address


def jobs(recording, still) -> dict:
    return {"simulate": ["simulate", still, "out.zarr", "--motion", "static", "--frames", 100],
            "reconstruct": ["reconstruct", recording, "out.zarr"],
            "evaluate": ["evaluate", recording, "--methods", "tfp", "--out", "out"]}


@pytest.mark.parametrize("job", ["simulate", "reconstruct", "evaluate"])
def test_a_job_on_a_scheduler_without_workers_says_it_waits_then_gives_up_in_one_line(
        no_workers, store, tmp_path, job):  # noqa: F811 - store: the fixture
    still = tmp_path / "inputs" / "still.png"
    iio.imwrite(still, np.random.default_rng(0).integers(0, 256, (32, 32, 3), np.uint8))
    work = tmp_path / "work"
    work.mkdir()
    args = [*jobs(store, still)[job], "--scheduler", no_workers]
    start = time.monotonic()
    result = subprocess.run([CSCSR, "-q", *map(str, args)], cwd=work, capture_output=True, text=True, timeout=60,
                            env={**os.environ, "DASK_CSCSR__WAIT_FOR_WORKERS": WAIT})
    seconds = time.monotonic() - start
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1, result.stderr
    assert len(lines) == 2, result.stderr
    assert "waiting for workers (0 connected)" in lines[0] and no_workers in lines[0], lines[0]
    assert lines[1].startswith(f"error: no worker at Dask scheduler {no_workers} within 2 s"), lines[1]
    assert "cscsr.wait-for-workers" in lines[1]
    assert seconds < 20, seconds
    assert os.listdir(work) == []  # no output, no claim


def test_a_worker_that_joins_while_the_job_waits_is_used(caplog):
    with LocalCluster(n_workers=0, processes=False, protocol="tcp://", host="127.0.0.1",
                      dashboard_address=None) as cluster:
        joins = threading.Timer(QUIET_WAIT + 1, lambda: cluster.scale(1))  # after the waiting line
        joins.start()
        try:
            with dask.config.set({"cscsr.wait-for-workers": "30s"}), caplog.at_level(logging.WARNING, "cscsr"), \
                    dask_client(scheduler=cluster.scheduler_address) as client:
                assert client.submit(sum, [1, 2]).result() == 3
        finally:
            joins.cancel()
    ours = [record.getMessage().split(" at ")[0] for record in caplog.records if record.name.startswith("cscsr")]
    assert ours == ["waiting for workers (0 connected)"]


@pytest.mark.parametrize("value, seconds", [("60s", 60.0), (5, 5.0), ("2 minutes", 120.0), (None, None)])
def test_the_wait_is_dasks_setting(value, seconds):
    with dask.config.set({"cscsr.wait-for-workers": value}):
        assert workers_timeout() == seconds


@pytest.mark.parametrize("value", ["soon", 0, -5, "0s"])
def test_a_wait_that_is_no_duration_is_refused_in_one_line(value):
    with dask.config.set({"cscsr.wait-for-workers": value}), pytest.raises(InputError, match="cscsr.wait-for-workers"):
        workers_timeout()


def test_the_default_wait_is_a_minute():
    assert workers_timeout() == 60.0
