"""Non-finite and out-of-range numbers, and options checked only after the output existed.

Every case goes through the real CLI (in-process) and must end the same way: a non-zero exit,
one line on stderr naming the option (or attribute, or tensor) and the value, no output path
afterwards, and the input unchanged. Numbers come from flags, watcher sidecars, store
attributes and weights tensors; each is checked once, before any output exists.
"""

import hashlib
import json
import os

import numpy as np
import pytest
import zarr

from tests.test_bad_input import assert_refused

FRAMES, HEIGHT, WIDTH = 100, 16, 16


def fingerprint(path) -> str:
    """A hash of every file under ``path`` (names and bytes): proof that an input is unchanged."""
    digest = hashlib.sha256()
    for root, dirs, files in sorted(os.walk(path)):
        dirs.sort()
        for name in sorted(files):
            full = os.path.join(root, name)
            digest.update(os.path.relpath(full, path).encode())
            with open(full, "rb") as handle:
                digest.update(handle.read())
    return digest.hexdigest()


def assert_nothing_made(tmp_path, before: set, *outputs) -> None:
    for out in outputs:
        assert not os.path.exists(out), f"{out} was created"
    assert set(os.listdir(tmp_path)) == before, "something was created or deleted beside the inputs"


@pytest.fixture
def capture(tmp_path):
    path = tmp_path / "c.npy"
    np.save(path, (np.random.default_rng(0).random((FRAMES, HEIGHT, WIDTH)) < 0.2).astype(np.uint8))
    return path


@pytest.fixture
def store(cli, tmp_path, capture):
    path = tmp_path / "s.zarr"
    result = cli("ingest", capture, path, "--cfa", "rggb")
    assert result.exit_code == 0, result.stderr
    return path


def set_attribute(store, name, value) -> None:
    zarr.open_group(str(store), mode="r+").attrs[name] = value


# --- flags: non-finite and out of range ----------------------------------------------------------

@pytest.mark.parametrize("value,fragment", [("inf", "fps must be a finite number, got inf"),
                                            ("1e400", "fps must be a finite number, got inf"),
                                            ("nan", "fps must be > 0, got nan"), ("-inf", "got -inf")])
def test_ingest_fps_not_finite(cli, tmp_path, capture, value, fragment):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(tmp_path)
    out = tmp_path / "s.zarr"
    assert_refused(cli("ingest", capture, out, "--fps", value), fragment)
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(tmp_path) == unchanged


@pytest.mark.parametrize("args,fragment", [
    (["--gain", "inf"], "--gain must be a finite number, got inf"),
    (["--gain", "nan"], "--gain must be > 0, got nan"),
    (["--gain", "-1"], "--gain must be > 0, got -1.0"),
    (["--gain", "1e39"], "--gain must be <= 1e+06 (at that gain one spike"),  # infinite in float32; 1e30: white
    (["--scale", "0"], "--scale must be >= 1, got 0"),  # was silently the default, 4
    (["--scale", "-2"], "--scale must be >= 1, got -2"),  # was a raw zarr message, after OUT existed
    (["--scale", "5"], "scale must be one of 1, 2, 3, 4, 8, got 5"),  # was refused inside every task
])
def test_reconstruct_numbers_refused_before_the_output(cli, tmp_path, store, args, fragment):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out = tmp_path / "o.zarr"
    assert_refused(cli("reconstruct", store, out, "--workers", 1, *args), fragment)
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(store) == unchanged


@pytest.mark.parametrize("args,fragment", [(["--gain", "inf"], "--gain must be a finite number, got inf"),
                                           (["--gain", "nan"], "--gain must be > 0, got nan"),
                                           (["--scale", "0"], "--scale must be one of 1, 2, 3, 4, 8, got 0")])
def test_preview_numbers(cli, tmp_path, store, args, fragment):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    image = tmp_path / "p.png"
    assert_refused(cli("preview", store, image, *args), fragment)
    assert_nothing_made(tmp_path, before, image)
    assert fingerprint(store) == unchanged


@pytest.mark.parametrize("args,fragment", [(["--fps", "inf"], "fps must be a finite number, got inf"),
                                           (["--speed", "nan"], "--speed must be a finite number, got nan"),
                                           (["--deform", "inf"], "--deform must be a finite number, got inf"),
                                           (["--brightness", "inf"], "--brightness must be a finite number, got inf"),
                                           (["--chunk-frames", "0"], "--chunk-frames must be >= 1, got 0")])
