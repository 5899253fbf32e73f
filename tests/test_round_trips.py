"""Ingest -> export byte identity on real .dat bytes, and .npz/.npy ingest."""

import numpy as np
import pytest

from pipeline.ingest import IngestOptions, ingest
from pipeline.spike_store import open_spike_store
from stages.bits import unpack_rows
from tests.conftest import integrate_and_fire, smooth_rate, write_dat


@pytest.mark.parametrize("height,width,frames,flip", [(1000, 1000, 48, True), (60, 250, 50, False), (10, 13, 20, True)])
def test_export_is_byte_identical(cli, tmp_path, height, width, frames, flip):
    bits = integrate_and_fire(smooth_rate(height, width), frames, seed=height)
    original = write_dat(tmp_path / "in.dat", bits, flip=flip)
    args = ["--height", height, "--width", width] + (["--flip"] if flip else [])
    assert cli("ingest", tmp_path / "in.dat", tmp_path / "s.zarr", *args).exit_code == 0
    stored = open_spike_store(str(tmp_path / "s.zarr"))
    np.testing.assert_array_equal(unpack_rows(stored.read(0, frames), width), bits)  # upright in the store
    assert cli("export", tmp_path / "s.zarr", tmp_path / "out.dat").exit_code == 0
    assert (tmp_path / "out.dat").read_bytes() == original


def test_head_columns_are_dropped_and_restored_as_zeros(cli, tmp_path):
    bits = integrate_and_fire(smooth_rate(8, 416), 30)
    bits[:, :, :16] = 0
    original = write_dat(tmp_path / "in.dat", bits)
    result = cli("ingest", tmp_path / "in.dat", tmp_path / "s.zarr", "--height", 8, "--width", 400, "--head-columns", 16)
    assert result.exit_code == 0, result.stderr
    np.testing.assert_array_equal(unpack_rows(open_spike_store(str(tmp_path / "s.zarr")).read(0, 30), 400), bits[:, :, 16:])
    assert cli("export", tmp_path / "s.zarr", tmp_path / "out.dat").exit_code == 0
    assert (tmp_path / "out.dat").read_bytes() == original


@pytest.mark.parametrize("dtype", [np.uint8, np.bool_, np.int64])
def test_npy_and_npz_ingest(tmp_path, dtype):
    bits = integrate_and_fire(smooth_rate(12, 20), 45).astype(dtype)
    np.save(tmp_path / "a.npy", bits)
    np.savez_compressed(tmp_path / "b.npz", spk=bits, label=3)
    for name in ("a.npy", "b.npz"):
        ingest(str(tmp_path / name), str(tmp_path / f"{name}.zarr"), IngestOptions(cfa="rggb"), progress=False)
        store = open_spike_store(str(tmp_path / f"{name}.zarr"))
        assert store.meta.cfa == "rggb" and store.spike_count == int(bits.sum())
        np.testing.assert_array_equal(unpack_rows(store.read(0, 45), 20), bits.astype(np.uint8))


def test_flip_records_the_upright_cfa(tmp_path):
    bits = integrate_and_fire(smooth_rate(8, 16), 41)
    write_dat(tmp_path / "in.dat", bits)
    ingest(str(tmp_path / "in.dat"), str(tmp_path / "s.zarr"), IngestOptions(8, 16, cfa="rggb", flip=True), progress=False)
    meta = open_spike_store(str(tmp_path / "s.zarr")).meta
    assert (meta.cfa, meta.flipped) == ("gbrg", True)  # rows swap parity when turned over
