"""Distributed reconstruction on a real LocalCluster(n_workers=2), real Zarr stores, real processes."""

import contextlib
import os
import time

import imageio.v3 as iio
import numpy as np
import pytest
import zarr

from pipeline.compute.hold import hold_environment
import pipeline.jobs.reconstruct as reconstruct_job
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from stages.reconstruction.methods import output_centres
from pipeline.jobs.simulate import SimulateOptions, simulate
from tests.conftest import CSCSR, committed_tasks, kill_mid_job, with_random_heads
from tests.test_bad_input import assert_refused
from tests.test_simulate import chunk_files, picture


@pytest.fixture(scope="module")
def recording(tmp_path_factory, client) -> str:
    """150 frames of a moving colour picture, LR 32x32 (HR 128x128), ground truth every 10 frames."""
    folder = tmp_path_factory.mktemp("recording")
    iio.imwrite(folder / "astronaut.png", picture("astronaut", 128))
    store = str(folder / "sim.zarr")
    simulate(str(folder / "astronaut.png"), store, SimulateOptions(scale=4, frames=150, motion="random", speed=0.2,
                                                                   reset="subtract", truth_every=10), workers=2, progress=False)
    return store


def video(url: str) -> tuple[np.ndarray, np.ndarray, dict]:
    group = zarr.open_group(url, mode="r")
    return group["video"][:], group["frames"][:], dict(group.attrs)


@pytest.mark.parametrize("every,expected", [(41, [20, 61, 102]), (10, list(range(20, 130, 10))), (1, list(range(20, 130)))])
def test_frames_at_the_recording_ends(recording, client, tmp_path, every, expected):
    assert output_centres(150, 41, every) == expected  # the last centre leaves 20 frames after it: 129 + 20 = 149
    out = str(tmp_path / "out.zarr")
    counts = reconstruct(recording, out, ReconstructOptions(every=every), client=client, progress=False)
    frames, centres, attrs = video(out)
    assert frames.shape == (len(expected), 128, 128, 3)
    assert list(centres) == expected and counts["frames"] == len(expected)
    assert attrs["state"] == "complete" and attrs["method"] == "tfp" and attrs["every"] == every
    assert output_centres(41, 41, 5) == [20] and output_centres(40, 41, 1) == []


def test_one_and_two_workers_give_identical_bytes(recording, client, tmp_path):
    options = ReconstructOptions(method="tfi", every=10, tile=16)
    reconstruct(recording, str(tmp_path / "two.zarr"), options, client=client, progress=False)
    reconstruct(recording, str(tmp_path / "one.zarr"), options, workers=1, progress=False)
    assert chunk_files(str(tmp_path / "one.zarr")) == chunk_files(str(tmp_path / "two.zarr"))


@pytest.mark.parametrize("method", ["tfp", "tfi"])
def test_tiled_equals_untiled_exactly(recording, client, tmp_path, method):
    """Halos cover the demosaicking and upsampling supports: tiles leave no seam at all."""
    whole, tiled = str(tmp_path / "whole.zarr"), str(tmp_path / "tiled.zarr")
    reconstruct(recording, whole, ReconstructOptions(method=method, every=41, tile=256), client=client, progress=False)
    reconstruct(recording, tiled, ReconstructOptions(method=method, every=41, tile=8), client=client, progress=False)
    whole_video, tiled_video = video(whole)[0], video(tiled)[0]
    assert zarr.open_group(tiled)["committed"].shape == (3, 4, 4)
    np.testing.assert_array_equal(tiled_video, whole_video)


def test_reconstruction_agrees_with_the_truth(recording, client, tmp_path):
    out = str(tmp_path / "out.zarr")
    reconstruct(recording, out, ReconstructOptions(every=10), client=client, progress=False)
    truth = zarr.open_group(recording)["truth"][:].astype(np.float64)
    frames = video(out)[0].astype(np.float64)
    psnr = lambda a, b: 10 * np.log10(255**2 / ((a - b) ** 2).mean())
    # Blurred by motion and a x4 bicubic from 32x32 (measured 17.6 dB), but the same pictures:
    assert psnr(frames, truth) > 15
    assert psnr(frames, truth) > psnr(frames, truth[:, :, ::-1]) + 3  # a mirrored truth agrees far less
    assert np.corrcoef(frames.ravel(), truth.ravel())[0, 1] > 0.85


