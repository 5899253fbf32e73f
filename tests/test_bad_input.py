"""Bad input: a one-line error naming the problem, a non-zero exit, and no output left."""

import os

import numpy as np
import pytest

from tests.conftest import write_dat


def assert_refused(result, *fragments):
    assert result.exit_code != 0
    lines = result.stderr.splitlines()
    assert len(lines) == 1, repr(result.stderr)  # no empty line either (a progress bar's, where stderr is piped)
    assert lines[0].startswith("error: ")
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.fixture
def small_dat(tmp_path):
    path = tmp_path / "ok.dat"
    write_dat(path, (np.random.default_rng(0).random((41, 8, 16)) < 0.2).astype(np.uint8))
    return path


def test_dat_size_not_a_multiple_of_the_frame(cli, small_dat, tmp_path):
    truncated = tmp_path / "cut.dat"
    truncated.write_bytes(small_dat.read_bytes()[:-5])  # 16 bytes/frame
    out = tmp_path / "s.zarr"
    assert_refused(cli("ingest", truncated, out, "--height", 8, "--width", 16), "not a multiple of the frame size 16", "11 bytes too many")
    assert not out.exists()


@pytest.mark.parametrize("args,fragment", [
    ([], "give both --height and --width"),
    (["--height", 8], "give both --height and --width"),
    (["--height", 0, "--width", 16], "height must be a positive integer"),
])
def test_dat_geometry_missing_or_nonsense(cli, small_dat, tmp_path, args, fragment):
    out = tmp_path / "s.zarr"
    assert_refused(cli("ingest", small_dat, out, *args), fragment)
    assert not out.exists()


def test_array_size_inconsistent_with_options(cli, tmp_path):
    np.save(tmp_path / "a.npy", np.zeros((41, 8, 16), np.uint8))
    out = tmp_path / "s.zarr"
    assert_refused(cli("ingest", tmp_path / "a.npy", out, "--height", 10), "--height 10 is inconsistent with the array's height 8")
    assert not out.exists()


def test_npz_values_not_binary(cli, tmp_path):
    spikes = np.zeros((300, 8, 16), np.uint8)
    spikes[250, 3, 5] = 2  # late in the stream: earlier blocks are already written
    np.savez(tmp_path / "bad.npz", spk=spikes)
    out = tmp_path / "s.zarr"
    from pipeline.jobs import ingest as module

    module.BLOCK_BYTES, saved = 16 * 64, module.BLOCK_BYTES
    try:
        assert_refused(cli("ingest", tmp_path / "bad.npz", out), "must be 0 or 1", "found 2 at frame 250, row 3, column 5")
    finally:
        module.BLOCK_BYTES = saved
    assert not out.exists()


@pytest.mark.parametrize("array,fragment", [
    (np.zeros((8, 16), np.uint8), "rank 2"),
    (np.zeros((2, 41, 8, 16), np.uint8), "rank 4"),
    (np.array([["a"]] * 3), "rank 2"),
    (np.zeros((41, 8, 16), "U1"), "dtype <U1"),
])
def test_npz_wrong_rank_or_dtype(cli, tmp_path, array, fragment):
    np.savez(tmp_path / "bad.npz", spk=array)
    out = tmp_path / "s.zarr"
    assert_refused(cli("ingest", tmp_path / "bad.npz", out), fragment)
    assert not out.exists()


def test_npz_missing_key_lists_what_is_there(cli, tmp_path):
    np.savez(tmp_path / "two.npz", a=np.zeros((41, 8, 16), np.uint8), b=np.zeros(3))
    assert_refused(cli("ingest", tmp_path / "two.npz", tmp_path / "s.zarr"), "no array 'spk'", "a, b")


def test_unknown_cfa(cli, small_dat, tmp_path):
    assert_refused(cli("ingest", small_dat, tmp_path / "s.zarr", "--height", 8, "--width", 16, "--cfa", "rgbw"), "unknown CFA 'rgbw'")
    assert not (tmp_path / "s.zarr").exists()


def test_odd_size_with_bayer_cfa(cli, tmp_path):
    np.save(tmp_path / "odd.npy", np.zeros((41, 7, 16), np.uint8))
    assert_refused(cli("ingest", tmp_path / "odd.npy", tmp_path / "s.zarr", "--cfa", "rggb"), "height 7 is odd")
    assert not (tmp_path / "s.zarr").exists()


