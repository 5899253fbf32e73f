"""Issue 34, points 4 and 5: servers that accept connections and never answer, and the Python API's checks.

4. A Dask scheduler (``--scheduler``, ``DASK_SCHEDULER_ADDRESS``) or an S3 endpoint that accepts
   connections and never answers: one line naming the address within a bounded time, exit 1, no
   output (``reconstruct`` was silent for 590 s and more, ``evaluate`` hung and left its ``--out``,
   S3 411 s).
5. The Python API checks what the command checks, by type and value, before anything is created:
   ``reconstruct(S, None)`` wrote a complete store to ``./None``, ``overwrite="no"`` replaced an existing
   video, ``ingest(flip="no")`` wrote a store and then raised, ``every="5"``, ``scale=4.0``,
   ``client="notaclient"`` and a closed client failed deep inside.
"""

import os
import socket
import subprocess
import sys
import threading
import time

import imageio.v3 as iio
import numpy as np
import pytest

from cscsr import evaluate, ingest, reconstruct, simulate
from stages.errors import InputError
from tests.reliability.test_numbers import assert_nothing_made, fingerprint
from tests.test_bad_input import assert_refused
from tests.test_simulate import picture

FRAMES, HEIGHT, WIDTH = 100, 16, 16
BOUND = 30  # seconds: the longest a refusal may take (start-up of a command included)


