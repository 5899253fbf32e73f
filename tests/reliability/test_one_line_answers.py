"""Answers that are one line and name the file (issue #34, point 8).

Each case is the reproduction from the issue: a usage error, a zero-frame store, a corrupt training
picture, a damaged checkpoint, an output that has no place to go (under a regular file, in a folder
that cannot be written), a full disk, S3 errors, ``CSCSR_DEBUG=0``, a watcher started without its
INBOX or its weights, and a recording still being written under ``--settle 0``. Each must end with
one line on stderr starting ``error:`` that names the problem (and the file, where there is one),
exit status 1, and nothing created.
"""

import contextlib
import os
import shutil
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from cscsr import samples
from tests.reliability.test_numbers import assert_nothing_made, fingerprint

FRAMES, HEIGHT, WIDTH = 100, 16, 16
REDS = {"height": samples.REDS_HEIGHT, "width": samples.REDS_WIDTH, "cfa": "mono", "flip": True}


def one_line(result, *fragments) -> str:
    """The answer of a refused command: status 1 and one line ``error: ...`` holding every fragment."""
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1, (result.exit_code, result.stderr)
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def store(cli, tmp_path):
    """A complete 100-frame 16x16 RGGB spike store."""
    capture = tmp_path / "c.npy"
    np.save(capture, (np.random.default_rng(0).random((FRAMES, HEIGHT, WIDTH)) < 0.2).astype(np.uint8))
    path = tmp_path / "s.zarr"
    assert cli("ingest", capture, path, "--cfa", "rggb").exit_code == 0
    os.remove(capture)
    return path


def _mount_tmpfs(path, options: str) -> bool:
    """Mount a tmpfs at ``path`` (root with the right to mount only); whether it worked."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    os.makedirs(path, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True)
    return done.returncode == 0


def _unmount(path) -> None:
    subprocess.run(["umount", "-l", str(path)], capture_output=True)


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder this process cannot write: chmod 0o500 for a user; as root (whom permissions do not stop),
    a read-only tmpfs, or skipped where mounting is not allowed."""
    folder = tmp_path / "locked"
    if os.geteuid() != 0:
        folder.mkdir()
        folder.chmod(0o500)
        yield folder
        folder.chmod(0o700)
    elif _mount_tmpfs(folder, "ro,size=64k"):
        yield folder
        _unmount(folder)
    else:
        pytest.skip("running as root, where chmod does not stop writes, and no tmpfs may be mounted here")


# --- usage errors: one line, status 1 ----------------------------------------------------------------

@pytest.mark.parametrize("args, fragments", [  # the program is "root" in Typer's test runner, "cscsr" installed
    (["info", "--bogus", "{store}"], [" info: no such option: --bogus", " info --help)"]),
    (["reconstruct", "{store}", "{out}", "--every", "abc"],
     [" reconstruct: invalid value for '--every'", "'abc'", " reconstruct --help)"]),
    (["reconstruct", "{store}", "{out}", "--every"], [" reconstruct: option '--every' requires an argument"]),
    (["info"], [" info: missing argument"]),
    (["nocommand"], ["no such command 'nocommand'"]),
    (["--bogus", "info", "{store}"], ["no such option: --bogus"]),
])
def test_a_usage_error_is_one_line_and_status_1(cli, tmp_path, store, args, fragments):
    out = tmp_path / "out.zarr"
    before = set(os.listdir(tmp_path))
    one_line(cli(*[a.format(store=store, out=out) for a in args]), *fragments)
    assert_nothing_made(tmp_path, before, out)


def test_help_still_works_and_a_usage_error_exits_1_from_the_installed_command(cli, cli_process, tmp_path):
    for args in (["--help"], ["reconstruct", "--help"]):
        result = cli(*args)
        assert result.exit_code == 0 and "Usage" in result.stdout, result.stderr
    process = cli_process("reconstruct", tmp_path / "s.zarr", tmp_path / "v.zarr", "--every", "abc")
    assert process.returncode == 1 and process.stdout == ""
    assert process.stderr.startswith("error: cscsr reconstruct: invalid value for '--every'")
    assert process.stderr.count("\n") == 1 and "╭" not in process.stderr
    assert os.listdir(tmp_path) == []


# --- info of a zero-frame store --------------------------------------------------------------------

def test_info_of_a_zero_frame_spike_store_is_one_line(cli, tmp_path):
    from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter

    path = tmp_path / "empty.zarr"
    writer = SpikeStoreWriter(str(path), SpikeMeta(HEIGHT, WIDTH, "rggb"), 0, chunk_frames=10)
    writer.finish(spike_count=0)
    for flags in ([], ["--json"]):
        one_line(cli("info", path, *flags), f"{path} is a spike store of 0 frames", "no spikes")


