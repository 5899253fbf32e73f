"""Ctrl-C leftovers, and the store an interrupted ``simulate`` leaves (issue #48, rough edges).

Ctrl-C is SIGINT to the command's whole process group, as a terminal sends it (``terminated_mid_work(ctrl_c=True)``
of ``test_sigterm``). Each test checks: the command ends within seconds with status 130 and the one line ``error:
interrupted`` (no traceback, nothing from worker processes, no "leaked semaphore objects" from multiprocessing's
resource tracker, which shares the command's standard error); beside OUT nothing is left (no output, no ``--out``
folder holding only its marker, no claim); no process it started is left running.

- ``simulate`` mid-work: a 35-line traceback was reported; it held in every run here before this change too.
- ``evaluate`` as its cluster starts: each worker process still importing printed a ``KeyboardInterrupt``
  traceback of its own (dozens of lines). Worker
  processes of a command now ignore Ctrl-C from their first import of ``pipeline.compute.stopping`` (before anything slow,
  checked with ``-X importtime``: a Ctrl-C sent as workers start cannot be timed reliably on a loaded machine), and
  share one resource tracker that the command starts deaf to Ctrl-C; the command closes them. CPU workers are now
  forked from a server that the command starts deaf to Ctrl-C, and begin with it ignored. Not held: a spawned (GPU)
  worker still in the interpreter's own start (tens of milliseconds on an idle machine, more on a loaded one), where
  Python sets up Ctrl-C before any code of ours runs (docs/reliability.md, "Known gaps").
- ``evaluate`` mid-work, its ``--out`` folder written: nothing of it is left (it held here before this change too).

A store left in state "writing" (a ``simulate`` killed outright) is named as the incomplete leftover of an
interrupted ``simulate``, with what to do (``--overwrite``), not only "already exists".
"""

import os
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import zarr

from pipeline.compute.stopping import COMMAND_LINE
from tests.conftest import CSCSR
from tests.reliability.test_sigterm import (assert_stopped, ctrl_c_as_at_a_terminal, terminated_mid_work,  # noqa: F401
                                           tmpdir_of_its_own)
from tests.test_bad_input import assert_refused