def test_resume_after_a_killed_run(recording, client, tmp_path, monkeypatch):
    clean, killed = str(tmp_path / "clean.zarr"), str(tmp_path / "killed.zarr")
    options = ReconstructOptions(method="tfi", every=10, tile=16)  # 11 frames x 4 tiles
    reconstruct(recording, clean, options, client=client, progress=False)
    total = 11 * 4

    command = [CSCSR, "reconstruct", recording, killed, "--method", "tfi", "--every", "10", "--tile", "16",
               "--workers", "1"]
    # the job's tasks hold after the 20th (pipeline.compute.hold): the kill lands mid-job on any machine, under any load
    kill_mid_job(command, lambda: committed_tasks(killed) >= 20,
                 env={**os.environ, **hold_environment(20, tmp_path / "never")})
    done_before = committed_tasks(killed)
    assert 20 <= done_before < total, done_before
    assert zarr.open_group(killed, mode="r").attrs["state"] == "writing"  # not passing for complete

    frames_before = int(zarr.open_group(killed, mode="r")["committed"][:].all(axis=(1, 2)).sum())
    bars = []

    @contextlib.contextmanager
    def recorded(description, total, *, done=0, unit="frames", enabled=True):
        bars.append({"total": total, "done": done, "advanced": []})
        yield bars[-1]["advanced"].append

    monkeypatch.setattr(reconstruct_job, "progress_bar", recorded)
    counts = reconstruct(recording, killed, ReconstructOptions(**{**options.__dict__, "resume": True}),
                         client=client, progress=True)
    assert counts["tasks_skipped"] == done_before and counts["tasks_run"] == total - done_before
    # the bar holds every output frame, those committed before shown done from its start, each other one once
    assert bars == [{"total": 11, "done": frames_before, "advanced": [1] * (11 - frames_before)}]
    resumed, clean_video = video(killed), video(clean)
    np.testing.assert_array_equal(resumed[0], clean_video[0])
    assert resumed[2]["state"] == "complete"
    # a write cut off by the kill may leave zarr's temporary file (NAME.<hex>.partial), which no reader opens
    assert {k for k in chunk_files(killed) if not k.endswith(".partial")} == chunk_files(clean).keys()
    for name, content in chunk_files(clean).items():
        if name.startswith(("video/", "committed/", "frames/")):
            assert chunk_files(killed)[name] == content, name


def test_resume_refuses_other_parameters(recording, client, tmp_path):
    out = str(tmp_path / "out.zarr")
    reconstruct(recording, out, ReconstructOptions(every=41), client=client, progress=False)
    with pytest.raises(ValueError, match="other parameters.*every 41 -> 10"):
        reconstruct(recording, out, ReconstructOptions(every=10, resume=True), client=client, progress=False)


def test_export_mp4_and_pngs(recording, client, cli, tmp_path):
    out = str(tmp_path / "out.zarr")
    reconstruct(recording, out, ReconstructOptions(every=41), client=client, progress=False)
    assert cli("export", out, tmp_path / "video.mp4").exit_code == 0
    decoded = iio.imread(tmp_path / "video.mp4")
    assert decoded.shape == (3, 128, 128, 3)
    assert np.abs(decoded.astype(float) - video(out)[0]).mean() < 6  # H.264 is lossy, but close
    assert cli("export", out, tmp_path / "frames").exit_code == 0
    assert sorted(os.listdir(tmp_path / "frames")) == ["frame_00000020.png", "frame_00000061.png", "frame_00000102.png"]
    np.testing.assert_array_equal(iio.imread(tmp_path / "frames" / "frame_00000061.png"), video(out)[0][1])


def test_evaluate_writes_table_csv_and_picture(recording, cli, tmp_path):
    result = cli("evaluate", recording, "--methods", "tfp,tfi", "--out", tmp_path / "ev", "--workers", 2)
    assert result.exit_code == 0, result.stderr
    assert "tfp" in result.stdout and "tfi" in result.stdout and "PSNR" in result.stdout
    summary = (tmp_path / "ev" / "summary.csv").read_text().splitlines()
    assert summary[0].startswith("method,psnr,ssim") and len(summary) == 3
    psnrs = [float(line.split(",")[1]) for line in summary[1:]]
    assert all(15 < value < 50 for value in psnrs)
    assert len((tmp_path / "ev" / "metrics.csv").read_text().splitlines()) == 1 + 2 * 11
    picture_ = iio.imread(tmp_path / "ev" / "comparison.png")
    assert picture_.shape == (128 + 22, 3 * 128 + 2 * 4, 3)