@pytest.fixture
def silent():
    """127.0.0.1:PORT of a TCP server that accepts every connection and never sends a byte."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(64)
    held, stop = [], threading.Event()

    def accept():
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])
            except OSError:  # the accept timed out, or the server closed
                pass

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    yield "127.0.0.1:%d" % server.getsockname()[1]
    stop.set()
    thread.join(2)
    for connection in held:
        connection.close()
    server.close()


@pytest.fixture
def store(tmp_path):
    """A 100-frame 16x16 RGGB spike store with ground truth at frames 20 and 61 (as simulate makes), in
    ``tmp_path/inputs`` so that ``tmp_path`` itself holds only what a command makes."""
    import zarr

    folder = tmp_path / "inputs"
    folder.mkdir()
    np.save(folder / "c.npy", (np.random.default_rng(0).random((FRAMES, HEIGHT, WIDTH)) < 0.2).astype(np.uint8))
    path = folder / "s.zarr"
    ingest(str(folder / "c.npy"), str(path), cfa="rggb")
    group = zarr.open_group(str(path), mode="r+")
    group.create_array("truth", data=np.zeros((2, 4 * HEIGHT, 4 * WIDTH, 3), np.uint8))
    group.create_array("truth_frames", data=np.array([20, 61], np.int64))
    return path


def timed(run):
    start = time.monotonic()
    result = run()
    return result, time.monotonic() - start


# --- 4. a scheduler that never answers ----------------------------------------------------------------

@pytest.mark.parametrize("how", ["--scheduler", "DASK_SCHEDULER_ADDRESS"])
def test_reconstruct_refuses_a_silent_scheduler_in_one_line(cli, tmp_path, store, silent, monkeypatch, how):
    before, out = set(os.listdir(tmp_path)), tmp_path / "out.zarr"
    address = f"tcp://{silent}"
    if how == "DASK_SCHEDULER_ADDRESS":
        monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", address)
        args = ()
    else:
        monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
        args = ("--scheduler", address)
    result, seconds = timed(lambda: cli("reconstruct", store, out, "--every", 41, *args))
    assert result.exit_code == 1
    assert_refused(result, f"cannot reach Dask scheduler {address}", "no answer within")
    assert seconds < BOUND
    assert_nothing_made(tmp_path, before, out)


def test_evaluate_refuses_a_silent_scheduler_before_its_out_exists(cli, tmp_path, store, silent, monkeypatch):
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    before, out = set(os.listdir(tmp_path)), tmp_path / "evaluation"
    result, seconds = timed(lambda: cli("evaluate", store, "--methods", "tfp", "--out", out, "--scheduler", silent))
    assert result.exit_code == 1
    assert_refused(result, f"cannot reach Dask scheduler {silent}", "no answer within")
    assert seconds < BOUND
    assert_nothing_made(tmp_path, before, out)


def test_the_api_refuses_a_silent_scheduler_before_any_output(tmp_path, store, silent, monkeypatch):
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", f"tcp://{silent}")
    before, out = set(os.listdir(tmp_path)), tmp_path / "out.zarr"
    start = time.monotonic()
    with pytest.raises(InputError, match=f"cannot reach Dask scheduler tcp://{silent}"):
        reconstruct(store, out, every=41)
    assert time.monotonic() - start < BOUND
    assert_nothing_made(tmp_path, before, out)


# --- 4. an S3 endpoint that never answers -------------------------------------------------------------

def cscsr_process(*args, env: dict) -> tuple[subprocess.CompletedProcess, float]:
    """The real command in a process of its own: its S3 filesystems are its own, not the test's (fsspec
    caches them per process)."""
    command = [os.path.join(os.path.dirname(sys.executable), "cscsr"), *map(str, args)]
    start = time.monotonic()
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    return done, time.monotonic() - start


def s3_environment(endpoint: str, **extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("AWS_", "FSSPEC_S3"))}
    env.update(AWS_ACCESS_KEY_ID="testing", AWS_SECRET_ACCESS_KEY="testing", AWS_DEFAULT_REGION="us-east-1",
               AWS_ENDPOINT_URL=endpoint, AWS_EC2_METADATA_DISABLED="true", **extra)
    return env


def assert_process_refused(done: subprocess.CompletedProcess, *fragments) -> None:
    from tests.conftest import CliResult

    assert done.returncode == 1, done.stderr
    assert_refused(CliResult(done.returncode, done.stdout, done.stderr), *fragments)


def test_info_refuses_a_silent_s3_endpoint_within_its_default_timeouts(silent, tmp_path):
    """The defaults (5 s to connect, 10 s to read): refused after 15 s, not 411 s."""
    url = "s3://spikes-bucket/s.zarr"
    done, seconds = cscsr_process("info", url, env=s3_environment(f"http://{silent}"))
    assert_process_refused(done, f"cannot reach {url}: no answer from http://{silent} within 15 s")
    assert seconds < BOUND


def test_reconstruct_refuses_a_silent_s3_endpoint_within_the_users_own_timeouts(silent, tmp_path):
    """fsspec's settings of the user's own (FSSPEC_S3_CONFIG_KWARGS) win over the defaults."""
    before, out, url = set(os.listdir(tmp_path)), tmp_path / "out.zarr", "s3://spikes-bucket/s.zarr"
    env = s3_environment(f"http://{silent}", FSSPEC_S3_CONFIG_KWARGS='{"connect_timeout": 1, "read_timeout": 2}')
    done, seconds = cscsr_process("reconstruct", url, out, "--workers", 1, env=env)
    assert_process_refused(done, f"cannot reach {url}: no answer from http://{silent} within 3 s")
    assert seconds < BOUND
    assert_nothing_made(tmp_path, before, out)


def test_s3_timeouts_default_under_the_users_settings(monkeypatch):
    import fsspec

    from pipeline.stores.storage import S3_TIMEOUTS, storage_options

    assert storage_options("/a/path") == {} and storage_options("memory://x") == {}
    assert storage_options("s3://b/k")["config_kwargs"] == S3_TIMEOUTS
    monkeypatch.setitem(fsspec.config.conf, "s3", {"config_kwargs": {"read_timeout": 60}})
    assert storage_options("s3://b/k")["config_kwargs"] == {**S3_TIMEOUTS, "read_timeout": 60}


def test_a_live_s3_endpoint_still_works(s3_endpoint, tmp_path):
    """The endpoint's first answer (any, even "no such bucket") lets the work go on."""
    url = "s3://spikes-bucket/live.zarr"
    np.save(tmp_path / "c.npy", np.zeros((41, 8, 8), np.uint8))
    made = ingest(str(tmp_path / "c.npy"), url)
    assert made.counts["frames"] == 41
    with pytest.raises(InputError, match="no-such-bucket") as refused:  # an answer: a missing store
        reconstruct("s3://no-such-bucket/s.zarr", str(tmp_path / "o.zarr"), workers=1)
    assert "cannot reach" not in str(refused.value)


# --- 5. the Python API checks what the command checks --------------------------------------------------

@pytest.fixture
def here(tmp_path, monkeypatch):
    """Run in an empty folder, to see a ``./None`` made."""
    folder = tmp_path / "cwd"
    folder.mkdir()
    monkeypatch.chdir(folder)
    return folder