# --- training: corrupt pictures and damaged checkpoints, named ------------------------------------

def test_a_corrupt_training_picture_is_named(cli, tmp_path):
    import imageio.v3 as iio

    pictures = tmp_path / "pictures"
    pictures.mkdir()
    iio.imwrite(pictures / "good.png", (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8))
    (pictures / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"cut short")
    out = tmp_path / "run"
    before = set(os.listdir(tmp_path))
    one_line(cli("train", out, "--pictures", pictures, "--steps", 1), f"training picture {pictures / 'bad.png'}",
             "cannot be used")
    assert_nothing_made(tmp_path, before, out)


def _checkpoint_cut_short(path) -> None:
    """A real-looking checkpoint (tensors, training metadata) whose last bytes are lost."""
    import torch
    from safetensors.torch import save_file

    save_file({"model.w": torch.zeros(64, 64)}, str(path), metadata={"step": "1", "options": "{}",
                                                                     "param_groups": "[]"})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("damage, said", [
    ("garbage", "is damaged: "),
    ("cut", "is damaged: "),
    ("no metadata", "it is damaged or not a cscsr training checkpoint"),
])
def test_resuming_from_a_damaged_checkpoint_names_it(cli, tmp_path, damage, said):
    import torch
    from safetensors.torch import save_file

    run = tmp_path / "run"
    run.mkdir()
    checkpoint = run / "checkpoint.safetensors"
    if damage == "garbage":
        checkpoint.write_bytes(b"not a checkpoint at all")
    elif damage == "cut":
        _checkpoint_cut_short(checkpoint)
    else:
        save_file({"model.w": torch.zeros(3)}, str(checkpoint))
    unchanged = fingerprint(run)
    one_line(cli("train", run, "--resume"), str(checkpoint), said)
    assert fingerprint(run) == unchanged


def test_a_damaged_portable_part_and_a_damaged_init_file_are_named(cli, tmp_path):
    from cscsr.weights.weights_io import default_weights

    run = tmp_path / "carried"
    run.mkdir()
    part = run / "checkpoint.part-1-of-1.safetensors"
    part.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json")
    unchanged = fingerprint(run)
    one_line(cli("train", run, "--resume"), f"portable checkpoint part {part} is damaged")
    assert fingerprint(run) == unchanged

    weights = tmp_path / "cut.safetensors"
    weights.write_bytes(open(default_weights("lite"), "rb").read()[:100_000])
    out = tmp_path / "fresh"
    before = set(os.listdir(tmp_path))
    one_line(cli("train", out, "--init", weights), f"{weights} is damaged")
    assert_nothing_made(tmp_path, before, out)


# --- outputs with no place to go --------------------------------------------------------------------

@pytest.mark.parametrize("command", ["reconstruct", "ingest", "preview", "export", "train", "make-testset",
                                     "watch"])
def test_an_output_under_a_regular_file_is_not_a_folder(cli, tmp_path, store, command):
    (tmp_path / "file.txt").write_text("mine\n")
    (tmp_path / "inbox").mkdir()
    target = tmp_path / "file.txt" / "deeper" / "out"
    args = {"reconstruct": [store, f"{target}.zarr", "--workers", 1], "ingest": [store, f"{target}.zarr"],
            "preview": [store, f"{target}.png"], "export": [store, f"{target}.dat"], "train": [target],
            "make-testset": [target, "--workers", 1], "watch": [tmp_path / "inbox", target, "--once"]}[command]
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    one_line(cli(command, *args), f"{tmp_path / 'file.txt'} is a file, not a folder")
    assert_nothing_made(tmp_path, before)
    assert (tmp_path / "file.txt").read_text() == "mine\n" and fingerprint(store) == unchanged


def test_a_watcher_whose_outbox_cannot_be_written_is_refused(cli, tmp_path, read_only_folder):
    (tmp_path / "inbox").mkdir()
    for outbox in (read_only_folder, read_only_folder / "outbox"):
        one_line(cli("watch", tmp_path / "inbox", outbox, "--once"), f"cannot write {outbox}",
                 f"the folder {read_only_folder} is not writable")
    assert os.listdir(read_only_folder) == []


# --- a full disk: one cause, named once --------------------------------------------------------------