def test_output_exists_without_overwrite(cli, small_dat, tmp_path):
    out = tmp_path / "s.zarr"
    assert cli("ingest", small_dat, out, "--height", 8, "--width", 16).exit_code == 0
    before = sorted(os.listdir(out))
    assert_refused(cli("ingest", small_dat, out, "--height", 8, "--width", 16), "already exists", "--overwrite")
    assert sorted(os.listdir(out)) == before  # the existing store is untouched
    assert cli("ingest", small_dat, out, "--height", 8, "--width", 16, "--overwrite").exit_code == 0
    (tmp_path / "x.dat").write_bytes(b"old")
    assert_refused(cli("export", out, tmp_path / "x.dat"), "already exists")
    assert (tmp_path / "x.dat").read_bytes() == b"old"


@pytest.mark.parametrize("source", ["/no/such/capture.dat", "memory://nowhere/capture.dat", "nosuchproto://x/capture.dat"])
def test_unreadable_url(cli, tmp_path, source):
    out = tmp_path / "s.zarr"
    assert_refused(cli("ingest", source, out, "--height", 8, "--width", 16), "capture.dat")
    assert not out.exists()


@pytest.mark.parametrize("kind", ["a named pipe (FIFO)", "a folder"])
def test_a_capture_that_is_no_regular_file_is_named_as_such(cli, tmp_path, kind):
    """A named pipe was read as "capture is empty: no complete frame" (and a reader of a pipe can wait for ever)."""
    capture = tmp_path / "c.dat"
    os.mkfifo(capture) if kind.startswith("a named pipe") else capture.mkdir()
    assert_refused(cli("ingest", capture, tmp_path / "s.zarr", "--height", 8, "--width", 16),
                   f"capture {capture} is {kind}, not a regular file")
    assert not (tmp_path / "s.zarr").exists()


def test_unknown_extension_and_missing_store(cli, tmp_path):
    (tmp_path / "c.avi").write_bytes(b"x")
    assert_refused(cli("ingest", tmp_path / "c.avi", tmp_path / "s.zarr"), "unknown capture type .avi")
    assert_refused(cli("info", tmp_path / "none.zarr"), "cannot read spike store")
    assert_refused(cli("export", tmp_path / "none.zarr", tmp_path / "o.dat"), "cannot read store")
    assert not (tmp_path / "o.dat").exists()


def test_incomplete_store_is_refused(cli, small_dat, tmp_path):
    import zarr

    out = tmp_path / "s.zarr"
    assert cli("ingest", small_dat, out, "--height", 8, "--width", 16).exit_code == 0
    zarr.open_group(str(out), mode="r+").attrs["state"] = "writing"  # as if the writer died
    assert_refused(cli("export", out, tmp_path / "o.dat"), "incomplete")
    assert "writing" in cli("info", out).stdout


def test_real_process_exit_status(cli_process, tmp_path):
    result = cli_process("ingest", tmp_path / "missing.dat", tmp_path / "s.zarr", "--height", 8, "--width", 16)
    assert result.returncode == 1
    assert result.stderr.strip().count("\n") == 0 and "missing.dat" in result.stderr
    assert "Usage" in cli_process("--help").stdout


def test_workers_and_a_named_scheduler_contradict_each_other(cli, small_dat, tmp_path):
    """--workers starts a local cluster, --scheduler runs on a named one: given both, the workers were silently
    ignored (or the job waited on an unreachable scheduler). Refused at once, before anything is read or made."""
    assert cli("ingest", small_dat, tmp_path / "s.zarr", "--height", 8, "--width", 16).exit_code == 0
    picture = tmp_path / "p.png"
    import imageio.v3 as iio

    iio.imwrite(picture, np.zeros((32, 32, 3), np.uint8))
    both = ("--workers", 1, "--scheduler", "tcp://127.0.0.1:1")  # nothing listens there: refused before trying
    for args in (("reconstruct", tmp_path / "s.zarr", tmp_path / "out.zarr"),
                 ("ingest", small_dat, tmp_path / "out.zarr", "--height", 8, "--width", 16),
                 ("simulate", picture, tmp_path / "out.zarr", "--motion", "static"),
                 ("evaluate", tmp_path / "s.zarr", "--out", tmp_path / "out"),
                 ("watch", tmp_path, tmp_path / "out", "--once")):
        assert_refused(cli(*args, *both), "--workers 1 and --scheduler tcp://127.0.0.1:1 contradict each other")
        assert not (tmp_path / "out.zarr").exists() and not (tmp_path / "out").exists()


