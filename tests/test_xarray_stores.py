"""Every kind of store opens with ``xarray.open_zarr``: dimension names that mean one thing per store,
frame indices as coordinates, consolidated metadata, and the attributes a viewer needs."""

import json
import os

import imageio.v3 as iio
import numpy as np
import pytest
import xarray as xr
import zarr

import cscsr
from pipeline.jobs.info import summarize_video
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from pipeline.jobs.simulate import SimulateOptions, simulate
from pipeline.stores.spike_store import open_spike_store
from pipeline.stores.video_store import open_video_store
from tests.test_simulate import picture


def opened(url: str) -> xr.Dataset:
    """The store as xarray sees it, from its consolidated metadata only (an error if there is none)."""
    return xr.open_zarr(url, consolidated=True)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> str:
    """82 frames of a moving 16x16 picture at scale 2 (LR 8x8), truth at frames 20, 40, 60."""
    folder = tmp_path_factory.mktemp("sim")
    iio.imwrite(folder / "astronaut.png", picture("astronaut", 16))
    store = str(folder / "sim.zarr")
    simulate(str(folder / "astronaut.png"), store, SimulateOptions(scale=2, frames=82, motion="random", truth_every=20,
                                                                   reset="subtract"), workers=1, progress=False)
    return store


def test_an_ingested_store_opens_with_xarray(tmp_path, monkeypatch):
    bits = (np.random.default_rng(3).random((20, 8, 12)) < 0.3).astype(np.uint8)
    np.save(tmp_path / "capture.npy", bits)
    monkeypatch.chdir(tmp_path)  # a relative source: the store records where it really is
    ingest("capture.npy", "spikes.zarr", IngestOptions(fps=1000.0), progress=False)
    ds = opened(str(tmp_path / "spikes.zarr"))
    assert ds["spikes"].dims == ("t", "y", "xbyte") and dict(ds.sizes) == {"t": 20, "y": 8, "xbyte": 2, "task": 1}
    assert ds["committed"].values.tolist() == [int(bits.sum())]  # ingest's record of its tasks (one here)
    assert ds["spikes"].dtype == np.uint8
    np.testing.assert_array_equal(ds["spikes"].values, np.packbits(bits, axis=-1, bitorder="little"))
    assert ds["spikes"].attrs["units"] == "bit-packed spikes, 1 = fired"
    assert ds["spikes"].attrs["fps"] == 1000.0 and ds["spikes"].attrs["width"] == 12
    assert ds.attrs["source"] == str(tmp_path / "capture.npy")
    assert ds.attrs["state"] == "complete" and ds.attrs["spike_count"] == int(bits.sum())
    assert ds.attrs["format_version"] == 1 and ds.attrs["cscsr_version"] == cscsr.__version__


def test_a_simulated_store_opens_with_xarray(simulated):
    ds = opened(simulated)
    assert dict(ds.sizes) == {"t": 82, "y": 8, "xbyte": 1, "k": 3, "hr_y": 16, "hr_x": 16, "c": 3, "k_flow": 2, "d": 2,
                              "task": 1}
    assert ds["spikes"].dims == ("t", "y", "xbyte") and ds["committed"].dims == ("task",)
    assert ds["committed"].values.tolist() == [ds.attrs["spike_count"]]  # its one task, committed
    assert ds["truth"].dims == ("k", "hr_y", "hr_x", "c") and ds["flow"].dims == ("k_flow", "hr_y", "hr_x", "d")
    assert list(ds.coords) == ["truth_frames"] and ds["truth_frames"].dims == ("k",)
    assert ds["truth_frames"].values.tolist() == [20, 40, 60]
    group = zarr.open_group(simulated, mode="r")
    np.testing.assert_array_equal(ds["truth"].values, group["truth"][:])
    np.testing.assert_array_equal(ds["flow"].values, group["flow"][:])
    assert ds["truth"].dtype == np.uint8 and ds["flow"].dtype == np.float32
    assert ds.attrs["simulated"] is True and ds.attrs["scale"] == 2 and ds.attrs["state"] == "complete"
    assert os.path.isabs(ds.attrs["source"]) and ds.attrs["source"].endswith("astronaut.png")