FULL_DISK_THEN_ANOTHER_ERROR = """
import errno, os, sys, time
from distributed import wait
from pipeline.compute.cluster import dask_client

def write(code):
    raise OSError(code, os.strerror(code))

if __name__ == "__main__":
    with dask_client(workers=1) as client:
        full = [client.submit(write, errno.ENOSPC, pure=False) for _ in range(5)]
        wait(full)
        time.sleep(0.5)
        print("--- another error ---", file=sys.stderr, flush=True)
        other = client.submit(write, errno.EIO, pure=False)
        wait(other)
        time.sleep(0.5)
        assert [f.status for f in full + [other]] == ["error"] * 6
"""


def test_worker_logs_drop_per_task_tracebacks_of_a_full_disk_only(tmp_path):
    """On the real workers of a local cluster (the filter is installed there), whose logs reach the standard error
    of the process that started the cluster: tasks that run out of space log nothing (the job names the cause once);
    any other OSError still logs its traceback."""
    script = tmp_path / "full_disk.py"
    script.write_text(FULL_DISK_THEN_ANOTHER_ERROR)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    quiet, loud = done.stderr.split("--- another error ---")
    assert "Compute Failed" not in quiet and "No space left" not in quiet, quiet
    assert "Compute Failed" in loud and "Input/output error" in loud


def test_a_job_that_fails_for_one_cause_names_it_once():
    from pipeline.jobs.reconstruct import JobIncomplete

    full = "[Errno 28] No space left on device"
    every = JobIncomplete("/full/out.zarr", {i: f"tile ({i % 2}, 0): {full}" for i in range(30)}, 30)
    message = str(every)
    assert message.count("No space left") == 1 and f"each: {full}" in message
    assert message.startswith("30 of 30 output frames failed (frames 0, 1,") and "/full/out.zarr" in message
    assert "the other frames are committed" not in message  # there are none
    some = str(JobIncomplete("o.zarr", {3: "tile (0, 0): a", 4: "tile (0, 1): b"}, 10))
    assert "frame 3: tile (0, 0): a" in some and "the other frames are committed in o.zarr" in some


def test_a_full_disk_is_one_line(cli, cli_process, tmp_path):
    """The issue's reproduction on a real full file system (a 64 KiB tmpfs): the job's answer is the
    dashboard link and one error line naming the cause once, not a traceback per task."""
    capture, spikes = tmp_path / "c.npy", tmp_path / "s.zarr"
    np.save(capture, (np.random.default_rng(0).random((120, 32, 32)) < 0.3).astype(np.uint8))
    assert cli("ingest", capture, spikes, "--cfa", "rggb").exit_code == 0
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "size=64k"):
        pytest.skip("no tmpfs may be mounted here (needs root and the right to mount)")
    try:
        run = cli_process("-q", "reconstruct", spikes, disk / "out.zarr", "--every", 10, "--tile", 16, "--workers", 1)
    finally:
        _unmount(disk)
    lines = [line for line in run.stderr.splitlines() if line.strip() and not line.startswith("dashboard: ")]
    assert run.returncode == 1 and len(lines) == 1, run.stderr[-3000:]
    assert lines[0].startswith("error: ") and lines[0].count("No space left on device") == 1, lines[0]


# --- S3 errors: no "Exception ignored" after the one line ----------------------------------------

