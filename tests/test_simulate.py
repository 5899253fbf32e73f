"""The simulator end to end on a real two-worker LocalCluster, real Zarr stores, real files."""

import hashlib
import os

import cv2
import imageio.v3 as iio
import numpy as np
import pytest
import zarr
from skimage import data

from pipeline.jobs.preview import preview
from pipeline.jobs.simulate import SimulateOptions, simulate
from pipeline.stores.spike_store import open_spike_store
from stages.capture.bits import unpack_rows
from stages.reconstruction.cfa import colour_index
from stages.measures.metrics import psnr
from stages.simulation.camera_path import backward_warp
from stages.simulation.sensor import area_downsample
from tests.test_bad_input import assert_refused


def picture(name: str, size: int) -> np.ndarray:
    """A bundled scikit-image picture, centre-cropped square and resized to ``size``."""
    image = getattr(data, name)()
    side = min(image.shape[:2])
    top, left = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
    return cv2.resize(image[top:top + side, left:left + side], (size, size), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="module")
def still(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("src") / "astronaut.png"
    iio.imwrite(path, picture("astronaut", 64))
    return str(path)


def read_arrays(url: str) -> dict:
    group = zarr.open_group(url, mode="r")
    return {name: group[name][:] for name in ("spikes", "truth", "truth_frames", "flow") if name in group}


def chunk_files(url: str) -> dict:
    files = {}
    for root, _, names in os.walk(url):
        for name in names:
            path = os.path.join(root, name)
            files[os.path.relpath(path, url)] = open(path, "rb").read()
    return files


def test_bit_identical_whatever_workers_and_chunking(still, tmp_path):
    options = dict(scale=2, frames=120, motion="random", deform=1.5, noise="realistic", reset="zero", truth_every=30, seed=7)
    one = str(tmp_path / "one.zarr")
    two = str(tmp_path / "two.zarr")
    other = str(tmp_path / "other_chunks.zarr")
    simulate(still, one, SimulateOptions(**options, chunk_frames=16), workers=1, progress=False)
    simulate(still, two, SimulateOptions(**options, chunk_frames=16), workers=2, progress=False)
    simulate(still, other, SimulateOptions(**options, chunk_frames=50), workers=2, progress=False)
    assert chunk_files(one) == chunk_files(two)  # every byte, metadata included
    first, last = read_arrays(one), read_arrays(other)
    assert first.keys() == last.keys() == {"spikes", "truth", "truth_frames", "flow"}
    for name in first:
        np.testing.assert_array_equal(first[name], last[name])
    assert first["spikes"].any()
    # A different seed changes the recording (the comparison above can fail).
    simulate(still, str(tmp_path / "seed.zarr"), SimulateOptions(**{**options, "seed": 8}, chunk_frames=16), workers=2, progress=False)
    assert not np.array_equal(read_arrays(str(tmp_path / "seed.zarr"))["spikes"], first["spikes"])


def test_static_subtract_fires_at_alpha_i_over_theta(still, tmp_path):
    alpha, theta, frames = 0.7, 1.3, 1000
    store = str(tmp_path / "static.zarr")
    simulate(still, store, SimulateOptions(scale=2, cfa="grbg", brightness=alpha, threshold=theta, frames=frames,
                                           motion="static", reset="subtract", chunk_frames=300), workers=2, progress=False)
    spikes = open_spike_store(store)
    rate = unpack_rows(spikes.read(0, frames), 32).mean(axis=0)
    hr = iio.imread(still).astype(np.float32) / 255
    lr = area_downsample(hr, 2)
    mosaic = np.take_along_axis(lr, colour_index("grbg", 32, 32)[:, :, None].astype(np.int64), axis=2)[:, :, 0]
    np.testing.assert_allclose(rate, np.clip(alpha * mosaic / theta, 0, 1), atol=1 / frames)
    attrs = spikes.attrs
    assert attrs["reset"] == "subtract" and attrs["gain"] == pytest.approx(theta / alpha)
    np.testing.assert_array_equal(read_arrays(store)["truth"][0], iio.imread(still))


@pytest.mark.parametrize("cfa,floor", [("mono", 30.0), ("rggb", 30.0)])
def test_round_trip_tfp_psnr_static_scale_1(tmp_path, cfa, floor):
    source = tmp_path / "coffee.png"
    iio.imwrite(source, picture("coffee", 96))
    store = str(tmp_path / "s.zarr")
    simulate(str(source), store, SimulateOptions(scale=1, cfa=cfa, frames=41, motion="static", reset="subtract"),
             workers=2, progress=False)
    truth = read_arrays(store)["truth"][0]
    shot = preview(store, centre=20)  # gain from the store: theta / alpha
    assert psnr(shot.image, truth) > floor


def test_zero_reset_bias_is_undone_by_the_classic_method(tmp_path):
    """Held-out pictures, reset zero: naive TFP is several dB worse than the inverted one."""
    from stages.reconstruction.tfp import tfp_rate

    gains = []
    for name in ("chelsea", "rocket", "immunohistochemistry"):
        source = tmp_path / f"{name}.png"
        iio.imwrite(source, picture(name, 64))
        store = str(tmp_path / f"{name}.zarr")
        simulate(str(source), store, SimulateOptions(scale=1, cfa="mono", brightness=0.8, frames=401, motion="static",
                                                     reset="zero", truth_every=400), workers=2, progress=False)
        opened = open_spike_store(store)
        assert opened.attrs["reset"] == "zero"
        truth = read_arrays(store)["truth"][0, :, :, 0].astype(np.float64)
        window = opened.read(0, 401)
        to_grey = lambda rate: np.round(np.clip(rate * opened.meta.gain, 0, 1) * 255)
        naive = psnr(to_grey(tfp_rate(window, 64, "subtract")), truth)
        undone = psnr(to_grey(tfp_rate(window, 64, "zero")), truth)
        gains.append(undone - naive)
    assert 3 <= np.mean(gains) <= 12, gains


def test_random_motion_flow_is_true(tmp_path):
    # A smooth picture: on a very sharp 64 px one, resampling blur alone gives ~0.02 error.
    source = tmp_path / "smooth.png"
    iio.imwrite(source, cv2.GaussianBlur(picture("astronaut", 64), (0, 0), 1.0))
    store = str(tmp_path / "moving.zarr")
    simulate(str(source), store, SimulateOptions(scale=2, frames=80, motion="random", speed=0.3, truth_every=6),
             workers=2, progress=False)
    arrays = read_arrays(store)
    truth, flow = arrays["truth"].astype(np.float32) / 255, arrays["flow"]
    assert flow.shape == (len(truth) - 1, 64, 64, 2)
    assert np.abs(flow).max() > 1  # it really moves
    inner = (slice(8, -8), slice(8, -8))
    for k in range(len(flow)):
        warped = backward_warp(truth[k + 1], flow[k])
        assert np.abs(warped - truth[k])[inner].mean() < 0.02
        assert np.abs(truth[k + 1] - truth[k])[inner].mean() > 2 * np.abs(warped - truth[k])[inner].mean()


@pytest.mark.parametrize("interp", ["flow", "linear"])
def test_video_and_folder_sources(tmp_path, interp):
    base = picture("astronaut", 96)
    frames = [np.roll(base, 3 * i, axis=1)[:64, :64] for i in range(4)]
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, frame in enumerate(frames):
        iio.imwrite(folder / f"{i:03d}.png", frame)
    iio.imwrite(tmp_path / "clip.mp4", np.stack(frames), fps=10, codec="libx264", quality=9)
    for src in (folder, tmp_path / "clip.mp4"):
        store = str(tmp_path / f"{src.name}-{interp}.zarr")
        simulate(str(src), store, SimulateOptions(scale=4, frames=82, interp=interp, truth_every=41), workers=2, progress=False)
        arrays = read_arrays(store)
        assert arrays["spikes"].shape == (82, 16, 2) and arrays["truth"].shape == (2, 64, 64, 3)
        assert list(arrays["truth_frames"]) == [20, 61]
        rate = unpack_rows(arrays["spikes"], 16).mean()
        assert 0.05 < rate < 0.6


def test_a_video_s_bytes_are_unchanged_since_the_first_simulator(tmp_path):
    """Known answer: the bytes simulated from these PNG frames, as the simulator wrote them before
    pair motions were shared and mosaics interpolated alone. A change to the latent frames, the
    sensor or the truth changes this digest: say so in docs/simulator.md (reproducibility)."""
    base = cv2.resize(data.astronaut(), (128, 128), interpolation=cv2.INTER_AREA)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(4):
        iio.imwrite(folder / f"{i:03d}.png", np.roll(base, (2 * i, 5 * i), axis=(0, 1))[:64, :96])
    store = str(tmp_path / "gbrg.zarr")
    simulate(str(folder), store, SimulateOptions(scale=4, cfa="gbrg", frames=82, interp="flow", truth_every=20,
                                                 chunk_frames=16), workers=2, progress=False)
    arrays = read_arrays(store)
    digest = hashlib.sha256(arrays["spikes"].tobytes() + arrays["truth"].tobytes()).hexdigest()
    assert digest[:16] == "1c2e7e17b9e30dd3"


def test_a_worker_decodes_each_source_frame_once(tmp_path, monkeypatch):
    from cscsr import lazy
    from pipeline.jobs import simulate_plan as scenes
    from pipeline.lazy.frames import made_scene
    from pipeline.stores.frame_sources import FrameSource

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        iio.imwrite(folder / f"{i:03d}.png", np.roll(picture("astronaut", 64), 4 * i, axis=1))
    scene = made_scene(lazy.open_frames(folder, frames=82).data)  # the job's scene of the folder
    reads = []
    monkeypatch.setattr(FrameSource, "read", lambda self, index: reads.append(index) or iio.imread(self.files[index]))
    scenes.intensities.cache_clear()
    lr = [scene.lr_frame(i) for i in range(3)]  # each frame's LR task...
    assert scene.pair(60)[0] == 1 and 0 < scene.pair(60)[1] < 1
    truth = scene.intensities(60)  # ...then truth between frames 1 and 2 (their motion made from their LR frames)
    assert reads == [0, 1, 2] and truth.shape == (64, 64, 3)
    np.testing.assert_array_equal(lr[1], area_downsample(scenes.intensities(scene.source, scene.version, 1), 4))


@pytest.mark.parametrize("args,fragment", [
    (["--threshold", 0], "threshold"),
    (["--brightness", -1], "brightness"),
    (["--cfa", "rgbw"], "unknown CFA 'rgbw'"),
    (["--interp", "cubic"], "unknown interpolation 'cubic'"),
    (["--frames", 40], "--frames 40 is too few"),
    (["--scale", 3], "scale must be one of"),
])
def test_bad_options(cli, still, tmp_path, args, fragment):
    out = tmp_path / "s.zarr"
    assert_refused(cli("simulate", still, out, "--motion", "static", "--workers", 1, *args), fragment)
    assert not out.exists()


def test_bad_sources(cli, tmp_path):
    iio.imwrite(tmp_path / "one.png", picture("camera", 64))
    iio.imwrite(tmp_path / "odd.png", picture("camera", 60))
    out = tmp_path / "s.zarr"
    assert_refused(cli("simulate", tmp_path / "one.png", out, "--workers", 1), "give --motion")
    assert_refused(cli("simulate", tmp_path / "odd.png", out, "--motion", "static", "--workers", 1), "not divisible by 2*scale = 8")
    assert_refused(cli("simulate", tmp_path / "none.mp4", out, "--workers", 1), "none.mp4")
    assert_refused(cli("simulate", tmp_path / "odd.png", out, "--motion", "static", "--cfa", "mono", "--scale", 8,
                       "--workers", 1), "scale")
    assert not out.exists()


def test_a_folder_of_frames_of_two_sizes_is_one_line_of_bad_input(cli, tmp_path):
    """Found as frame 1 is read, in a task: it was "SpikesIncomplete: to_spikes ...: fix the cause and call
    to_spikes again with resume=True", the Python API's advice, which the command cannot follow."""
    (tmp_path / "mixed").mkdir()
    iio.imwrite(tmp_path / "mixed" / "a.png", picture("camera", 64))
    iio.imwrite(tmp_path / "mixed" / "b.png", picture("camera", 32))
    result = cli("simulate", tmp_path / "mixed", tmp_path / "s.zarr", "--workers", 1)
    assert_refused(result, "mixed: frame 1 has shape (32, 32")
    assert "resume" not in result.stderr and "SpikesIncomplete" not in result.stderr
    assert not (tmp_path / "s.zarr").exists()


def test_evaluate_refuses_a_truth_smaller_than_ssim_s_window_before_any_reconstruction(cli, tmp_path):
    """An 8x8 scene: scikit-image's "win_size exceeds image extent ... at least 7x7" came after every method ran."""
    iio.imwrite(tmp_path / "tiny.png", picture("camera", 8))
    assert cli("simulate", tmp_path / "tiny.png", tmp_path / "tiny.zarr", "--motion", "static", "--workers", 1
               ).exit_code == 0
    assert_refused(cli("evaluate", tmp_path / "tiny.zarr", "--out", tmp_path / "ev", "--workers", 1),
                   "its truth frames are 8x8 HR pixels, smaller than SSIM's 11x11 window")
    assert not (tmp_path / "ev").exists()


def test_a_mono_sensor_takes_any_lr_size(cli, tmp_path):
    """A Bayer cell is 2x2 LR pixels, a mono pixel one: a 60x60 picture at x4 is a 15x15 mono recording (it was
    refused as "not divisible by 2*scale = 8 (mono Bayer cells ...)"), and gets its ground truth."""
    iio.imwrite(tmp_path / "odd.png", picture("camera", 60))
    out = tmp_path / "mono.zarr"
    done = cli("simulate", tmp_path / "odd.png", out, "--motion", "random", "--frames", 41, "--cfa", "mono",
               "--workers", 1)
    assert done.exit_code == 0, done.stderr
    store = open_spike_store(str(out))
    assert store.shape == (41, 15, 15) and store.attrs["cfa"] == "mono" and store.group["truth"].shape[1:3] == (60, 60)
    assert_refused(cli("simulate", tmp_path / "odd.png", tmp_path / "rggb.zarr", "--motion", "static", "--workers", 1),
                   "not divisible by 2*scale = 8 (a rggb cell of 2x2 LR pixels is 8x8 HR pixels)")


def test_a_zarr_source_without_video_names_the_video_stores_dimensions(cli, tmp_path):
    zarr.open_group(tmp_path / "other.zarr", mode="w").create_array("pictures", shape=(2, 8, 8, 3), dtype=np.uint8)
    result = cli("simulate", tmp_path / "other.zarr", tmp_path / "s.zarr", "--workers", 1)
    assert_refused(result, "without a 'video' array (j, hr_y, hr_x, c")  # the video store's own dimension names
    assert "t, y, x" not in result.stderr and not (tmp_path / "s.zarr").exists()


def test_a_video_s_lr_frames_and_pair_motions_are_one_task_each(tmp_path):
    """The job's graph of a video of 4 frames over 100 spike frames in chunks of 40: every chunk's mosaics read the
    LR frames and motion of the pairs they lie in (0-1, 1-2 and 2-3), each made by one task of the graph."""
    from cscsr import lazy

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(4):
        iio.imwrite(folder / f"{i:03d}.png", np.roll(picture("astronaut", 64), 4 * i, axis=1))
    spikes = lazy.simulate(lazy.open_frames(folder, frames=100, chunk_frames=40), truth_every=30)
    graph = dict(spikes.data.__dask_graph__())
    names = [key[0].rsplit("-", 1)[-1] for key in graph if isinstance(key, tuple) and "-source-" in key[0]]
    assert sorted(names) == ["lr"] * 4 + ["motion"] * 3
    pairs = [[pair[0] for pair in task[2]] for key, task in graph.items() if "increments" in str(key)]
    assert sorted(pairs) == [[0, 1], [1, 2], [2]]


def test_the_job_s_workers_never_import_dask_array(still, tmp_path):
    """The job builds its graph in its own process; its workers run the tasks without ``dask.array`` (which imports
    xarray, pandas and SciPy's extras: 50 MiB a worker), as before it was a front door to the lazy stages."""
    import sys

    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, dashboard_address=":0") as cluster, Client(cluster) as client:
        simulate(still, str(tmp_path / "s.zarr"), SimulateOptions(scale=2, frames=60, motion="random", chunk_frames=20),
                 scheduler=cluster.scheduler_address, progress=False)
        imported = client.run(lambda: sorted(name for name in ("dask.array", "xarray", "pandas") if name in sys.modules))
    assert list(imported.values()) == [[]]
    assert zarr.open_group(str(tmp_path / "s.zarr"), mode="r").attrs["state"] == "complete"  # it ran there


