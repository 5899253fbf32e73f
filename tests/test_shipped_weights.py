"""The weights that ship in cscsr/weights: used by default, described, and better than the classic methods."""

import json

import imageio.v3 as iio
import pytest
import zarr

from cscsr.weights.weights_io import default_weights, read_metadata
from pipeline.jobs.evaluate import evaluate
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from pipeline.jobs.simulate import SimulateOptions, simulate
from tests.test_simulate import chunk_files, picture

MARGIN_DB = 0.5  # measured: +1.59 dB over TFI on this clip (PSNR 22.32 vs 20.73, SSIM 0.710 vs 0.642)


@pytest.fixture(scope="module")
def held_out(tmp_path_factory) -> str:
    """A held-out picture (coffee: never in training) moving, LR 48x48 at x4, zero reset, truth at 3 windows."""
    folder = tmp_path_factory.mktemp("held_out")
    iio.imwrite(folder / "coffee.png", picture("coffee", 192))
    store = str(folder / "sim.zarr")
    simulate(str(folder / "coffee.png"), store,
             SimulateOptions(scale=4, cfa="grbg", frames=123, motion="random", speed=0.4, reset="zero", brightness=0.8,
                             truth_every=41, seed=3), workers=2, progress=False)
    return store


def test_the_shipped_weights_describe_how_they_were_made():
    metadata = read_metadata(default_weights("lite"))
    assert json.loads(metadata["config"])["name"] == "lite"
    assert int(metadata["steps"]) >= 1000 and metadata["command"].startswith("cscsr train")
    assert "alpha 0.6-1.0" in metadata["data"] and "four CFA phases" in metadata["data"]


def test_reconstruct_without_weights_uses_the_shipped_ones(held_out, client, tmp_path):
    implicit, explicit = str(tmp_path / "implicit.zarr"), str(tmp_path / "explicit.zarr")
    reconstruct(held_out, implicit, ReconstructOptions(method="cscsr", every=41), client=client, progress=False)
    reconstruct(held_out, explicit, ReconstructOptions(method="cscsr", every=41, weights=str(default_weights("lite"))),
                client=client, progress=False)
    assert zarr.open_group(implicit, mode="r").attrs["weights"].endswith("cscsr-lite.safetensors")
    assert chunk_files(implicit) == chunk_files(explicit)


def test_the_shipped_weights_beat_the_classic_methods(held_out, client, tmp_path):
    rows = {r["method"]: r for r in evaluate(held_out, ["tfp", "tfi", "cscsr"], str(tmp_path / "ev"), client=client,
                                             progress=False)}
    assert rows["cscsr"]["frames"] == 3
    assert rows["cscsr"]["psnr"] > max(rows["tfp"]["psnr"], rows["tfi"]["psnr"]) + MARGIN_DB
    assert rows["cscsr"]["ssim"] > max(rows["tfp"]["ssim"], rows["tfi"]["ssim"])



FULL_MARGIN_DB = 1.5  # measured: full +2.28 dB over TFI on this clip (23.01 vs 20.73, SSIM 0.751 vs 0.642)


def test_the_shipped_full_weights_carry_their_training_record():
    metadata = read_metadata(default_weights("full"))
    assert json.loads(metadata["config"])["name"] == "full" and metadata["storage"] == "float16"
    record = json.loads(metadata["training_record"])
    assert "H100" in record["hardware"] and sum(run["steps"] for run in record["runs"]) > 3000
    assert default_weights("full").stat().st_size < 13_000_000  # fp16: small enough to come back from a lease


def test_the_shipped_full_weights_beat_lite_and_the_classic_methods(held_out, client, tmp_path):
    full = str(default_weights("full"))
    rows = {r["method"]: r for r in evaluate(held_out, ["tfi", "cscsr"], str(tmp_path / "lite"), client=client,
                                             progress=False)}
    rows["full"] = evaluate(held_out, ["cscsr"], str(tmp_path / "full"), client=client, weights=full,
                            progress=False)[0]
    assert rows["full"]["psnr"] > rows["tfi"]["psnr"] + FULL_MARGIN_DB
    assert rows["full"]["psnr"] > rows["cscsr"]["psnr"] and rows["full"]["ssim"] > rows["cscsr"]["ssim"]


def test_the_shipped_weights_are_named_by_their_configuration(held_out, client, tmp_path):
    by_name, by_path = str(tmp_path / "name.zarr"), str(tmp_path / "path.zarr")
    reconstruct(held_out, by_name, ReconstructOptions(method="cscsr", every=41, weights="full"), client=client,
                progress=False)
    reconstruct(held_out, by_path, ReconstructOptions(method="cscsr", every=41, weights=str(default_weights("full"))),
                client=client, progress=False)
    assert zarr.open_group(by_name, mode="r").attrs["weights"] == str(default_weights("full"))
    assert chunk_files(by_name) == chunk_files(by_path)


def test_every_shipped_file_records_the_output_its_network_makes():
    """A mono network's output is grey (three equal channels), not per colour: its file said "per colour (RGB)"."""
    from cscsr.weights.weights_io import SHIPPED, conventions, load_model, read_metadata

    for name in ("lite", "full", "lite-mono"):
        path = SHIPPED / f"cscsr-{name}.safetensors"
        assert read_metadata(path)["output"] == conventions(load_model(path)[0].config)["output"]
    assert "grey" in read_metadata(SHIPPED / "cscsr-lite-mono.safetensors")["output"]


def test_every_shipped_file_counts_its_steps_one_way():
    """``steps`` is every optimiser step the weights have had, ``run_steps`` the last run's, and a file made from
    another (``initialised_from``) has that file's steps and its own (they were cumulative in one file, the last
    run's in another, "529 + 2593" in the third)."""
    import re

    from cscsr.weights.weights_io import SHIPPED, read_metadata

    for name in ("lite", "full", "lite-mono"):
        metadata = read_metadata(SHIPPED / f"cscsr-{name}.safetensors")
        steps, run_steps = int(metadata["steps"]), int(metadata["run_steps"])
        parent = re.search(r"\((\d+) steps\)$", metadata.get("initialised_from", ""))
        assert steps >= run_steps > 0 and (parent is None or steps == int(parent.group(1)) + run_steps), name
