"""Clearer answers: inputs of the wrong kind, options that do not apply, damaged stores and files.

Each case goes through the real CLI (in-process) on real files and stores and must end with one
line on stderr naming the file (or option) and the cause, a non-zero exit, and no output made.
"""

import functools
import json
import os

import numpy as np
import pytest
import zarr

from tests.conftest import CliResult
from tests.reliability.test_numbers import assert_nothing_made, fingerprint
from tests.test_bad_input import assert_refused

FRAMES, HEIGHT, WIDTH = 100, 16, 16


@pytest.fixture
def store(cli, tmp_path):
    """A complete 100-frame 16x16 RGGB spike store, with ground truth at frames 20 and 61 (as simulate makes)."""
    capture = tmp_path / "c.npy"
    np.save(capture, (np.random.default_rng(0).random((FRAMES, HEIGHT, WIDTH)) < 0.2).astype(np.uint8))
    path = tmp_path / "s.zarr"
    result = cli("ingest", capture, path, "--cfa", "rggb")
    assert result.exit_code == 0, result.stderr
    group = zarr.open_group(str(path), mode="r+")
    group.create_array("truth", data=np.zeros((2, 4 * HEIGHT, 4 * WIDTH, 3), np.uint8))
    group.create_array("truth_frames", data=np.array([20, 61], np.int64))
    os.remove(capture)
    return path


@pytest.fixture
def shipped():
    from cscsr.weights.weights_io import default_weights

    return str(default_weights("lite"))


# --- --weights with a classic method -------------------------------------------------------------

@pytest.mark.parametrize("method", ["tfp", "tfi"])
def test_weights_with_a_classic_method_are_refused_before_the_output(cli, tmp_path, store, shipped, method):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out = tmp_path / "out.zarr"
    assert_refused(cli("reconstruct", store, out, "--method", method, "--weights", shipped, "--workers", 1),
                   "--weights is for the network", f"{method} has no weights to load")
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(store) == unchanged


def test_weights_with_only_classic_methods_in_evaluate_or_watch_are_refused(cli, tmp_path, store, shipped):
    before = set(os.listdir(tmp_path))
    evaluation, outbox = tmp_path / "evaluation", tmp_path / "outbox"
    assert_refused(cli("evaluate", store, "--methods", "tfp,tfi", "--weights", shipped, "--out", evaluation),
                   "--weights is for the network", "tfp, tfi have no weights")
    assert_refused(cli("watch", tmp_path / "inbox", outbox, "--method", "tfi", "--weights", shipped, "--once"),
                   "--weights is for the network", "tfi has no weights")
    assert_nothing_made(tmp_path, before, evaluation, outbox)


def test_evaluate_gives_the_weights_to_the_network_only(store, shipped):
    """``evaluate --methods tfp,cscsr --weights W``: W is the network's; tfp's output never records it."""
    from pipeline.jobs.evaluate import checked_evaluation

    _, _, options = checked_evaluation(str(store), ["tfp", "cscsr"], shipped)
    assert options["tfp"].weights is None and options["cscsr"].weights == shipped


def test_a_classic_output_never_records_weights(cli, tmp_path, store):
    out = tmp_path / "out.zarr"
    result = cli("reconstruct", store, out, "--method", "tfp", "--workers", 1)
    assert result.exit_code == 0, result.stderr
    attrs = zarr.open_group(str(out), mode="r").attrs
    assert attrs["state"] == "complete" and attrs["weights"] is None


# --- a video store where a spike store is wanted, and info of a video store ---------------------

def test_a_video_store_is_named_as_one_and_info_describes_it(cli, tmp_path, store):
    video = tmp_path / "v.zarr"
    result = cli("reconstruct", store, video, "--method", "tfp", "--every", 20, "--workers", 1)
    assert result.exit_code == 0, result.stderr
    said = f"{video} is a video store (3 frames of 64x64 RGB, method tfp, state complete), not a spike store: " \
           f"give the spike store it was made from ({store})"
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(video)
    out, picture, evaluation = tmp_path / "again.zarr", tmp_path / "p.png", tmp_path / "evaluation"
    assert_refused(cli("reconstruct", video, out, "--workers", 1), said)
    assert_refused(cli("preview", video, picture), said)
    assert_refused(cli("evaluate", video, "--out", evaluation, "--workers", 1), said)
    assert_nothing_made(tmp_path, before, out, picture, evaluation)
    assert fingerprint(video) == unchanged

    info = json.loads(cli("info", video, "--json").stdout)
    assert {k: info[k] for k in ("kind", "state", "frames", "height", "width", "method", "every", "tiles_committed")} \
        == {"kind": "video store", "state": "complete", "frames": 3, "height": 64, "width": 64, "method": "tfp",
            "every": 20, "tiles_committed": "3 of 3"}
    assert info["fps"] == pytest.approx(20000 / 20) and info["spike_frames"] == "20..60" and info["source"] == str(store)
    table = cli("info", video).stdout
    assert "video store" in table and "tfp" in table and "complete" in table