def test_a_failed_simulation_says_what_the_command_line_can_do(tmp_path, monkeypatch):
    """A task's failure other than bad input (a worker's disk, a lost cluster): the error named what the Python API
    can do (``call to_spikes again with resume=True``) to a user of ``cscsr simulate``, which has no --resume and
    removed the store. It says the store was removed and to run the command again."""
    import pipeline.jobs.simulate as job
    from pipeline.stores.spike_writes import SpikesIncomplete

    def failed(writes, *args, **kwargs):
        try:
            raise OSError(28, "No space left on device")
        except OSError as cause:
            raise SpikesIncomplete(f"to_spikes {writes.url}: 0 of 1 tasks committed ... call to_spikes again with "
                                   f"resume=True") from cause

    iio.imwrite(tmp_path / "p.png", np.zeros((32, 32, 3), np.uint8))
    monkeypatch.setattr(job, "write_store", failed)
    with pytest.raises(SpikesIncomplete) as raised:
        job.simulate(str(tmp_path / "p.png"), str(tmp_path / "s.zarr"), SimulateOptions(frames=41, motion="static"),
                     workers=1, progress=False)
    assert str(raised.value) == (f"simulate {tmp_path / 's.zarr'}: [Errno 28] No space left on device: the "
                                 f"unfinished store was removed (a simulation is not resumed): fix the cause and run "
                                 f"it again")