def test_a_missing_output_path_is_refused_not_written_to_none(store, here):
    with pytest.raises(TypeError, match=r"reconstruct\(\): out must be a path or URL .*got None"):
        reconstruct(store, None, workers=1)
    with pytest.raises(TypeError, match=r"ingest\(\): store must be a path or URL"):
        ingest(str(store.parent / "c.npy"), None)
    with pytest.raises(TypeError, match=r"evaluate\(\): out must be a path or URL"):
        evaluate(store, "tfp", None)
    with pytest.raises(TypeError, match=r"reconstruct\(\): store must be a path or URL .*got 3"):
        reconstruct(3, "out.zarr")
    with pytest.raises(ValueError, match=r"reconstruct\(\): out is empty"):
        reconstruct(store, "", workers=1)
    assert os.listdir(here) == []


def test_yes_no_options_must_be_true_or_false(store, tmp_path, here):
    video = tmp_path / "video"  # an existing output that overwrite="no" must not replace
    video.mkdir()
    (video / "keep.txt").write_text("mine\n")
    unchanged = fingerprint(video)
    with pytest.raises(TypeError, match="--overwrite must be True or False, got 'no'"):
        reconstruct(store, video, overwrite="no", workers=1)
    with pytest.raises(TypeError, match="--flip must be True or False, got 'no'"):
        ingest(str(store.parent / "c.npy"), "flipped.zarr", flip="no")
    with pytest.raises(TypeError, match="--resume must be True or False"):
        reconstruct(store, "out.zarr", resume=1, workers=1)
    with pytest.raises(TypeError, match="progress must be True or False"):
        reconstruct(store, "out.zarr", progress="yes", workers=1)
    with pytest.raises(TypeError, match="--overwrite must be True or False, got 'no'"):
        evaluate(store, "tfp", video, overwrite="no", workers=1)
    assert fingerprint(video) == unchanged and os.listdir(here) == []


def test_numbers_and_names_of_the_wrong_type_are_named(store, tmp_path, here):
    iio.imwrite(tmp_path / "scene.png", picture("astronaut", 64))
    cases = [
        (lambda: reconstruct(store, "o.zarr", every="5", workers=1), "--every must be an integer, got '5'"),
        (lambda: reconstruct(store, "o.zarr", scale=4.0, workers=1), "--scale must be an integer, got 4.0"),
        (lambda: reconstruct(store, "o.zarr", window=41.0, workers=1), "--window must be an integer"),
        (lambda: reconstruct(store, "o.zarr", method=None, workers=1), "--method must be a string, got None"),
        (lambda: reconstruct(store, "o.zarr", workers="2"), "--workers must be an integer, got '2'"),
        (lambda: simulate(str(tmp_path / "scene.png"), "s.zarr", scale=4.0, motion="static", workers=1),
         "--scale must be an integer, got 4.0"),
        (lambda: simulate(str(tmp_path / "scene.png"), "s.zarr", frames="82", motion="static", workers=1),
         "--frames must be an integer"),
        (lambda: ingest(str(store.parent / "c.npy"), "i.zarr", height="16"), "--height must be an integer"),
        (lambda: ingest(str(store.parent / "c.npy"), "i.zarr", cfa=None), "--cfa must be a string"),
        (lambda: evaluate(store, 5, "evaluation", workers=1), "methods must be a string"),
        (lambda: evaluate(store, [None], "evaluation", workers=1), "methods must be a string"),
    ]
    for call, message in cases:
        with pytest.raises(TypeError, match=message):
            call()
    assert os.listdir(here) == []


@pytest.mark.parametrize("job", ["ingest", "simulate", "reconstruct", "evaluate"])
def test_a_client_that_is_not_a_running_client_is_refused(store, tmp_path, here, job):
    from distributed import Client, LocalCluster

    iio.imwrite(tmp_path / "scene.png", picture("astronaut", 64))
    calls = {"ingest": lambda client: ingest(str(store.parent / "c.npy"), "i.zarr", client=client),
             "simulate": lambda client: simulate(str(tmp_path / "scene.png"), "s.zarr", motion="static", client=client),
             "reconstruct": lambda client: reconstruct(store, "o.zarr", client=client),
             "evaluate": lambda client: evaluate(store, "tfp", "evaluation", client=client)}
    with pytest.raises(TypeError, match=rf"{job}\(\): client must be a distributed.Client .*got 'notaclient'"):
        calls[job]("notaclient")
    with LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        closed = Client(cluster)
        closed.close()
        with pytest.raises(ValueError, match=rf"{job}\(\): client is closed, not running"):
            calls[job](closed)
    assert os.listdir(here) == []
