"""Jobs claiming one output at the same moment: exactly one gets it, every time (``pipeline.stores.lease.claimed``).

Two claimants are released together by a barrier, ``ROUNDS`` times: two processes on a local path
(the kernel lock), two threads on ``memory://``; the winner holds its claim until the loser has
tried. Then: a claim whose job was SIGKILLed is free at once; S3's conditional write refuses a
second claim; and two real ``cscsr reconstruct`` processes started together on one OUT (with
different methods) end with one winner, one refusal, and the winner's video."""

import json
import multiprocessing
import os
import socket
import subprocess
import sys
import threading
import time

import fsspec
import pytest
import zarr

from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.stores.lease import claim_path, claimed
from stages.errors import InputError
from tests.conftest import integrate_and_fire, smooth_rate, write_dat

ROUNDS = 50
BIN = os.path.dirname(sys.executable)


def _claimant(base: str, rounds: int, start, after, results) -> None:
    """One claimant (a process of its own): each round, claim an output at the barrier's signal."""
    for r in range(rounds):
        url = f"{base}/out{r % 5}.zarr"  # outputs come back: a claim file its last holder removed is reused
        start.wait()
        try:
            with claimed(url):
                results.put((r, os.getpid(), "won"))
                after.wait()  # hold the claim until the other claimant has tried
        except InputError as error:
            results.put((r, os.getpid(), str(error)))
            after.wait()


def outcomes(results, rounds: int) -> dict:
    got = {}
    for _ in range(2 * rounds):
        r, who, what = results.get(timeout=60)
        got.setdefault(r, []).append((who, what))
    return got


def check_one_winner(got: dict, rounds: int, url_of) -> None:
    assert sorted(got) == list(range(rounds))
    for r, pair in got.items():
        won = [who for who, what in pair if what == "won"]
        lost = [what for who, what in pair if what != "won"]
        assert len(won) == 1 and len(lost) == 1, (r, pair)
        assert lost[0].startswith(f"{url_of(r)} is being written by another job") and f"pid {won[0]}" in lost[0], lost


def test_two_processes_claim_one_local_output_at_once(tmp_path):
    context = multiprocessing.get_context("spawn")
    start, after, results = context.Barrier(2), context.Barrier(2), context.Queue()
    claimants = [context.Process(target=_claimant, args=(str(tmp_path), ROUNDS, start, after, results))
                 for _ in range(2)]
    for process in claimants:
        process.start()
    got = outcomes(results, ROUNDS)
    for process in claimants:
        process.join(30)
        assert process.exitcode == 0
    check_one_winner(got, ROUNDS, lambda r: f"{tmp_path}/out{r % 5}.zarr")
    assert os.listdir(tmp_path) == []  # every claim file removed by its holder


def test_two_threads_claim_one_memory_output_at_once():
    start, after = threading.Barrier(2), threading.Barrier(2)
    results = __import__("queue").Queue()

    def claimant(name):
        for r in range(ROUNDS):
            start.wait()
            try:
                with claimed(f"memory://claims/out{r % 5}.zarr"):
                    results.put((r, name, "won"))
                    after.wait()
            except InputError as error:
                results.put((r, name, str(error)))
                after.wait()

    threads = [threading.Thread(target=claimant, args=(name,)) for name in ("a", "b")]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    got = outcomes(results, ROUNDS)
    for r, pair in got.items():
        assert sorted(what == "won" for _, what in pair) == [False, True], (r, pair)
    assert not fsspec.filesystem("memory").exists("/claims/.out0.zarr.claim")


def test_a_killed_holder_frees_its_claim_at_once(tmp_path):
    out = str(tmp_path / "out.zarr")
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom pipeline.stores.lease import claimed\n"
                               f"with claimed({out!r}):\n    print('held', flush=True)\n    time.sleep(120)"],
                              stdout=subprocess.PIPE, text=True, cwd=os.getcwd())
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match=f"being written by another job .*pid {holder.pid}"):
            with claimed(out):
                pass
    finally:
        holder.kill()
        holder.wait()
    assert os.path.exists(claim_path(out)[1])  # left behind by the kill ...
    with claimed(out):  # ... and no obstacle: the kernel let go of the lock with the process
        os.symlink(tmp_path, tmp_path.parent / f"{tmp_path.name}-link")
        for spelling in (f"file://{out}/", f"{tmp_path}-link/out.zarr", f"{tmp_path}/../{tmp_path.name}/out.zarr"):
            with pytest.raises(InputError, match="being written by another job"):  # one claim, however spelt
                with claimed(spelling):
                    pass
    assert not os.path.exists(claim_path(out)[1])


def test_s3_claims_are_conditional_writes(s3_endpoint):
    url = "s3://spikes-bucket/claimed.zarr"
    fs, path = claim_path(url)
    with claimed(url):
        assert json.loads(fs.cat_file(path))["pid"] == os.getpid()
        with pytest.raises(FileExistsError):  # what refuses the second claim: S3's If-None-Match
            fs.pipe_file(path, b"{}", mode="create")
        with pytest.raises(InputError, match="being written by another job"):
            with claimed(url):
                pass
    assert not fs.exists(path)
    fs.pipe_file(path, json.dumps({"host": "elsewhere", "pid": 1, "heartbeat": time.time() - 3600}).encode())
    with claimed(url):  # a claim not renewed for an hour belongs to a dead job: taken over
        assert json.loads(fs.cat_file(path))["pid"] == os.getpid()


@pytest.fixture
def spike_store(tmp_path) -> str:
    write_dat(tmp_path / "x.dat", integrate_and_fire(smooth_rate(16, 16), 123))
    ingest(str(tmp_path / "x.dat"), str(tmp_path / "s.zarr"), IngestOptions(16, 16, cfa="rggb"), progress=False)
    return str(tmp_path / "s.zarr")


def test_two_reconstructs_started_together_on_one_output(spike_store, tmp_path):
    from pipeline.compute.hold import hold_environment

    out, release = str(tmp_path / "out.zarr"), tmp_path / "release"
    env = {**os.environ, **hold_environment(0, release)}  # the winner's first task waits: it cannot finish early
    jobs = {method: subprocess.Popen([f"{BIN}/cscsr", "reconstruct", spike_store, out, "--method", method,
                                      "--overwrite", "--workers", "1", "--tile", "8"],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            for method in ("tfp", "tfi")}
    deadline = time.time() + 240
    while all(job.poll() is None for job in jobs.values()):
        assert time.time() < deadline, "neither job was refused"
        time.sleep(0.05)
    loser = next(method for method, job in jobs.items() if job.poll() is not None)
    winner = "tfi" if loser == "tfp" else "tfp"
    stderr = jobs[loser].stderr.read()
    assert jobs[loser].returncode == 1 and stderr.strip().splitlines() == [
        f"error: {out} is being written by another job (host {socket.gethostname()}, pid {jobs[winner].pid}): "
        f"wait for it to finish or stop it first"], stderr
    release.touch()
    assert jobs[winner].wait(240) == 0, jobs[winner].stderr.read()
    group = zarr.open_group(out, mode="r")
    assert group.attrs["state"] == "complete" and group.attrs["method"] == winner
    assert group["committed"][:].all()
    assert sorted(os.listdir(tmp_path)) == ["out.zarr", "release", "s.zarr", "x.dat"]  # no claim file left
