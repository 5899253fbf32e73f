"""SIGTERM (``docker stop``, systemd, Kubernetes, ``kill``) during a command (issue #48, item 4).

It ended the process at once: a PNG export left a folder of a few frames that a rerun called "already exists",
the mp4 encoder kept running orphaned, and its temporary mp4 was left behind. SIGTERM now does what Ctrl-C does
(``pipeline.compute.stopping``): the clean-up runs, the command says ``error: terminated (SIGTERM)`` and exits 143.

Each test starts ``cscsr`` as a user does, with a ``TMPDIR`` of its own, waits until it is working (its output
appearing), sends SIGTERM once and checks: the process ends within seconds, non-zero, with that one line; no
process it started (recorded from the process table while it ran) is left; ``TMPDIR`` holds nothing but Dask's
shared lock files (what a finished run leaves too); beside OUT nothing reads as complete, and the same command
run again without ``--overwrite`` succeeds (``--resume`` for ``reconstruct`` and a parallel ``ingest``, whose
unfinished store is kept for it; the next ``watch --once`` for the ``watch`` service).
"""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest
import zarr

from tests.conftest import CSCSR, committed_tasks

STOP_SECONDS = 20  # from SIGTERM to the exit
DASK_LOCKS = {"dask-scratch-space", "dask-scratch-space/global.lock", "dask-scratch-space/purge.lock"}


Stopped = tuple[subprocess.CompletedProcess, float]  # the command's result, seconds from the signal to its exit


def ctrl_c_as_at_a_terminal() -> None:
    """In a child before it runs: SIGINT at its default, as a terminal's shell starts a command (a shell that runs
    this suite in the background, as `nohup make test &` does, starts it with SIGINT ignored, and Python keeps that)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def terminated_mid_work(args: list, ready, *, cwd, tmpdir, ctrl_c: bool = False, env: dict | None = None,
                        release=None, group: bool = False) -> Stopped:
    """Run ``cscsr -q ARGS`` in ``cwd`` with ``TMPDIR=tmpdir`` (and ``env`` added to its environment), SIGTERM it once
    ``ready()`` holds (``group``: its whole process group, workers too, as ``kill -- -PGID`` or a supervisor does;
    ``ctrl_c``: SIGINT to its whole process group, as a terminal's Ctrl-C), then create the file
    ``release`` if given (tasks held by :func:`held` go on: a task takes a while, not for ever); -> (its result,
    seconds from the signal to its exit), once every process it started (its descendants, sampled while it ran) is
    gone."""
    process = subprocess.Popen([CSCSR, "-q", *map(str, args)], cwd=cwd,
                               env={**os.environ, **(env or {}), "TMPDIR": str(tmpdir)},
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                               preexec_fn=ctrl_c_as_at_a_terminal)
    try:
        started, descendants = psutil.Process(process.pid), set()
        deadline = time.monotonic() + 120
        while not ready():
            assert process.poll() is None, f"it ended before it was stopped: {process.communicate()}"
            assert time.monotonic() < deadline, "it never got going"
            descendants |= set(_descendants(started))
            time.sleep(0.05)
        descendants |= set(_descendants(started))
        if ctrl_c or group:
            os.killpg(process.pid, signal.SIGINT if ctrl_c else signal.SIGTERM)
        else:
            process.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        if release is not None:
            open(release, "w").close()
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


DEFERRED = """
import os, signal, sys
from pipeline.compute.stopping import Terminated, interrupt_on, interrupts_deferred
interrupt_on(signal.SIGTERM)
try:
    with interrupts_deferred():
        os.kill(os.getpid(), signal.SIGTERM)
        print("the frame went out whole", flush=True)
    print("never: the block ended", flush=True)
except Terminated:
    print("terminated after the block", flush=True)
os.kill(os.getpid(), signal.SIGTERM)  # the handler is back: a second signal is ignored, as interrupt_on promises
print("still here")
"""


def test_an_interrupt_inside_a_deferred_write_is_raised_when_the_write_ends():
    """A frame piped to the mp4 encoder is never cut in two (the encoder then printed "Invalid buffer size" after
    the one line, CI 2026-11-27): the interrupt waits for the end of the block, then is raised as it would have
    been."""
    result = subprocess.run([sys.executable, "-c", DEFERRED], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["the frame went out whole", "terminated after the block", "still here"]


IN_A_FINALIZER = """
import os, signal, sys, time
from pipeline.compute.stopping import Terminated, interrupt_on
interrupt_on(signal.SIG{name})

class Dropped:
    def __del__(self):  # the signal's handler runs here, as it did in an asyncio Future's __del__
        os.kill(os.getpid(), signal.SIG{name})
        for _ in range(1000):
            pass

try:
    Dropped()
    for _ in range(200):
        time.sleep(0.01)  # the job going on
    print("finished: the interrupt was lost", flush=True)
except {raised}:
    print("stopped", flush=True)
"""


@pytest.mark.parametrize("name, raised", [("INT", "KeyboardInterrupt"), ("TERM", "Terminated")])
def test_an_interrupt_that_lands_in_a_finalizer_still_stops_the_job(name, raised):
    """Python drops an exception raised in ``__del__`` ("Exception ignored in"): a Ctrl-C that landed in one let
    `simulate` finish and exit 0 (CI 2026-11-27). It is delivered again, to the main thread."""
    code = IN_A_FINALIZER.format(name=name, raised=raised)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.stdout.splitlines() == ["stopped"], result.stderr
    assert "Exception ignored" not in result.stderr


BEFORE_A_CALL_BEGAN = """
import os, signal, threading, time
from distributed.utils import LoopRunner, sync
from pipeline.compute.stopping import Terminated, interrupt_on
interrupt_on(signal.SIGTERM)
runner = LoopRunner(asynchronous=False)
runner.start()
runner.loop.add_callback(time.sleep, 1.0)  # the event loop busy: the call below has not begun when SIGTERM comes
threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGTERM)).start()