def test_simulate_numbers(cli, tmp_path, args, fragment):
    import imageio.v3 as iio

    source = tmp_path / "still.png"
    iio.imwrite(source, np.random.default_rng(1).integers(0, 255, (32, 32, 3), np.uint8))
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(tmp_path)
    out = tmp_path / "sim.zarr"
    assert_refused(cli("simulate", source, out, "--motion", "static", "--workers", 1, *args), fragment)
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(tmp_path) == unchanged


# --- numbers from files: sidecars, store attributes, weights ---------------------------------------

def test_sidecar_fps_1e400_is_recorded_as_failed_and_nothing_stored(cli, tmp_path, capture):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    (inbox / "rec.npy").write_bytes(capture.read_bytes())
    (inbox / "rec.json").write_text('{"fps": 1e400, "cfa": "rggb"}')  # JSON reads 1e400 as infinity
    past = os.path.getmtime(capture) - 60
    for name in os.listdir(inbox):
        os.utime(inbox / name, (past, past))
    unchanged = fingerprint(inbox)
    result = cli("watch", inbox, outbox, "--once", "--settle", 0, "--workers", 1)
    assert result.exit_code == 1, result.stderr  # refused as its sidecar is read: every recording of the pass
    rows = json.loads(cli("status", outbox, "--json").stdout)  # one JSON list
    assert [(r["name"], r["state"]) for r in rows] == [("rec", "failed")]
    assert rows[0]["error"] == "sidecar rec.json: fps must be a finite number, got inf"
    stored = [p.relative_to(outbox) for p in outbox.rglob("rec*")]  # a spike store would be spikes/rec.zarr
    assert not stored  # no spike store, no video
    assert fingerprint(inbox) == unchanged


@pytest.mark.parametrize("value", [float("inf"), float("nan")])
def test_info_json_of_a_store_with_a_non_finite_fps(cli, tmp_path, store, value):
    set_attribute(store, "fps", value)
    unchanged = fingerprint(store)
    result = cli("info", store, "--json")
    assert_refused(result, str(store), "attribute fps must be")
    assert result.stdout == ""  # never a line of JSON with a bare Infinity or NaN
    assert fingerprint(store) == unchanged


def test_info_json_is_strict_json(cli, store):
    result = cli("info", store, "--json")
    assert result.exit_code == 0, result.stderr

    def refuse(constant):
        raise AssertionError(f"not JSON: {constant}")

    assert json.loads(result.stdout, parse_constant=refuse)["fps"] == 20000.0


@pytest.mark.parametrize("name,value,fragment", [
    ("gain", -1.0, "attribute gain must be > 0, got -1.0"),  # failed inside every task before
    ("gain", float("inf"), "attribute gain must be a finite number, got inf"),
    ("threshold", 0.0, "attribute threshold must be > 0, got 0.0"),
    ("scale", 0, "attribute scale must be >= 1, got 0"),
    ("scale", 5, "scale must be one of 1, 2, 3, 4, 8, got 5"),
])
def test_store_attribute_out_of_range(cli, tmp_path, store, name, value, fragment):
    set_attribute(store, name, value)
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out = tmp_path / "o.zarr"
    assert_refused(cli("reconstruct", store, out, "--workers", 1), fragment)
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(store) == unchanged


def test_weights_with_a_nan_tensor_are_refused_naming_file_and_tensor(cli, tmp_path, store):
    from safetensors.torch import load_file, save_file

    from cscsr.weights.weights_io import default_weights, read_metadata

    shipped = default_weights("lite")
    tensors = load_file(str(shipped))
    name = sorted(k for k, v in tensors.items() if v.is_floating_point())[3]
    tensors[name] = tensors[name].clone()
    tensors[name].view(-1)[0] = float("nan")
    weights = tmp_path / "nan.safetensors"
    save_file(tensors, str(weights), metadata=read_metadata(shipped))
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out = tmp_path / "o.zarr"
    result = cli("reconstruct", store, out, "--method", "cscsr", "--weights", weights, "--scale", 4, "--workers", 1)
    assert_refused(result, str(weights), f"tensor {name}", "1 non-finite values")
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(store) == unchanged