def test_bad_input(cli, recording, tmp_path):
    out = tmp_path / "out.zarr"
    zarr.open_group(str(tmp_path / "empty.zarr"), mode="w", attributes={"height": 8, "width": 8, "cfa": "mono"})
    assert_refused(cli("reconstruct", tmp_path / "empty.zarr", out, "--workers", 1), "no 'spikes' array")
    np.save(tmp_path / "short.npy", np.zeros((30, 8, 8), np.uint8))
    assert cli("ingest", tmp_path / "short.npy", tmp_path / "short.zarr").exit_code == 0
    assert_refused(cli("reconstruct", tmp_path / "short.zarr", out, "--workers", 1), "longer than the recording (30 frames)")
    assert_refused(cli("reconstruct", recording, out, "--window", 40, "--workers", 1), "positive odd number")
    assert_refused(cli("reconstruct", recording, out, "--window", 151, "--workers", 1), "longer than the recording")
    assert_refused(cli("reconstruct", recording, out, "--every", 0, "--workers", 1), "--every must be >= 1")
    assert_refused(cli("reconstruct", recording, out, "--method", "magic", "--workers", 1), "unknown method 'magic'")
    assert_refused(cli("evaluate", tmp_path / "short.zarr", "--out", tmp_path / "ev", "--workers", 1), "no ground truth")
    assert not out.exists()
    start = time.time()
    assert_refused(cli("reconstruct", recording, out, "--scheduler", "tcp://127.0.0.1:9"), "cannot reach Dask scheduler")
    assert time.time() - start < 15 and not out.exists()
    out.mkdir()
    assert_refused(cli("reconstruct", recording, out, "--workers", 1), "already exists", "--resume or --overwrite")
    assert_refused(cli("reconstruct", recording, tmp_path / "none.zarr", "--resume", "--workers", 1), "does not exist")


def test_submission_stays_in_a_bounded_window(client):
    """However many tasks a job has, at most ``limit`` are submitted and unfinished at once."""
    from pipeline.compute.executor import in_bounded_window

    submitted, finished = [0], [0]

    def submissions():
        for i in range(200):
            assert submitted[0] - finished[0] < 6  # never more than the window outstanding
            submitted[0] += 1
            yield client.submit(lambda x: x, i, pure=False)

    results = []
    for future in in_bounded_window(submissions(), limit=6):
        finished[0] += 1
        results.append(future.result())
    assert sorted(results) == list(range(200))


def test_a_video_store_is_a_simulation_source(recording, client, tmp_path):
    """Stages compose through stores: reconstructed HR video -> simulated spikes again."""
    video_store = str(tmp_path / "video.zarr")
    reconstruct(recording, video_store, ReconstructOptions(every=41), client=client, progress=False)
    again = str(tmp_path / "again.zarr")
    simulate(video_store, again, SimulateOptions(scale=2, frames=41, interp="linear"), workers=1, progress=False)
    group = zarr.open_group(again, mode="r")
    assert group["spikes"].shape == (41, 64, 8) and group["truth"].shape == (1, 128, 128, 3)
    frames = video(video_store)[0]
    # 3 source frames spread over spike frames 0..40: frame 20 falls exactly on source frame 1.
    np.testing.assert_array_equal(group["truth"][0], frames[1])


@pytest.fixture(scope="module")
def random_weights(tmp_path_factory) -> str:
    """A randomly initialised ``lite`` network saved as safetensors (trained weights are another issue)."""
    import torch

    from cscsr.network.config import named
    from cscsr.network.model import CSCSR
    from cscsr.weights.weights_io import save_weights

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("weights") / "lite-random.safetensors"
    save_weights(with_random_heads(CSCSR(named("lite"))), path, steps="0 (random initialisation)")
    return str(path)


def test_cscsr_on_the_cluster_matches_the_network_run_directly(recording, client, random_weights, tmp_path):
    """4 tiles per frame, batched frames, two worker processes: the same bytes as one process
    running the network on whole frames (the 32-px halo covers this 32x32 frame from every tile)."""
    import torch

    from cscsr.weights.weights_io import load_model
    from pipeline.stores.spike_store import open_spike_store
    from stages.capture.bits import unpack_rows
    from stages.reconstruction.colour import expose

    out = str(tmp_path / "cscsr.zarr")
    options = ReconstructOptions(method="cscsr", weights=random_weights, every=41, tile=16)
    counts = reconstruct(recording, out, options, client=client, progress=False)
    frames, centres, attrs = video(out)
    assert frames.shape == (3, 128, 128, 3) and counts["tasks_run"] == 4  # a task a tile: its 3 frames, one batch
    assert attrs["state"] == "complete" and attrs["method"] == "cscsr" and attrs["weights"] == random_weights

    store = open_spike_store(recording)
    model, _ = load_model(random_weights)
    clips = np.stack([unpack_rows(store.read(c - 20, c + 21), 32) for c in centres])
    from cscsr.inference.reconstructor import one_thread_on_cpu

    with one_thread_on_cpu(torch.device("cpu")), torch.inference_mode():  # as the workers run it
        rate = model(torch.from_numpy(clips).float(), store.meta.cfa, store.meta.reset == "zero", 4)["image"]
    expected = np.stack([expose(r, attrs["gain"]) for r in rate.permute(0, 2, 3, 1).numpy()])
    assert np.array_equal(frames, expected)

    reconstruct(recording, str(tmp_path / "one.zarr"), options, workers=1, progress=False)
    assert chunk_files(str(tmp_path / "one.zarr")) == chunk_files(out)


