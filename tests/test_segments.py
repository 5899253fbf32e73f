"""Segments: each in a fresh process with its own cluster; outcomes, errors and crashes reach the job."""

import contextlib
import functools
import os

import pytest

from pipeline.compute import cluster
from pipeline.compute.executor import in_segments
from pipeline.compute.worker_start import NETWORK_PRELOAD
from pipeline.jobs.reconstruct import Outcome
from stages.errors import InputError


def one_outcome_per_item(client, items, label):
    """A segment's work: an outcome per item, tagged with the segment process's pid (in ``error``)."""
    assert client.run(os.getpid)  # a live cluster of its own
    for start in items:
        yield Outcome(start, start, start + 1, 0, 0, f"{label} {os.getpid()}")


def refuses(client, items):
    raise InputError("the store went away")
    yield  # a generator, like the real work


def crashes(client, items):
    os._exit(3)
    yield


def test_each_segment_runs_in_its_own_process_and_streams_its_outcomes():
    work = functools.partial(one_outcome_per_item, label="seg")
    outcomes = list(in_segments(work, iter(range(5)), 2, workers=1, show_dashboard=False))
    assert [o.start for o in outcomes] == [0, 1, 2, 3, 4]
    pids = [int(o.error.split()[1]) for o in outcomes]
    assert len(set(pids)) == 3 and os.getpid() not in pids  # segments of 2, 2 and 1, each its own process
    assert pids[0] == pids[1] and pids[2] == pids[3] != pids[0]


def test_an_error_in_a_segment_is_the_job_s_error_and_a_crash_is_named():
    with pytest.raises(InputError, match="the store went away"):
        list(in_segments(refuses, range(3), 2, workers=1, show_dashboard=False))
    with pytest.raises(RuntimeError, match=r"segment process stopped \(exit code 3\).*--resume"):
        list(in_segments(crashes, range(3), 2, workers=1, show_dashboard=False))


def test_a_job_of_one_segment_runs_it_in_this_process_on_a_cluster_of_its_own():
    """Items that fit in one segment: no second interpreter, the same outcomes, a cluster closed with the job."""
    work = functools.partial(one_outcome_per_item, label="here")
    outcomes = list(in_segments(work, iter(range(3)), 3, workers=1, show_dashboard=False))
    assert [o.start for o in outcomes] == [0, 1, 2] and {o.error for o in outcomes} == {f"here {os.getpid()}"}
    assert list(in_segments(work, iter(()), 3, workers=1, show_dashboard=False)) == []
    with pytest.raises(InputError, match="the store went away"):  # the job's own error, as it raised it
        list(in_segments(refuses, range(3), 3, workers=1, show_dashboard=False))


def test_in_segments_hands_the_job_s_preload_to_its_segment_s_cluster(monkeypatch):
    """``in_segments(preload=...)`` reaches the segment's ``dask_client`` (a network job's: ``NETWORK_PRELOAD``;
    what the server then imports: test_gpu_cluster.py). A job of one segment, in this process: a spawned segment
    gets it through ``_segment``'s arguments, which no monkeypatch here reaches."""
    asked = []

    @contextlib.contextmanager
    def recorded_client(*, workers, preload=()):
        asked.append((workers, preload))
        yield None

    monkeypatch.setattr(cluster, "dask_client", recorded_client)
    assert list(in_segments(lambda client, items: iter(items), iter(range(2)), 2, workers=1, show_dashboard=False,
                            preload=NETWORK_PRELOAD)) == [0, 1]
    assert list(in_segments(lambda client, items: iter(items), iter(range(1)), 2, workers=1,
                            show_dashboard=False)) == [0]
    assert asked == [(1, NETWORK_PRELOAD), (1, ())]


def test_a_segment_whose_job_is_gone_before_it_starts_does_not_outlive_it():
    """A job killed while its segment's interpreter was still starting left the segment writing OUT for seconds,
    with no claim held (a user's sweep saw 300 more tasks committed after the kill): a process told its job's id
    exits at once when its parent is another (here: the job's id is one that is not its parent)."""
    import subprocess
    import sys

    code = "import os; from pipeline.compute.executor import _die_with_parent; _die_with_parent({}); print('alive')"
    gone = subprocess.run([sys.executable, "-c", code.format(1)], capture_output=True, text=True, timeout=120)
    assert gone.returncode == 1 and "alive" not in gone.stdout
    here = subprocess.run([sys.executable, "-c", code.format("os.getppid()")], capture_output=True, text=True,
                          timeout=120)
    assert here.returncode == 0 and here.stdout.strip() == "alive"