def test_non_finite_pixels_are_never_marked_complete(tmp_path, store, monkeypatch):
    """The last guard: should a method still make NaN (a bug, a network overflowing), the task fails,
    the job ends incomplete and the output is never marked complete."""
    from distributed import Client

    import pipeline.jobs.reconstruct as module
    from stages.reconstruction.methods import RateReconstructor

    def nan_rate(packed, width, reset):
        return np.full((packed.shape[1], width), np.nan, np.float32)

    import pipeline.jobs.reconstruct_tasks as tasks  # what the job's workers run

    monkeypatch.setattr(tasks, "reconstructor", lambda *args, **kwargs: RateReconstructor("tfp", nan_rate))
    out = tmp_path / "o.zarr"
    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=":0") as client:
        with pytest.raises(module.JobIncomplete, match="not finite"):
            module.reconstruct(str(store), str(out), module.ReconstructOptions(gain=1.0), client=client,
                               progress=False)
    assert zarr.open_group(str(out), mode="r").attrs["state"] == "writing"


# --- options checked before any output: --workers, --methods ---------------------------------------

def workers_command(command, tmp_path, store, workers):
    out = tmp_path / "out"
    return out, {
        "reconstruct": ["reconstruct", store, out],
        "simulate": ["simulate", store, out],  # the source is not even read
        "evaluate": ["evaluate", store, "--out", out],
        "make-testset": ["make-testset", out],
        "evaluate-testset": ["evaluate-testset", tmp_path / "set", "--out", out],
        "watch": ["watch", tmp_path / "inbox", out, "--once"],
    }[command] + ["--workers", workers]


@pytest.mark.parametrize("command", ["reconstruct", "simulate", "evaluate", "make-testset", "evaluate-testset", "watch"])
@pytest.mark.parametrize("workers,fragment", [(0, "--workers must be >= 1, got 0"),
                                              (100_000, "(at most 4 per core and 256 in all), got 100000")])
def test_workers_refused_before_any_output(cli, tmp_path, store, command, workers, fragment):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out, args = workers_command(command, tmp_path, store, workers)
    assert_refused(cli(*args), fragment)
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(store) == unchanged


@pytest.mark.parametrize("methods,fragment", [
    ("tfp,bogus", "--methods: unknown method 'bogus': expected one of tfp, tfi, cscsr, cscsr-ensemble"),  # ran tfp
    ("", "--methods is empty"),  # was an IndexError
    (" , ", "--methods is empty"),
    ("tfp,tfp", "--methods names tfp twice"),
])
def test_evaluate_methods_refused_before_any_method_runs(cli, tmp_path, store, methods, fragment):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out = tmp_path / "ev"
    assert_refused(cli("evaluate", store, "--methods", methods, "--out", out, "--workers", 1), fragment)
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(store) == unchanged


def test_evaluate_testset_bad_methods_leave_an_existing_out_alone(cli, tmp_path):
    out = tmp_path / "ev"
    out.mkdir()
    (out / "kept.txt").write_text("earlier results")
    assert_refused(cli("evaluate-testset", tmp_path / "set", "--methods", "tfp,bogus", "--out", out),
                   "unknown method 'bogus'")
    assert os.listdir(out) == ["kept.txt"] and (out / "kept.txt").read_text() == "earlier results"


def test_evaluate_a_method_that_cannot_serve_the_store_is_refused_before_the_others_run(cli, tmp_path, store):
    """Every method is checked against the store (and its weights loaded) before the first one runs:
    on a mono store, cscsr with colour weights is refused before tfp has written anything."""
    set_attribute(store, "cfa", "mono")
    group = zarr.open_group(str(store), mode="r+")
    group.create_array("truth", shape=(2, HEIGHT * 4, WIDTH * 4, 3), chunks=(1, HEIGHT * 4, WIDTH * 4, 3), dtype=np.uint8)
    group.create_array("truth_frames", data=np.array([20, 61], np.int64))
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out = tmp_path / "ev"
    assert_refused(cli("evaluate", store, "--methods", "tfp,cscsr", "--weights", "lite", "--out", out, "--workers", 1),
                   "colour (Bayer) CSCSR network and the recording", "is mono")
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(store) == unchanged


@pytest.mark.parametrize("args,fragment", [(["--fps", "inf"], "--fps must be a finite number, got inf"),
                                           (["--every", 0], "--every must be >= 1, got 0"),
                                           (["--settle", "nan"], "--settle must be >= 0, got nan"),
                                           (["--backoff", "inf"], "--backoff must be a finite number, got inf"),
                                           (["--max-attempts", 0], "--max-attempts must be >= 1, got 0")])
def test_watch_options_refused_before_outbox_exists(cli, tmp_path, args, fragment):
    (tmp_path / "inbox").mkdir()
    outbox = tmp_path / "outbox"
    assert_refused(cli("watch", tmp_path / "inbox", outbox, "--once", *args), fragment)
    assert not outbox.exists()
