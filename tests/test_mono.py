"""Mono recordings through the network (issue 57): the mono configuration, its shipped weights by default on
the command line, the Python API and the lazy graphs, and both mismatches of weights and recording refused."""

import json
import subprocess
import tomllib
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import zarr

from cscsr.network.config import CSCSRConfig, named
from cscsr.network.model import CSCSR
from cscsr.weights.mono_init import mono_state
from cscsr.weights.weights_io import default_weights, load_model, read_metadata
from pipeline.jobs.simulate import SimulateOptions, simulate
from tests.test_bad_input import assert_refused
from tests.test_simulate import chunk_files, picture

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = "cscsr/weights/cscsr-lite-mono.safetensors"


@pytest.fixture(scope="module")
def mono(tmp_path_factory) -> str:
    """A colour picture seen by a mono sensor, moving: 82 frames of LR 24x24 (x4), truth at both windows."""
    folder = tmp_path_factory.mktemp("mono")
    iio.imwrite(folder / "coffee.png", picture("coffee", 96))
    store = str(folder / "mono.zarr")
    simulate(str(folder / "coffee.png"), store, SimulateOptions(scale=4, cfa="mono", frames=82, motion="random",
                                                                speed=0.2, reset="subtract", truth_every=41, seed=5),
             workers=1, progress=False)
    return store


def test_the_mono_network_is_the_colour_one_with_one_branch():
    lite, mono = CSCSR(named("lite")), CSCSR(named("lite-mono"))
    assert len(mono.bssr) == len(mono.temporal) == 1 and len(lite.bssr) == 3
    assert mono.integration.fuse.in_channels == 24 + 1 + 2 and mono.integration.heads[1].out_channels == 1
    # a file from before the switch (no "colours" in its configuration) is a colour network
    old = {k: v for k, v in json.loads(named("lite").to_json()).items() if k != "colours"}
    assert CSCSRConfig.from_json(json.dumps(old)) == named("lite")
    for bad in (2, 0):
        with pytest.raises(Exception, match="colours must be 3"):
            CSCSRConfig("x", colours=bad).check()


def test_the_mono_start_is_the_colour_network_s_green_branch():
    colour, _ = load_model("lite")
    state = mono_state(colour.state_dict(), colour.config)
    model = CSCSR(named("lite-mono")).eval()
    model.load_state_dict(state)  # every tensor of the mono network, shapes as it needs them
    assert torch.equal(state["bssr.0.window.weight"], colour.state_dict()["bssr.1.window.weight"])
    fuse = colour.state_dict()["integration.fuse.weight"]  # (48, 3*24 + 1 + 6, 3, 3)
    assert torch.equal(state["integration.fuse.weight"][:, 24], fuse[:, 72])  # the reset
    assert torch.allclose(state["integration.fuse.weight"][:, 25], fuse[:, 73:76].sum(1))  # TFP: R + G + B
    assert torch.allclose(state["integration.heads.1.weight"][0], colour.state_dict()["integration.heads.1.weight"].mean(0))
    spikes = (torch.rand(2, 41, 13, 10, generator=torch.Generator().manual_seed(0)) < 0.3).float()  # odd: mono may
    with torch.inference_mode():
        image = model(spikes, "mono", False, 4)["image"]
    assert image.shape == (2, 3, 52, 40) and torch.equal(image[:, 0], image[:, 2])  # grey as three equal channels
    with pytest.raises(Exception, match="mono CSCSR network and the clip's CFA is 'rggb'"):
        model(spikes[..., :12, :], "rggb")
    with pytest.raises(Exception, match="colour .Bayer. CSCSR network and the clip is mono"):
        colour(spikes[..., :12, :], "mono")


def test_a_mono_store_through_the_network_by_cli_api_and_lazy(mono, cli, tmp_path):
    """Without --weights a mono recording takes the shipped mono weights; the command line on one worker, the
    API on two and the lazy graph write the same bytes, which are the network's own on the whole windows."""
    import cscsr
    from cscsr import lazy
    from pipeline.stores.spike_store import open_spike_store
    from stages.reconstruction.methods import Window
    from cscsr.inference.reconstructor import load_reconstructor

    one, two, graph = tmp_path / "one.zarr", str(tmp_path / "two.zarr"), str(tmp_path / "lazy.zarr")
    assert cli("reconstruct", mono, one, "--method", "cscsr", "--workers", 1).exit_code == 0
    written = cscsr.reconstruct(mono, two, method="cscsr", workers=2)
    import dask

    with dask.config.set(scheduler="threads"):
        lazy.to_video(lazy.reconstruct(lazy.windows(lazy.open_spikes(mono), every=41), method="cscsr"), graph)
    attrs = zarr.open_group(str(one), mode="r").attrs
    assert attrs["weights"].endswith("cscsr-lite-mono.safetensors") and written.attrs["weights"] == attrs["weights"]
    assert chunk_files(str(one)) == chunk_files(two)
    video = zarr.open_group(str(one), mode="r")["video"][:]
    assert np.array_equal(video, zarr.open_group(graph, mode="r")["video"][:])
    assert video.shape == (2, 96, 96, 3) and np.array_equal(video[..., 0], video[..., 1])

    store = open_spike_store(mono)
    windows = [Window(store.read(c - 20, c + 21), 24, "mono", store.meta.reset, attrs["gain"], 4) for c in (20, 61)]
    assert np.array_equal(video, np.stack(load_reconstructor(str(default_weights("lite-mono")), "cpu").many(windows)))