def test_requests_in_flight_at_exit_end_quietly():
    """The mechanism, deterministically: a request still inside aiobotocore's context (as s3fs's are,
    retrying) on zarr's event loop when the command exits used to print "Exception ignored ... was
    created in a different Context" with its traceback."""
    code = """
import asyncio, time
import pipeline.stores.storage
from aiobotocore.context import start_as_current_context
from zarr.core.sync import _get_loop

async def in_flight():
    async with start_as_current_context():
        await asyncio.sleep(60)

asyncio.run_coroutine_threadsafe(in_flight(), _get_loop())
time.sleep(0.2)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    assert done.returncode == 0 and done.stderr == "", done.stderr


class _ClosingS3(BaseHTTPRequestHandler):
    """An S3 endpoint whose bucket answers and whose objects drop the connection (retried, then failed)."""

    def log_message(self, *args) -> None:
        pass

    def _answer(self) -> None:
        if self.path.split("?")[0].rstrip("/").count("/") <= 1:
            self.send_response(200)
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        self.close_connection = True
        with contextlib.suppress(OSError):
            self.connection.shutdown(2)

    do_HEAD = do_GET = _answer


def test_an_s3_error_is_one_line(cli_process, tmp_path):
    server = ThreadingHTTPServer(("127.0.0.1", 0), _ClosingS3)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        env = {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1",
               "AWS_CONFIG_FILE": os.devnull, "AWS_SHARED_CREDENTIALS_FILE": os.devnull,
               "FSSPEC_S3_ENDPOINT_URL": f"http://127.0.0.1:{server.server_address[1]}",
               "FSSPEC_S3_CONFIG_KWARGS": '{"retries": {"mode": "standard", "total_max_attempts": 2}}'}
        run = cli_process("info", "s3://bucket/s.zarr", env=env)
    finally:
        server.shutdown()
    assert run.returncode == 1 and run.stdout == ""
    assert run.stderr.count("\n") == 1 and run.stderr.startswith("error: "), run.stderr[-3000:]
    assert "Exception ignored" not in run.stderr and "different Context" not in run.stderr


# --- CSCSR_DEBUG=0 is off -----------------------------------------------------------------------------

def test_cscsr_debug_zero_does_not_turn_debugging_on(cli, tmp_path, monkeypatch):
    from pipeline.cli import debugging

    for value, on in [("1", True), ("true", True), ("YES", True), (" yes ", True), ("0", False), ("false", False),
                      ("no", False), ("", False), ("off", False)]:
        monkeypatch.setenv("CSCSR_DEBUG", value)
        assert debugging() is on, value
    monkeypatch.setenv("CSCSR_DEBUG", "0")
    one_line(cli("info", tmp_path / "missing.zarr"), str(tmp_path / "missing.zarr"))
    monkeypatch.setenv("CSCSR_DEBUG", "1")
    with pytest.raises(Exception):  # the traceback, as asked
        cli("info", tmp_path / "missing.zarr")


# --- the watcher: refused before it starts, and a file still being written ---------------------------

def test_a_watcher_without_its_inbox_creates_nothing(cli, tmp_path):
    outbox = tmp_path / "outbox"
    (tmp_path / "notes.txt").write_text("x")
    before = set(os.listdir(tmp_path))
    one_line(cli("watch", tmp_path / "missing", outbox, "--once"), f"inbox {tmp_path / 'missing'} does not exist")
    one_line(cli("watch", tmp_path / "notes.txt", outbox, "--once"), "is a file, not a folder")
    assert_nothing_made(tmp_path, before, outbox)


def test_a_watcher_whose_weights_are_missing_or_damaged_does_not_start(cli, tmp_path):
    from cscsr.weights.weights_io import default_weights

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    (inbox / "a.dat").write_bytes(b"\x00" * 1000)
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(open(default_weights("lite"), "rb").read()[:100_000])
    before = set(os.listdir(tmp_path))
    one_line(cli("watch", inbox, outbox, "--once", "--method", "cscsr", "--settle", 0,
                 "--weights", tmp_path / "missing.safetensors"), "missing.safetensors not found")
    one_line(cli("watch", inbox, outbox, "--once", "--method", "cscsr", "--settle", 0, "--weights", cut),
             f"{cut} is damaged")
    assert_nothing_made(tmp_path, before, outbox)  # no OUTBOX, so no ledger with the recording burnt


def test_settle_zero_never_takes_a_file_still_being_written(tmp_path):
    """--settle 0: a capture still growing is left for a later pass (its size changes between two looks a
    second apart); one written just before the pass and finished is taken in that pass."""
    from pipeline.inbox.ledger import Ledger
    from pipeline.inbox.watch import WatchOptions, watch_once

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    reds = open(samples.path(samples.REDS_DAT), "rb").read()
    growing = inbox / "growing.dat"
    stop = threading.Event()

    def write_slowly() -> None:
        with open(growing, "wb") as handle:
            for start in range(0, len(reds), 4096):
                handle.write(reds[start:start + 4096])
                handle.flush()
                if stop.wait(0.05):
                    return

    writer = threading.Thread(target=write_slowly)
    writer.start()
    try:
        time.sleep(0.2)
        counts = watch_once(str(inbox), str(outbox), WatchOptions(settle=0), client=None)
    finally:
        stop.set()
        writer.join()
    assert counts == {"processed": 0, "waiting": 1, "skipped": 0, "refused": 0}
    assert Ledger(outbox).rows() == []  # never fingerprinted into the ledger, never ingested half-written

    os.remove(growing)
    (inbox / "landed.dat").write_bytes(reds[:50_000])  # finished just now: not whole frames, refused on ingest
    (inbox / "landed.json").write_text('{"height": %d, "width": %d, "cfa": "mono"}' % (REDS["height"], REDS["width"]))
    counts = watch_once(str(inbox), str(outbox), WatchOptions(settle=0), client=None)
    assert counts["refused"] == 1 and counts["waiting"] == 0
    (row,) = Ledger(outbox).rows()
    assert (row.name, row.state, row.final) == ("landed", "failed", 1)