# --- info of a spike store with lost chunks --------------------------------------------------------

def test_info_of_a_store_with_missing_chunks_names_them_and_never_says_complete(cli, tmp_path):
    from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter

    path = tmp_path / "chunked.zarr"
    packed = np.random.default_rng(1).integers(0, 256, (FRAMES, HEIGHT, WIDTH // 8), np.uint8)
    writer = SpikeStoreWriter(str(path), SpikeMeta(HEIGHT, WIDTH, "rggb"), FRAMES, chunk_frames=10)
    writer.write(0, packed)
    writer.finish(spike_count=int(np.unpackbits(packed).sum()))
    whole = json.loads(cli("info", path, "--json").stdout)
    assert whole["state"] == "complete" and whole["missing_chunks"] is None and whole["firing_rate"] > 0

    for t in (3, 4, 9):
        os.remove(path / "spikes" / "c" / str(t) / "0" / "0")
    info = json.loads(cli("info", path, "--json").stdout)
    assert info["state"] == "damaged: 3 of 10 chunks of spikes (frames 30..39, 40..49, 90..99) missing (lost data)"
    assert info["missing_chunks"] == "3 of 10 chunks of spikes (frames 30..39, 40..49, 90..99)"
    assert info["firing_rate"] is None  # a rate over data that is not all there would be a wrong answer
    assert "damaged" in cli("info", path).stdout and "complete" not in cli("info", path).stdout


# --- one line naming the file and the cause ---------------------------------------------------------

def closed_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_urls_are_named_with_the_cause(cli, tmp_path, store):
    before = set(os.listdir(tmp_path))
    http = f"http://127.0.0.1:{closed_port()}/s.zarr"
    assert_refused(cli("info", http), f"cannot reach {http}: ClientConnectorError", "Cannot connect to host")
    assert_refused(cli("info", "ftp://no-such-host.invalid/s.zarr"), "cannot reach ftp://no-such-host.invalid/s.zarr: ")
    assert_refused(cli("reconstruct", store, "ftp://no-such-host.invalid/o.zarr", "--workers", 1),
                   "cannot reach ftp://no-such-host.invalid/o.zarr: ")
    assert_nothing_made(tmp_path, before)


def test_ingest_tells_an_unreachable_host_from_a_missing_file(cli, tmp_path):
    """fsspec's HTTP filesystem says a file does not exist when its host cannot be reached."""
    import http.server
    import threading

    before = set(os.listdir(tmp_path))
    closed = f"http://127.0.0.1:{closed_port()}/x.npy"
    assert_refused(cli("ingest", closed, tmp_path / "a.zarr"), f"cannot reach {closed}: ClientConnectorError")
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):  # the server shares the command's stderr
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(tmp_path)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        missing = f"http://127.0.0.1:{server.server_address[1]}/no-such-capture.npy"  # a 404 from a live server
        assert_refused(cli("ingest", missing, tmp_path / "b.zarr"), f"cannot read {missing}: no such file")
    finally:
        server.shutdown()
    assert_nothing_made(tmp_path, before)


def test_s3_without_credentials_names_the_url_and_what_to_set(s3_endpoint, tmp_path, store):
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if not k.startswith(("AWS_", "FSSPEC_S3"))}
    env.update(AWS_ENDPOINT_URL=s3_endpoint, AWS_EC2_METADATA_DISABLED="true", AWS_CONFIG_FILE=str(tmp_path / "none"),
               AWS_SHARED_CREDENTIALS_FILE=str(tmp_path / "none"))
    cscsr = os.path.join(os.path.dirname(sys.executable), "cscsr")
    for args, url in ((["info", "s3://spikes-bucket/nothing.zarr"], "s3://spikes-bucket/nothing.zarr"),
                      (["reconstruct", store, "s3://spikes-bucket/o.zarr", "--workers", 1], "s3://spikes-bucket/o.zarr")):
        done = subprocess.run([cscsr, *map(str, args)], capture_output=True, text=True, env=env, timeout=300)
        assert_refused(CliResult(done.returncode, done.stdout, done.stderr), f"cannot reach {url}: no S3 credentials found", "AWS_ACCESS_KEY_ID")