def test_weights_and_recording_of_different_kinds_are_refused(mono, cli, tmp_path):
    out = tmp_path / "out.zarr"
    assert_refused(cli("reconstruct", mono, out, "--method", "cscsr", "--weights", "lite", "--workers", 1),
                   "cscsr-lite.safetensors hold a colour (Bayer) CSCSR network and the recording", "is mono")
    np.save(tmp_path / "bayer.npy", np.zeros((41, 8, 8), np.uint8))
    assert cli("ingest", tmp_path / "bayer.npy", tmp_path / "bayer.zarr", "--cfa", "rggb").exit_code == 0
    assert_refused(cli("reconstruct", tmp_path / "bayer.zarr", out, "--method", "cscsr", "--weights", "lite-mono",
                       "--workers", 1), "cscsr-lite-mono.safetensors hold a mono CSCSR network and the recording",
                   "colour (Bayer rggb)")
    assert not out.exists()


def test_the_mono_weights_ship_with_the_package_and_describe_their_training():
    tracked = subprocess.run(["git", "ls-files", "--error-unmatch", SHIPPED], cwd=ROOT, capture_output=True)
    assert tracked.returncode == 0  # committed: a fresh clone has it
    package_data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "*.safetensors" in package_data["cscsr.weights"]  # and so does an installed package
    metadata = read_metadata(default_weights("lite-mono"))
    assert json.loads(metadata["config"])["colours"] == 1 and int(metadata["steps"]) >= 100
    assert metadata["command"].startswith("cscsr train") and "mono" in metadata["data"]
    model, _ = load_model("lite-mono")
    assert model.config.mono and 0.8e6 < model.parameter_counts()["network"] < 0.85e6


def test_onnx_and_bf16_run_the_mono_network(mono, client, tmp_path):
    """--backend onnx and --precision bf16 take a mono recording as the colour ones: close to fp32 torch."""
    import cscsr

    videos = {}
    for name, options in {"fp32": {}, "onnx": {"backend": "onnx"}, "bf16": {"precision": "bf16"}}.items():
        written = cscsr.reconstruct(mono, str(tmp_path / f"{name}.zarr"), method="cscsr", client=client, **options)
        assert written.attrs["weights"].endswith("cscsr-lite-mono.safetensors")
        videos[name] = zarr.open_group(str(tmp_path / f"{name}.zarr"), mode="r")["video"][:].astype(int)
    assert np.abs(videos["onnx"] - videos["fp32"]).max() <= 1  # float rounding
    bf16 = np.abs(videos["bf16"] - videos["fp32"])
    assert bf16.mean() < 2 and np.array_equal(videos["bf16"][..., 0], videos["bf16"][..., 2])


def test_the_watcher_takes_each_recording_s_weights_by_its_cfa(tmp_path, client):
    """One watcher with --method cscsr and no --weights: a mono capture gets the mono weights, a colour one lite."""
    from pipeline.inbox.watch import WatchOptions, watch_once
    from tests.conftest import integrate_and_fire, smooth_rate, write_dat
    from tests.test_watch import settled, states

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    for name, cfa, seed in (("grey", "mono", 1), ("colour", "rggb", 2)):
        write_dat(inbox / f"{name}.dat", integrate_and_fire(smooth_rate(16, 16, seed=seed), 41, seed=seed))
        (inbox / f"{name}.json").write_text(json.dumps({"height": 16, "width": 16, "cfa": cfa}))
    settled(inbox)
    counts = watch_once(str(inbox), str(outbox), WatchOptions(method="cscsr", tile=16, settle=0), client)
    assert counts["processed"] == 2 and {k: v[0] for k, v in states(outbox).items()} == {"grey": "done", "colour": "done"}
    weights = {name: zarr.open_group(str(outbox / f"{name}.zarr"), mode="r").attrs["weights"] for name in ("grey", "colour")}
    assert weights["grey"].endswith("cscsr-lite-mono.safetensors") and weights["colour"].endswith("cscsr-lite.safetensors")


def test_a_mono_line_of_one_pixel_goes_through_the_network(mono, tmp_path):
    """A side of one pixel (a line-scan capture, a one-row selection at the frame's edge) is a mono clip like any
    other: it pads by repeating its one pixel. The network refused it with a Bayer clip's message, in every task,
    leaving a store that no --resume could finish. Through the lazy graph: each window the network's own."""
    import dask

    from cscsr import lazy
    from cscsr.inference.reconstructor import load_reconstructor
    from pipeline.stores.spike_store import open_spike_store
    from stages.reconstruction.methods import Window

    line = lazy.open_spikes(mono).isel(y=slice(0, 1))  # the recording's first row: the halo stops at its edges
    with dask.config.set(scheduler="threads"):
        lazy.to_video(lazy.reconstruct(lazy.windows(line, every=41), method="cscsr"), str(tmp_path / "l.zarr"))
    group = zarr.open_group(str(tmp_path / "l.zarr"), mode="r")
    frames = group["video"][:]
    assert group.attrs["state"] == "complete" and frames.shape == (2, 4, 96, 3)
    store = open_spike_store(mono)
    gain = group.attrs["gain"]
    windows = [Window(store.read(c - 20, c + 21)[:, :1], 24, "mono", store.meta.reset, gain, 4) for c in (20, 61)]
    assert np.array_equal(frames, np.stack(load_reconstructor(str(default_weights("lite-mono")), "cpu").many(windows)))