def test_options_that_would_be_ignored_or_that_are_no_rate_are_refused(cli, small_dat, tmp_path):
    """--speed and --deform shape the random camera path alone: with a static picture or a video they were ignored
    without a word. An --fps below 1 is a frame period given for the rate (5e-05 s at 20 kHz): it was recorded, and
    every time (--start 2.5s, the video's t) came out 10^8 times too long. Each refused before anything is made, in
    the CLI and in the Python API's words."""
    import imageio.v3 as iio

    from cscsr import lazy
    from stages.errors import InputError

    picture, folder = tmp_path / "p.png", tmp_path / "video"
    iio.imwrite(picture, np.zeros((32, 32, 3), np.uint8))
    folder.mkdir()
    for i in range(2):
        iio.imwrite(folder / f"{i}.png", np.full((32, 32, 3), 60 * i, np.uint8))
    out = tmp_path / "out.zarr"
    for args, words in (
            (("simulate", picture, out, "--motion", "static", "--speed", 1),
             "--speed applies to the random camera path (--motion random) only, not to --motion static"),
            (("simulate", folder, out, "--deform", 0.5, "--speed", 1),
             "--speed and --deform apply to the random camera path (--motion random) only, not to a video's own"),
            (("simulate", picture, out, "--motion", "random", "--fps", 5e-5),
             "--fps must be >= 1 spike frame a second, got 5e-05: it is a rate, not a frame period"),
            (("ingest", small_dat, out, "--height", 8, "--width", 16, "--fps", 0.5), "--fps must be >= 1"),
            (("ingest", small_dat, out, "--height", 8, "--width", 16, "--fps", 0), "--fps must be > 0, got 0")):
        assert_refused(cli(*args), words)
        assert not out.exists()
    assert lazy.open_frames(picture, frames=41, motion="random", speed=0.2).shape == (41, 32, 32, 3)
    with pytest.raises(InputError, match=r"^speed applies to the random camera path \(motion random\) only"):
        lazy.open_frames(picture, frames=41, motion="static", speed=1.0)
    with pytest.raises(InputError, match=r"^fps must be >= 1 spike frame a second, got 0.5"):
        lazy.simulate(lazy.open_frames(picture, frames=41, motion="random"), fps=0.5)


def test_a_new_store_named_as_a_file_of_another_format_is_refused(cli, small_dat, tmp_path):
    """``reconstruct rec.zarr out.mp4`` wrote a Zarr folder named out.mp4 (no video), ``ingest c.dat c.npy`` a
    spike store named as a NumPy file: refused in one line that names the store to give and the export that
    makes the file, before anything is made; in the Python API too."""
    from cscsr import lazy
    from stages.errors import InputError

    store = tmp_path / "s.zarr"
    assert cli("ingest", small_dat, store, "--height", 8, "--width", 16).exit_code == 0
    for args, words in ((("reconstruct", store, tmp_path / "out.mp4"),
                         f"out.mp4 names a video file, but this writes a video store (a Zarr folder): name it "
                         f"{tmp_path / 'out.zarr'} (cscsr export"),
                        (("ingest", small_dat, tmp_path / "out.npy", "--height", 8, "--width", 16),
                         "out.npy names a NumPy array, but this writes a spike store"),
                        (("reconstruct", store, tmp_path / "out.PNG", "--dry-run"), "out.PNG names a picture")):
        assert_refused(cli(*args), words)
    with pytest.raises(InputError, match=r"out.avi names a video file, but this writes a video store"):
        lazy.to_video(lazy.reconstruct(lazy.windows(lazy.open_spikes(store)), method="tfp"), tmp_path / "out.avi")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.dat", "s.zarr"]