def test_files_of_the_wrong_kind_are_named_with_the_cause(cli, tmp_path, store):
    (tmp_path / "fake.png").write_text("a note, not a picture\n")
    (tmp_path / "outbox").write_text("a file where a folder is wanted\n")
    (tmp_path / "weights").mkdir()
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(tmp_path)
    made = [tmp_path / name for name in ("sim.zarr", "o.zarr", "p.xyz", "p")]
    assert_refused(cli("simulate", tmp_path / "fake.png", made[0], "--motion", "static", "--workers", 1),
                   f"{tmp_path / 'fake.png'} is not a valid PNG image: it cannot be decoded (it starts with b'a note, ')")
    assert_refused(cli("watch", tmp_path / "inbox", tmp_path / "outbox", "--once"),
                   f"OUTBOX {tmp_path / 'outbox'} is a file, not a folder")
    for args in (("reconstruct", store, made[1], "--method", "cscsr", "--weights", tmp_path / "weights", "--workers", 1),
                 ("model-info", "--weights", tmp_path / "weights")):
        assert_refused(cli(*args), f"weights {tmp_path / 'weights'} is a folder, not a weights file")
    assert_refused(cli("preview", store, made[2]), f"{made[2]}: unknown image extension '.xyz': expected one of .png")
    assert_refused(cli("preview", store, made[3]), f"{made[3]}: unknown image extension (none)")
    assert_nothing_made(tmp_path, before, *made)
    assert fingerprint(tmp_path) == unchanged


# --- a lost or garbage chunk during reconstruct: one summary line, no traceback per task -------------

def test_lost_and_garbage_chunks_end_in_one_line_not_a_traceback_per_task(cli_process, tmp_path):
    from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter

    path, out = tmp_path / "lost.zarr", tmp_path / "v.zarr"
    writer = SpikeStoreWriter(str(path), SpikeMeta(HEIGHT, WIDTH, "rggb"), 400, chunk_frames=10)
    writer.write(0, np.random.default_rng(1).integers(0, 256, (400, HEIGHT, WIDTH // 8), np.uint8))
    writer.finish(spike_count=1)
    os.remove(path / "spikes" / "c" / "5" / "0" / "0")  # frames 50..59: lost
    (path / "spikes" / "c" / "20" / "0" / "0").write_bytes(b"garbage" * 10)  # frames 200..209: damaged

    result = cli_process("reconstruct", path, out, "--every", 5, "--gain", 1, "--workers", 2)
    assert result.returncode == 1
    assert "Compute Failed" not in result.stderr and "InputError(" not in result.stderr, result.stderr[:2000]
    errors = [line for line in result.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith("error: JobIncomplete: 20 of 72 output frames failed"), errors
    assert "the chunk of frames 50..59 is missing (lost data)" in errors[0]
    assert zarr.open_group(str(out), mode="r").attrs["state"] == "writing"


def test_only_our_own_task_errors_are_kept_out_of_worker_logs():
    """The filter drops a ``Compute Failed`` record for an InputError; an unexpected error keeps its traceback;
    a heartbeat cut by the local cluster's shutdown is dropped."""
    import logging

    from pipeline.compute.cluster import QuietExpectedErrors

    def record(exception_text):
        return logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1,
                                 "Compute Failed\nKey: %s\nState: %s\nTask: %s\nException: %r\nTraceback: %r\n",
                                 ("k", "executing", "task", exception_text, "  File ..."), None)

    quiet = QuietExpectedErrors()
    assert not quiet.filter(record("InputError('spike store s.zarr: the chunk of frames 0..9 is missing')"))
    assert quiet.filter(record("ZeroDivisionError('division by zero')"))
    assert quiet.filter(record("ValueError('3 of 12 values of the exposed image are not finite')"))
    assert quiet.filter(logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1, "other %s", ("x",), None))
    # A heartbeat cut by the cluster's shutdown at the end of a job (it broke the one-line answer above once
    # in six suite runs with a core kept busy) is dropped with its traceback; other heartbeat trouble is not.
    try:
        raise OSError("Stream is closed")
    except OSError:
        import sys

        cut = logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1,
                                "Failed to communicate with scheduler during heartbeat.", (), sys.exc_info())
    assert not quiet.filter(cut)
    assert quiet.filter(logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1,
                                          "Unexpected exception during heartbeat. Closing worker.", (), None))
    # a peer gone while this worker sent it a result, as the cluster of a SIGTERM'd job closed (CI, 2026-11-27)
    assert not quiet.filter(logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1,
                                              "failed during get data with %s -> %s", ("tcp://a", "tcp://b"), None))