async def never_begun():
    return 1

try:
    sync(runner.loop, never_begun)
except Terminated:
    time.sleep(1.5)  # the loop runs the call's clean-up (its cancel) meanwhile
    print("terminated", flush=True)
runner.stop()
"""


def test_an_interrupt_before_a_dask_call_began_prints_no_traceback_of_dask_s():
    """Dask's clean-up of a call into the client that an interrupt cut short before it began reads a future never
    assigned: Tornado logged that NameError with its traceback before the command's one line (a SIGTERM'd
    simulate, CI 2026-11-29). The process that handles interrupts drops that one error."""
    result = subprocess.run([sys.executable, "-c", BEFORE_A_CALL_BEGAN], capture_output=True, text=True, timeout=60)
    assert result.stdout.splitlines() == ["terminated"], result.stderr
    assert "NameError" not in result.stderr and "Traceback" not in result.stderr, result.stderr


UNSTARTED_COROUTINE = """
import signal, sys
from pipeline.compute.stopping import interrupt_on, quiet_finalizers
if sys.argv[1] == "interrupted":
    interrupt_on(signal.SIGTERM)
    quiet_finalizers()

async def read():
    return 1

pending = read()  # a zarr read the interrupt cut short before it began
print("exiting", flush=True)
"""


@pytest.mark.parametrize("interrupted", [True, False])
def test_a_read_cut_short_before_it_began_prints_nothing_after_the_one_line(interrupted):
    """A SIGTERM'd export printed "RuntimeWarning: coroutine 'AsyncArray._get_selection' was never awaited" after the
    command's one line (CI 2026-11-30): a process that handles the interrupt drops that warning on its way out;
    without an interrupt it is kept, since it then means a bug."""
    argument = "interrupted" if interrupted else "running"
    result = subprocess.run([sys.executable, "-c", UNSTARTED_COROUTINE, argument], capture_output=True, text=True,
                            timeout=60)
    assert result.stdout.splitlines() == ["exiting"], result.stderr
    assert ("was never awaited" in result.stderr) is not interrupted, result.stderr


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


@pytest.mark.parametrize("group,ctrl_c", [(False, False), (True, False), (False, True)])
def test_sigterm_during_a_dry_run_is_said_as_such_and_leaves_nothing(spikes, tmp_path, tmpdir_of_its_own, group,
                                                                     ctrl_c):
    """A dry run stopped while its sampled tasks run: to the whole process group, its workers went with the signal
    and the cleanup's lost connection (CommClosedError, exit 1) was said instead of the signal; Ctrl-C printed
    asyncio's "never retrieved" AllExit first; a task still running could write its scratch folder back."""
    from pipeline.compute.hold import hold_environment

    release = tmp_path / "release"
    scratch = lambda: [name for name in os.listdir(tmpdir_of_its_own) if name.startswith("cscsr-dry-run-")]  # noqa: E731
    args = ["reconstruct", spikes, tmp_path / "out.zarr", "--workers", 2, "--every", 5, "--dry-run"]
    result, seconds = terminated_mid_work(args, lambda: scratch() and os.listdir(tmpdir_of_its_own / scratch()[0]),
                                          cwd=tmp_path, tmpdir=tmpdir_of_its_own, group=group, release=release,
                                          env=hold_environment(0, release), ctrl_c=ctrl_c)
    if ctrl_c:
        assert_stopped(result, seconds, status=130, line="error: interrupted")
    else:
        assert_stopped(result, seconds)
    assert sorted(os.listdir(tmp_path)) == ["release", "tmp"] and temporary_files(tmpdir_of_its_own) == set()


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


