"""Ingest -> export byte identity on real .dat bytes, and .npz/.npy ingest."""

import numpy as np
import pytest
import zarr

from pipeline.jobs.export import export_dat
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.stores.spike_store import open_spike_store
from stages.capture.bits import unpack_rows
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


def sps10_capture(frames: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(spikes (T, H, 400), stored rows (T, H, 416)): an SPS10-shaped capture whose 16 trailing header
    columns hold each row's line number in binary (LSB first), the layout SpikeCV and Spike-Zoo read."""
    bits = integrate_and_fire(smooth_rate(height, 400), frames)
    line = (np.arange(height)[:, None] >> np.arange(16)) & 1  # (H, 16)
    header = np.broadcast_to(line, (frames, height, 16)).astype(np.uint8)
    return bits, np.concatenate([bits, header], axis=-1)


@pytest.mark.parametrize("flip", [False, True])
def test_trailing_head_columns_are_dropped_as_spikecv_does(cli, tmp_path, flip):
    bits, stored = sps10_capture(30, 8)
    write_dat(tmp_path / "in.dat", stored, flip=flip)
    result = cli("ingest", tmp_path / "in.dat", tmp_path / "s.zarr", "--height", 8, "--width", 400, "--head-columns", 16,
                 *(["--flip"] if flip else []))
    assert result.exit_code == 0, result.stderr
    picture = unpack_rows(open_spike_store(str(tmp_path / "s.zarr")).read(0, 30), 400)
    # SpikeCV's load_dat: np.delete(frames, np.arange(400, 416), 2); Spike-Zoo: spikes[:, :, :-16]
    np.testing.assert_array_equal(picture, np.delete(stored, np.arange(400, 416), 2))
    assert open_spike_store(str(tmp_path / "s.zarr")).meta.head_at == "end"
    # export: the same bytes with the header columns zeroed (the store keeps the picture only)
    assert cli("export", tmp_path / "s.zarr", tmp_path / "out.dat").exit_code == 0
    zeroed = np.concatenate([bits, np.zeros_like(stored[..., 400:])], axis=-1)
    assert (tmp_path / "out.dat").read_bytes() == write_dat(tmp_path / "zeroed.dat", zeroed, flip=flip)


def test_stores_written_with_leading_head_columns_still_export_their_layout(tmp_path):
    """A store from before the header side was recorded (head_columns, no head_at) had them at the start."""
    bits = integrate_and_fire(smooth_rate(8, 400), 20)
    leading = np.concatenate([np.zeros((20, 8, 16), np.uint8), bits], axis=-1)
    original = write_dat(tmp_path / "in.dat", leading)
    write_dat(tmp_path / "picture.dat", bits)
    ingest(str(tmp_path / "picture.dat"), str(tmp_path / "s.zarr"), IngestOptions(height=8, width=400), progress=False)
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="r+")
    group.attrs.update(head_columns=16)  # as the old ingest of in.dat recorded it
    group.attrs.pop("head_at")
    export_dat(str(tmp_path / "s.zarr"), str(tmp_path / "out.dat"), progress=False)
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


@pytest.mark.parametrize("height,width,note", [(100, 60, ""), (101, 61, "its last row and last column repeated"),
                                               (100, 61, "its last column repeated")])
def test_mp4_export_keeps_the_frame_size_and_says_when_it_pads(cli, tmp_path, height, width, note):
    """Sides that are not multiples of 16 are not stretched (imageio's default, with its own warning); an odd side,
    which H.264's yuv420p cannot hold, grows by one repeated row or column, said in one line of our own."""
    import imageio.v3 as iio

    from pipeline.stores.video_store import COMMITTED, VIDEO, create_video_store

    frames = np.stack([np.broadcast_to(np.linspace(0, 255, width, dtype=np.uint8)[None, :, None], (height, width, 3))
                       for _ in range(2)])
    store = str(tmp_path / "video.zarr")
    group = create_video_store(store, centres=[20, 61], hr_size=(height, width), tile_hr=(height, width), tiles=(1, 1),
                               attrs={"method": "tfp"})
    group[VIDEO][:] = frames
    group[COMMITTED][:] = 1
    group.attrs["state"] = "complete"
    result = cli("export", store, tmp_path / "video.mp4")
    assert result.exit_code == 0 and result.stdout == f"wrote {tmp_path / 'video.mp4'}\n"
    assert "IMAGEIO" not in result.stderr and "macro_block_size" not in result.stderr
    padded = (height + height % 2, width + width % 2)
    if note:
        assert len(result.stderr.splitlines()) == 1  # one line, no progress bar's empty one
        assert "WARNING cscsr.export" in result.stderr
        assert f"frames are {width}x{height}" in result.stderr and f"the video is {padded[1]}x{padded[0]}" in result.stderr
        assert note in result.stderr
    else:
        assert result.stderr == ""  # no progress bar where stderr is piped, nor its empty line
    decoded = iio.imread(tmp_path / "video.mp4")
    assert decoded.shape == (2, *padded, 3)
    assert np.abs(decoded[:, :height, :width].astype(float) - frames).mean() < 4  # in place: not resampled


def test_an_mp4_of_frames_only_h264_level_6_holds_is_said_to_be_so():
    """A whole 1000x1000 sensor at x4 is 4000x4000 HR: H.264 level 6 (203 Mb/s, a user's sweep measured), which many
    hardware players and browsers do not decode; the export says so, and what to do. 4096x2304 (level 5.2) is not
    said, 2304x4096 neither (the same macroblocks), one macroblock row more is."""
    from pipeline.jobs.export import beyond_common_players

    assert beyond_common_players(4000, 4000).startswith("frames of 4000x4000 make an H.264 level 6 video")
    assert beyond_common_players(2304, 4096) is None and beyond_common_players(4096, 2304) is None
    assert beyond_common_players(2320, 4096) is not None and beyond_common_players(1000, 1000) is None