def test_cscsr_ensemble_on_the_cluster_matches_the_self_ensemble_run_directly(recording, client, random_weights,
                                                                             tmp_path):
    """--method cscsr-ensemble: the network averaged over 8 flips and turns, the same bytes on two
    workers as the reconstructor run in this process, and not the plain network's bytes."""
    from cscsr.inference.reconstructor import load_reconstructor
    from pipeline.stores.spike_store import open_spike_store
    from stages.reconstruction.methods import Window

    out = str(tmp_path / "ensemble.zarr")
    reconstruct(recording, out, ReconstructOptions(method="cscsr-ensemble", weights=random_weights, every=41),
                client=client, progress=False)
    frames, centres, attrs = video(out)
    assert attrs["state"] == "complete" and attrs["method"] == "cscsr-ensemble"

    store = open_spike_store(recording)
    windows = [Window(store.read(c - 20, c + 21), 32, store.meta.cfa, store.meta.reset, attrs["gain"], 4)
               for c in centres]
    ensemble = load_reconstructor(random_weights, "cpu", self_ensemble=True)
    assert np.array_equal(frames, np.stack(ensemble.many(windows)))
    plain = load_reconstructor(random_weights, "cpu")
    assert not np.array_equal(frames, np.stack(plain.many(windows)))


@pytest.mark.parametrize("method", ["cscsr", "cscsr-ensemble"])
def test_network_refusals(method, cli, recording, random_weights, tmp_path):
    out = tmp_path / "out.zarr"
    assert_refused(cli("reconstruct", recording, out, "--method", method, "--weights", tmp_path / "none.safetensors",
                       "--workers", 1), "weights file", "not found")
    assert_refused(cli("reconstruct", recording, out, "--method", method, "--weights", random_weights,
                       "--window", 21, "--workers", 1), "takes windows of 41 frames")
    assert_refused(cli("reconstruct", recording, out, "--method", method, "--weights", random_weights,
                       "--scale", 3, "--workers", 1), "upsamples by 2 or 4")
    np.save(tmp_path / "mono.npy", np.zeros((41, 8, 8), np.uint8))
    assert cli("ingest", tmp_path / "mono.npy", tmp_path / "mono.zarr").exit_code == 0
    assert_refused(cli("reconstruct", tmp_path / "mono.zarr", out, "--method", method, "--weights", random_weights,
                       "--workers", 1), "mono")
    assert not out.exists()
    out.mkdir()
    assert_refused(cli("reconstruct", recording, out, "--method", method, "--weights", tmp_path / "none.safetensors",
                       "--overwrite", "--workers", 1), "not found")
    assert out.exists()  # a refused --overwrite leaves the old output alone


def test_blocks_are_fixed_by_frame_number():
    from pipeline.jobs.reconstruct_tasks import MethodSpec, cut
    from stages.reconstruction.tiles import tile_grid

    grid = tile_grid(16, 32, 16, 0)  # two tiles, one a block
    blocks = cut(MethodSpec("tfp"), "rec.zarr", "id", list(range(20, 30)), 0, 1, 41, grid, 4, "rggb", "subtract", 4,
                 16, 1.0, False, 50)  # a method of 4 windows a pass, a recording of 50 frames: these are its all
    assert blocks.frames == (4, 4, 2) and list(blocks.units())[:3] == [(0, 0), (0, 1), (1, 0)]
    done = np.zeros((10, 1, 2), bool)
    done[0:4, 0, 0] = True
    done[4, 0, 1] = True  # a partly done block runs whole, exactly as it did the first time
    units = list(blocks.units(done))
    assert (0, 0) not in units and (1, 1) in units and (2, 1) in units