def held(tmp_path, after: int = 3) -> dict:
    """The environment that holds a job's tasks after the ``after``-th of each process (pipeline.compute.hold) until
    the file ``tmp_path/release`` exists (``terminated_mid_work(release=...)`` creates it after the signal): the signal
    lands mid-job on any machine, under any load."""
    from pipeline.compute.hold import hold_environment

    return hold_environment(after, tmp_path / "release")


@pytest.mark.parametrize("workers", [None, 2], ids=["one-process", "workers-2"])
def test_sigterm_during_ingest_removes_or_keeps_its_store_for_resume(tmp_path, tmpdir_of_its_own, workers):
    """A one-process ingest removes its unfinished store (a rerun succeeds); a parallel one keeps what it committed,
    never "complete", and ``--resume`` finishes it. 8 tasks of 2340 frames of 128x112. The parallel one's held tasks
    are never released: a task still running at the signal, for longer than the workers' nannies wait, which kill
    them; their ``worker-*.dirlock`` files in Dask's scratch space were left (purged after the cluster now)."""
    from pipeline.stores.spike_store import open_spike_store
    from tests.test_parallel_ingest import random_dat

    random_dat(tmp_path / "c.dat", 16384, 128 * 128 // 8, seed=1)
    work = tmp_path / "work"
    work.mkdir()
    args = ["ingest", tmp_path / "c.dat", "s.zarr", "--height", 128, "--width", 112, "--head-columns", 16, "--flip",
            "--cfa", "gbrg", "--task-frames", 2340, *(["--workers", workers] if workers else [])]
    result, seconds = terminated_mid_work(args, lambda: committed_tasks(work / "s.zarr") >= 3, cwd=work,
                                          tmpdir=tmpdir_of_its_own, env=held(tmp_path),
                                          release=None if workers else tmp_path / "release")
    assert_stopped(result, seconds)
    assert temporary_files(tmpdir_of_its_own) == set()
    if workers:
        assert os.listdir(work) == ["s.zarr"]  # kept for --resume, no claim left beside it
        assert open_spike_store(str(work / "s.zarr"), allow_incomplete=True).attrs["state"] == "writing"
        args.append("--resume")
    else:
        assert os.listdir(work) == []  # the unfinished store removed
    again = subprocess.run([CSCSR, "-q", *map(str, args)], cwd=work, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert open_spike_store(str(work / "s.zarr")).attrs["state"] == "complete"


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> str:
    """A small simulated spike store with ground truth: 250 frames of 32x32 LR pixels, 6 truth frames."""
    import imageio.v3 as iio

    from pipeline.jobs.simulate import SimulateOptions, simulate
    from tests.test_simulate import picture

    folder = tmp_path_factory.mktemp("sigterm-simulated")
    iio.imwrite(folder / "scene.png", picture("coffee", 128))
    simulate(str(folder / "scene.png"), str(folder / "scene.zarr"),
             SimulateOptions(scale=4, frames=250, motion="random", speed=0.3), workers=1, progress=False)
    return str(folder / "scene.zarr")


def test_sigterm_during_evaluate_removes_its_out_folder(simulated, tmp_path, tmpdir_of_its_own):
    work = tmp_path / "work"
    work.mkdir()
    args = ["evaluate", simulated, "--methods", "tfp,tfi", "--out", "ev", "--workers", 2]
    # 6 tasks (truth frames) of tfp: each worker holds after its 1st
    result, seconds = terminated_mid_work(args, lambda: committed_tasks(work / "ev" / "tfp.zarr") >= 2, cwd=work,
                                          tmpdir=tmpdir_of_its_own, env=held(tmp_path, after=1),
                                          release=tmp_path / "release")
    assert_stopped(result, seconds)
    assert os.listdir(work) == []  # no --out folder, no claim beside it
    assert temporary_files(tmpdir_of_its_own) == set()

    again = subprocess.run([CSCSR, "-q", *map(str, args)], cwd=work, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr  # not "already exists"
    assert {"metrics.csv", "summary.csv", "comparison.png"} <= set(os.listdir(work / "ev"))


def test_sigterm_during_watch_leaves_the_recording_resumable_and_the_next_pass_finishes_it(simulated, tmp_path,
                                                                                           tmpdir_of_its_own):
    """The service (no ``--once``) SIGTERMed while it reconstructs: its ledger keeps the recording to retry, no video
    reads as made, and ``watch --once`` finishes it."""
    import shutil

    from pipeline.inbox.ledger import Ledger
    from tests.test_watch import _ledger_state, settled

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    shutil.copytree(simulated, inbox / "scene.zarr")
    settled(inbox)
    args = ["watch", inbox, outbox, "--interval", "1s", "--workers", 2, "--every", 5, "--tile", 16, "--settle", 0]
    result, seconds = terminated_mid_work(args, lambda: (_ledger_state(outbox, "scene") == "running"
                                                         and committed_tasks(outbox / "scene.zarr") >= 3),
                                          cwd=tmp_path, tmpdir=tmpdir_of_its_own, env=held(tmp_path),
                                          release=tmp_path / "release")
    assert_stopped(result, seconds)
    assert temporary_files(tmpdir_of_its_own) == set()
    assert _ledger_state(outbox, "scene") == "running"  # as after a kill: the next pass takes it up again
    assert sorted(os.listdir(outbox)) == [".watch.lock", "ledger.sqlite", "scene.zarr"]  # no video that reads as made
    assert zarr.open_group(str(outbox / "scene.zarr"), mode="r").attrs["state"] == "writing"

    once = [arg for arg in map(str, args) if arg not in ("--interval", "1s")] + ["--once"]
    again = subprocess.run([CSCSR, "-q", *once], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert [(row.name, row.state, row.attempts) for row in Ledger(outbox).rows()] == [("scene", "done", 2)]
    assert os.path.getsize(outbox / "scene.mp4") > 0


def test_sigterm_during_make_testset_removes_the_folder_and_its_claim(tmp_path, tmpdir_of_its_own):
    """Stopped in its first picture's simulation (each store has a cluster of its own, with a task or two per worker:
    every task held from the first, the first store created): no folder, no claim (both would be in ``work``), so a
    new run needs no ``--overwrite``. (Making the set in full, nine stores, is tests/test_testset.py's.)"""
    work = tmp_path / "work"
    work.mkdir()
    args = ["make-testset", "set", "--workers", 2]
    result, seconds = terminated_mid_work(args, lambda: os.path.isdir(work / "set" / "astronaut_a0.6.zarr" / "spikes"),
                                          cwd=work, tmpdir=tmpdir_of_its_own, env=held(tmp_path, after=0),
                                          release=tmp_path / "release")
    assert_stopped(result, seconds)
    assert os.listdir(work) == []  # the unfinished test set removed, its claim released
    assert temporary_files(tmpdir_of_its_own) == set()


def test_sigterm_during_train_keeps_its_checkpoint_and_resume_goes_on(tmp_path, tmpdir_of_its_own, cli):
    """A training run (a long job on one machine) stopped once it has checkpointed: exit 143, no half-written
    checkpoint or weights file, and --resume goes on from the checkpoint it kept (run in this process: what it goes
    on from is only what the stopped process left on disk)."""
    work = tmp_path / "work"
    work.mkdir()
    args = ["train", "run", "--steps", "400", "--batch", "2", "--lr-side", "16", "--checkpoint-every", "2",
            "--validate-every", "100", "--validation-clips", "1", "--warmup", "2", "--pool", "4"]
    checkpoint = work / "run" / "checkpoint.safetensors"
    stopped, seconds = terminated_mid_work(args, checkpoint.exists, cwd=work, tmpdir=tmpdir_of_its_own)
    assert_stopped(stopped, seconds)
    assert checkpoint.exists() and not list(work.rglob("*.partial"))
    # torch's compile cache (torchinductor_USER) is kept by every run, interrupted or not: a cache, not a leftover
    assert not {name for name in temporary_files(tmpdir_of_its_own) if not name.startswith("torchinductor_")}
    assert not (work / "run" / "cscsr-lite.safetensors").exists()  # no final weights of a run that did not end
    # to step 6: on from the checkpoint the stopped run kept (step 2's, or step 4's had the signal come late)
    again = cli("-q", args[0], work / args[1], args[2], "6", *args[4:], "--resume")
    assert again.exit_code == 0, again.stderr
    assert (work / "run" / "cscsr-lite.safetensors").exists()