@pytest.fixture(scope="module")
def still(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("interrupted") / "still.png"
    iio.imwrite(path, np.random.default_rng(0).integers(0, 256, (64, 64, 3), np.uint8))
    return str(path)


@pytest.fixture(scope="module")
def with_truth(still, tmp_path_factory) -> str:
    """A simulated spike store of 600 frames with ground truth every 41 frames: something to evaluate."""
    path = tmp_path_factory.mktemp("interrupted-truth") / "s.zarr"
    made = subprocess.run([CSCSR, "-q", "simulate", still, str(path), "--motion", "random", "--frames", "600",
                           "--workers", "1"], capture_output=True, text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    return str(path)


def assert_interrupted(result, seconds: float, work) -> None:
    assert_stopped(result, seconds, status=130, line="error: interrupted")
    assert os.listdir(work) == []  # no output, no folder holding only its marker, no claim


def test_ctrl_c_during_simulate_is_one_line_and_leaves_nothing(still, tmp_path, tmpdir_of_its_own):  # noqa: F811
    work = tmp_path / "work"
    work.mkdir()
    args = ["simulate", still, "sim.zarr", "--motion", "random", "--frames", 2000, "--chunk-frames", 50, "--workers", 2]

    def chunks_written() -> int:
        return sum(len(files) for _, _, files in os.walk(work / "sim.zarr" / "spikes"))

    result, seconds = terminated_mid_work(args, lambda: chunks_written() >= 3, cwd=work, tmpdir=tmpdir_of_its_own,
                                          ctrl_c=True)
    assert_interrupted(result, seconds, work)


def test_ctrl_c_during_evaluate_is_one_line_and_leaves_no_out_folder(with_truth, tmp_path,
                                                                     tmpdir_of_its_own):  # noqa: F811
    work = tmp_path / "work"
    work.mkdir()
    args = ["evaluate", with_truth, "--methods", "tfp", "--out", "ev", "--workers", 2]
    result, seconds = terminated_mid_work(args, lambda: os.path.isdir(work / "ev" / "tfp.zarr"), cwd=work,
                                          tmpdir=tmpdir_of_its_own, ctrl_c=True)  # its reconstruction under way
    assert_interrupted(result, seconds, work)


def imports(env: dict, *args: str) -> subprocess.CompletedProcess:
    """``python -X importtime -c 'import pipeline.cli' ARGS`` with ``env`` added: what a worker process of the
    command does first as multiprocessing spawns it (``--multiprocessing-fork``), the command's script being its
    main module; prints whether SIGINT still raises KeyboardInterrupt."""
    code = "import signal, pipeline.cli; print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)"
    return subprocess.run([sys.executable, "-X", "importtime", "-c", code, *args], capture_output=True, text=True,
                          env={**os.environ, **env}, timeout=60, preexec_fn=ctrl_c_as_at_a_terminal)


def test_a_worker_of_the_command_ignores_ctrl_c_before_its_slow_imports():
    """Ctrl-C as a command's cluster starts: each worker process, importing the command's modules (typer, Dask) for a
    second or more, printed a KeyboardInterrupt traceback of its own. It now ignores Ctrl-C from its first import of
    ``pipeline.compute.stopping``, which ``pipeline.cli`` makes before anything else."""
    worker = imports({COMMAND_LINE: "1"}, "--multiprocessing-fork")
    assert worker.returncode == 0, worker.stderr
    assert worker.stdout.strip() == "False"
    modules = [line.rsplit("|", 1)[-1].strip() for line in worker.stderr.splitlines() if "|" in line]
    assert modules.index("pipeline.compute.stopping") < min(modules.index(name) for name in ("json", "typer", "rich"))
    assert imports({COMMAND_LINE: "1"}).stdout.strip() == "True"  # the command itself: Ctrl-C as before
    assert imports({}, "--multiprocessing-fork").stdout.strip() == "True"  # processes of the Python API's callers


FIRST_HANDLER = """
import multiprocessing, signal, sys
from pipeline.compute.worker_start import forked_workers

def report(queue):
    queue.put(signal.getsignal(signal.SIGINT) is signal.default_int_handler)

if __name__ == "__main__":
    forked_workers()
    context = multiprocessing.get_context("forkserver")
    queue = context.Queue()
    process = context.Process(target=report, args=(queue,))
    process.start()
    print(queue.get(timeout=60))
    process.join()
"""


def test_a_worker_forked_for_a_command_ignores_ctrl_c_from_its_first_instruction(tmp_path):
    """A local cluster's CPU workers are forked from one server (pipeline.compute.worker_start.forked_workers): a
    command's server starts deaf to Ctrl-C and preloads pipeline.compute.stopping, so a worker forked from it
    begins with Ctrl-C ignored, not only from its first import (the known gap of a spawned worker's interpreter
    start). Outside a command (the Python API) a forked worker begins with Python's default, as a spawned one."""
    script = tmp_path / "first_handler.py"  # a file: the forked process finds report() in it
    script.write_text(FIRST_HANDLER)

    def handler_is_default(env: dict) -> str:
        done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                              env={**os.environ, **env}, timeout=60, preexec_fn=ctrl_c_as_at_a_terminal)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()

    assert handler_is_default({COMMAND_LINE: "1"}) == "False"
    assert handler_is_default({}) == "True"


def test_simulate_over_its_own_interrupted_store_says_what_it_is_and_what_to_do(still, tmp_path, cli):
    out = tmp_path / "sim.zarr"
    args = ["simulate", still, out, "--motion", "static", "--frames", 100, "--workers", 1]
    assert cli(*args).exit_code == 0
    zarr.open_group(str(out), mode="r+").attrs["state"] = "writing"  # as a simulate killed outright leaves it
    assert_refused(cli(*args), f"output {out} already exists: an incomplete spike store (state 'writing'), the "
                               "leftover of an interrupted simulate; pass --overwrite to replace it")
    assert cli(*args, "--overwrite").exit_code == 0
    assert zarr.open_group(str(out), mode="r").attrs["state"] == "complete"