def test_a_video_store_opens_with_xarray(simulated, client, tmp_path):
    out = str(tmp_path / "video.zarr")
    reconstruct(simulated, out, ReconstructOptions(method="tfp", every=20), client=client, progress=False)
    ds = opened(out)
    assert dict(ds.sizes) == {"j": 3, "hr_y": 16, "hr_x": 16, "c": 3, "tile_y": 1, "tile_x": 1}
    assert ds["video"].dims == ("j", "hr_y", "hr_x", "c") and ds["video"].dtype == np.uint8
    assert list(ds.coords) == ["frames"] and ds["frames"].values.tolist() == [20, 40, 60]
    np.testing.assert_array_equal(ds["video"].values, zarr.open_group(out, mode="r")["video"][:])
    assert ds["committed"].values.tolist() == [[[1]], [[1]], [[1]]]
    video = ds["video"].attrs
    assert video["units"] == "8-bit sRGB" and video["window"] == 41 and video["every"] == 20
    assert video["fps"] == ds.attrs["fps"] == 20000.0 / 20
    assert ds.attrs["format_version"] == 1 and ds.attrs["cscsr_version"] == cscsr.__version__
    assert ds.attrs["source"] == simulated and ds.attrs["state"] == "complete"
    assert summarize_video(out, open_video_store(out))["fps"] == 1000.0  # info reads it from the store itself

    # a resumed run on the finished store keeps it whole: consolidated, complete, nothing redone
    counts = reconstruct(simulated, out, ReconstructOptions(method="tfp", every=20, resume=True), client=client,
                         progress=False)
    assert counts == {"frames": 3, "tasks_run": 0, "tasks_skipped": 3}
    again = opened(out)
    assert again.attrs["state"] == "complete" and again["frames"].values.tolist() == [20, 40, 60]


def test_a_store_moved_elsewhere_still_names_its_source(simulated, client, tmp_path, monkeypatch):
    """A store made from a relative path records the absolute one; an old store that recorded the
    relative path still resumes from the same place."""
    monkeypatch.chdir(os.path.dirname(simulated))
    out = str(tmp_path / "video.zarr")
    reconstruct("sim.zarr", out, ReconstructOptions(method="tfp", every=20), client=client, progress=False)
    assert open_video_store(out).attrs["source"] == simulated
    open_video_store(out, writable=True).attrs["source"] = "sim.zarr"  # as stores before this change recorded it
    counts = reconstruct("sim.zarr", out, ReconstructOptions(method="tfp", every=20, resume=True), client=client,
                         progress=False)
    assert counts["tasks_skipped"] == 3 and opened(out).attrs["source"] == "sim.zarr"


def test_old_stores_without_dimension_names_or_consolidation_still_read(simulated, tmp_path):
    """Our readers never look at dimension names: a store written before them reads the same."""
    import shutil

    old = tmp_path / "old.zarr"
    shutil.copytree(simulated, old)
    root = json.loads((old / "zarr.json").read_text())
    root.pop("consolidated_metadata")
    (old / "zarr.json").write_text(json.dumps(root))
    for name, dims in (("spikes", ["t", "y", "xbyte"]), ("truth", ["k", "y", "x", "c"]), ("flow", ["k", "y", "x", "d"])):
        meta = json.loads((old / name / "zarr.json").read_text())
        meta["dimension_names"], meta["attributes"] = dims, {}
        (old / name / "zarr.json").write_text(json.dumps(meta))
    store, new = open_spike_store(str(old)), open_spike_store(simulated)
    assert store.n_frames == 82 and store.meta == new.meta
    np.testing.assert_array_equal(store.read(0, 82), new.read(0, 82))
    with pytest.raises(ValueError):  # what this change fixes: xarray refused such a store
        xr.open_zarr(str(old), consolidated=False)
