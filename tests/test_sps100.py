"""The megapixel camera's raw captures (#37): ``cscsr ingest SRC STORE --layout sps100``.

Captures are made here from known spike arrays by the layout of ``stages.capture.sps100`` (itself built from SpikeCV's
public reader, not from a real capture): 64-byte half-lines of 500 pixel bits (LSB first) and a 12-bit tag
(line, channel), 2000 a frame, row ``k // 2`` and columns ``500 * (k % 2)``.. from half-line ``k``. Round trips in
one process and in parallel, a capture begun mid-frame (mid-packet, even), and damage (a dropped packet, a
corrupted tag) refused in one line naming the byte offset, with nothing left behind, in the last frame too (#48),
whose packets are checked as any frame's; a capture cut short in its last frame said in one warning line."""

import os

import numpy as np
import pytest

from pipeline.stores import spike_store
from pipeline.jobs.ingest import IngestOptions, ingest, plan_ingest
from pipeline.stores.spike_store import open_spike_store
from stages.capture import sps100
from stages.capture.bits import unpack_rows
from stages.errors import InputError
from tests.test_bad_input import assert_refused
from tests.test_parallel_ingest import store_files

FB = sps100.FRAME_BYTES  # 128,000 bytes a frame

# Frame tag sequences (line, channel), each every pair once, from line 500 channel 0 to line 500 channel 3: one in
# order, one shuffled (the reader learns the sequence from the first whole frame, it assumes no order).
IN_ORDER = [(500, 0)] + [(line, 0) for line in range(1, 500)] + [(line, c) for c in (1, 2, 3) for line in range(1, 501)]
_middle = [pair for pair in IN_ORDER if pair not in ((500, 0), (500, 3))]
SHUFFLED = [(500, 0)] + [_middle[i] for i in np.random.default_rng(9).permutation(len(_middle))] + [(500, 3)]


def halves(bits: np.ndarray, sequence=IN_ORDER) -> np.ndarray:
    """(T, 1000, 1000) 0/1 -> (T, 2000, 64) bytes of half-lines: row r's columns 0..499 in half-line 2r, 500..999
    in 2r + 1, each 500 pixel bits then its 12-bit tag (line | channel << 10) in bits 500..511, LSB first."""
    frames = bits.shape[0]
    full = np.zeros((frames, sps100.HALVES, 512), np.uint8)
    full[:, :, :500] = bits.reshape(frames, sps100.HALVES, 500)
    tags = np.array([line | channel << 10 for line, channel in sequence])
    full[:, :, 500:] = (tags[:, None] >> np.arange(12)) & 1
    return np.packbits(full, axis=-1, bitorder="little")


def write_capture(path, bits: np.ndarray, *, sequence=IN_ORDER, lead: int = 0, tail: int = 0, flip: bool = False
                  ) -> bytes:
    """A capture of ``bits`` (frames upside down with ``flip``, as a real camera's), begun ``lead`` bytes before
    the end of a frame (the last bytes of one more frame) and ended ``tail`` bytes into another; -> its bytes."""
    frames = halves(bits[:, ::-1] if flip else bits, sequence)
    extra = halves(np.ones((2, 1000, 1000), np.uint8), sequence).reshape(2, FB)
    data = extra[0, FB - lead:].tobytes() + frames.tobytes() + extra[1, :tail].tobytes()
    with open(path, "wb") as handle:
        handle.write(data)
    return data


def spikes(frames: int, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((frames, 1000, 1000)) < 0.2).astype(np.uint8)


def stored(store) -> np.ndarray:
    return unpack_rows(open_spike_store(str(store)).spikes[:], 1000)


@pytest.fixture
def small_chunks(monkeypatch):
    """Chunks of 2 frames (125,000 packed bytes each), so a few frames make several tasks."""
    monkeypatch.setattr(spike_store, "TARGET_CHUNK_BYTES", 2 * 1000 * 125)


def test_one_process_and_parallel_round_trips(cli, tmp_path, small_chunks):
    """A capture begun mid-frame and ended mid-frame: its 6 whole frames, in one process and on ``--workers 2``,
    the same bytes, file for file; the options recorded for --resume name the layout."""
    bits = spikes(6)
    write_capture(tmp_path / "c.raw", bits, lead=3 * 64 + 16, tail=5000)
    args = ("--layout", "sps100", "--cfa", "rggb", "--task-frames", "2")
    one = cli("-q", "ingest", tmp_path / "c.raw", tmp_path / "one.zarr", *args)
    assert one.exit_code == 0, one.stderr
    assert "1000x1000" in one.stdout
    two = cli("-q", "ingest", tmp_path / "c.raw", tmp_path / "two.zarr", *args, "--workers", "2")
    assert two.exit_code == 0, two.stderr
    assert "(3 tasks run, 0 already committed)" in two.stdout
    assert np.array_equal(stored(tmp_path / "one.zarr"), bits)
    assert store_files(tmp_path / "one.zarr") == store_files(tmp_path / "two.zarr")
    store = open_spike_store(str(tmp_path / "one.zarr"))
    assert store.attrs["spike_count"] == int(bits.sum()) and store.attrs["cfa"] == "rggb"
    assert store.group["committed"].attrs["options"]["layout"] == "sps100"
    resumed = cli("-q", "ingest", tmp_path / "c.raw", tmp_path / "one.zarr", "--cfa", "rggb", "--task-frames", "2",
                  "--resume")  # by extension (.raw: none), not as it was ingested
    assert_refused(resumed, "unknown capture type .raw")


@pytest.mark.parametrize("lead", [0, 1, 7, 64 * 1999 + 5, FB - 1])
def test_a_capture_begun_anywhere_is_read_from_its_first_whole_frame(tmp_path, lead):
    """Mid-packet, mid-half-line, just after a frame start: the first whole frame is found; flipped frames and a
    shuffled (line, channel) sequence as well."""
    bits = spikes(3, seed=lead)
    write_capture(tmp_path / "c.dat", bits, sequence=SHUFFLED, lead=lead, tail=64 * 3 + 9, flip=True)
    ingest(str(tmp_path / "c.dat"), str(tmp_path / "s.zarr"), IngestOptions(flip=True, layout="sps100"), progress=False)
    assert np.array_equal(stored(tmp_path / "s.zarr"), bits)


def test_the_layout_geometry_by_hand():
    """One pixel at a time, against the description: row 1 column 3 is bit 3 of half-line 2; row 0 column 500
    is bit 0 of half-line 1 (byte 0, bit 0); row 999 column 999 bit 499 of half-line 1999 (byte 62, bit 3)."""
    for (row, column), (half, byte, bit) in {(1, 3): (2, 0, 3), (0, 500): (1, 0, 0), (999, 999): (1999, 62, 3),
                                             (0, 499): (0, 62, 3), (5, 504): (11, 0, 4)}.items():
        raw = np.zeros((1, sps100.HALVES, 64), np.uint8)
        raw[0, half, byte] = 1 << bit
        packed = sps100.halves_to_packed(raw)
        assert packed.shape == (1, 1000, 125)
        assert np.argwhere(unpack_rows(packed, 1000)[0]).tolist() == [[row, column]]


def _refused_leaving_nothing(cli, tmp_path, src, *fragments):
    result = cli("ingest", src, tmp_path / "s.zarr", "--layout", "sps100")
    assert_refused(result, *fragments)
    assert not (tmp_path / "s.zarr").exists()


def test_a_dropped_packet_is_refused_naming_its_offset(cli, client, tmp_path, small_chunks):
    """A packet missing mid-way (frame 2, half-line 300): refused where its half-line's tag should be, in one
    process, in parallel (the first task that finds it) and by a dry run (which reads the middle task, this one),
    leaving no store."""
    lead = 100
    data = write_capture(tmp_path / "ok.dat", spikes(6, seed=3), lead=lead)
    half_line = lead + 2 * FB + 300 * 64
    damaged = tmp_path / "c.dat"
    damaged.write_bytes(data[:half_line + 16] + data[half_line + 32:])  # its second packet dropped
    _refused_leaving_nothing(cli, tmp_path, damaged, f"at byte {half_line + 48}:", "half-line 300 of frame 2",
                             "dropped or corrupted")
    options = IngestOptions(layout="sps100", task_frames=2)  # 3 tasks: 5 whole frames after the drop
    with pytest.raises(InputError, match=f"at byte {half_line + 48}: half-line 300 of frame 2"):
        ingest(str(damaged), str(tmp_path / "p.zarr"), options, progress=False, client=client)
    assert not (tmp_path / "p.zarr").exists()
    with pytest.raises(InputError, match=f"at byte {half_line + 48}: half-line 300 of frame 2"):
        plan_ingest(str(damaged), str(tmp_path / "d.zarr"), options)
    assert not (tmp_path / "d.zarr").exists()


@pytest.mark.parametrize("frame,half_line,bit", [(3, 77, 500), (0, 1000, 511), (0, 1999, 505), (5, 0, 509)])
def test_a_corrupted_tag_is_refused_naming_its_offset(cli, tmp_path, frame, half_line, bit):
    """One tag bit flipped, in a later frame or in the first whole frame (never skipped to the next one): refused
    naming the byte offset of the packet that carries it; nothing left."""
    lead = 64 * 7 + 3
    data = bytearray(write_capture(tmp_path / "ok.dat", spikes(6, seed=4), lead=lead))
    start = lead + frame * FB + half_line * 64
    data[start + bit // 8] ^= 1 << (bit % 8)
    (tmp_path / "c.dat").write_bytes(bytes(data))
    _refused_leaving_nothing(cli, tmp_path, tmp_path / "c.dat", f"at byte {start + 48}:", f"half-line {half_line}")


@pytest.mark.parametrize("half_line,packet", [(700, 1), (0, 0), (1998, 3)])
def test_a_packet_dropped_in_the_last_frame_is_refused_naming_its_offset(cli, client, tmp_path, small_chunks,
                                                                           half_line, packet):
    """A packet missing from the last frame leaves it a partial frame at the capture's end, whose packets are
    checked as any frame's (#48): refused where the half-line that holds the drop has its tag, not read as 3
    whole frames and a frame cut short, in one process (after its first task is written) and in parallel (the
    last task), leaving no store."""
    lead = 100
    data = write_capture(tmp_path / "ok.dat", spikes(4, seed=5), lead=lead)
    start = lead + 3 * FB + half_line * 64
    damaged = tmp_path / "c.dat"
    damaged.write_bytes(data[:start + 16 * packet] + data[start + 16 * (packet + 1):])
    refused = cli("ingest", damaged, tmp_path / "s.zarr", "--layout", "sps100", "--task-frames", "2")
    assert_refused(refused, f"at byte {start + 48}: half-line {half_line} of frame 3", "dropped or corrupted")
    assert not (tmp_path / "s.zarr").exists()
    options = IngestOptions(layout="sps100", task_frames=2)  # 2 tasks: frames 0-1, and 2 with the partial frame
    with pytest.raises(InputError, match=f"at byte {start + 48}: half-line {half_line} of frame 3"):
        ingest(str(damaged), str(tmp_path / "p.zarr"), options, progress=False, client=client)
    assert not (tmp_path / "p.zarr").exists()


@pytest.mark.parametrize("lead,tail", [(64 * 5, 64 * 700 + 32), (0, 48), (64 * 5, 0), (0, 0)])
def test_partial_frames_at_either_end_are_not_read_and_said_in_one_line_each(cli, client, tmp_path, small_chunks,
                                                                             caplog, lead, tail):
    """Begun inside a frame, or cut at a packet boundary in its last (its packets in sequence): its whole frames,
    and one warning line for each end naming the bytes not read (the leading ones were skipped without a word),
    in one process and in parallel; none when it begins and ends with a whole frame."""
    bits = spikes(3, seed=6)
    write_capture(tmp_path / "c.dat", bits, lead=lead, tail=tail)
    lines = ([f"{tmp_path / 'c.dat'}: its first {lead:,} bytes, before frame 0, are a frame the capture began "
              f"inside of: not read"] if lead else []) + \
        ([f"{tmp_path / 'c.dat'}: its last {tail:,} bytes, after frame 2, are a frame cut short (its packets in "
          f"sequence): not read"] if tail else [])
    one = cli("-q", "ingest", tmp_path / "c.dat", tmp_path / "one.zarr", "--layout", "sps100", "--task-frames", "2")
    assert one.exit_code == 0 and one.stdout.startswith(f"{tmp_path / 'one.zarr'}: "), one.stderr
    assert np.array_equal(stored(tmp_path / "one.zarr"), bits)
    said = one.stderr.strip().splitlines()
    assert len(said) == len(lines) and all("WARNING cscsr.ingest" in line for line in said), one.stderr
    assert all(line.endswith(text) for line, text in zip(said, lines)), one.stderr
    caplog.clear()  # (the command's line, which it also logged)
    with caplog.at_level("WARNING", logger="cscsr.ingest"):
        ingest(str(tmp_path / "c.dat"), str(tmp_path / "two.zarr"), IngestOptions(layout="sps100", task_frames=2),
               progress=False, client=client)
    assert store_files(tmp_path / "one.zarr") == store_files(tmp_path / "two.zarr")
    assert [record.getMessage() for record in caplog.records if record.name == "cscsr.ingest"] == lines


def test_options_and_captures_that_do_not_fit_the_layout_are_refused(cli, tmp_path):
    """Each in one line, before anything is created."""
    write_capture(tmp_path / "c.dat", spikes(1))
    np.save(tmp_path / "a.npy", np.zeros((2, 4, 8), np.uint8))
    (tmp_path / "zeros.dat").write_bytes(bytes(3 * FB))
    (tmp_path / "short.dat").write_bytes((tmp_path / "c.dat").read_bytes()[:FB - 64])
    for args, fragments in [
        (("--height", "500"), ("--height 500 is inconsistent with the sps100 layout's fixed 1000x1000",)),
        (("--width", "1000", "--height", "1000", "--head-columns", "16"), ("--head-columns applies to the .dat",)),
        (("--key", "spk"), ("--key",)),
    ]:
        assert_refused(cli("ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--layout", "sps100", *args), *fragments)
    assert_refused(cli("ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--layout", "sps1000"),
                   "unknown raw layout 'sps1000': expected one of dat, sps100")
    assert_refused(cli("ingest", tmp_path / "a.npy", tmp_path / "s.zarr", "--layout", "sps100"), "is a .npy array")
    assert_refused(cli("ingest", tmp_path / "zeros.dat", tmp_path / "s.zarr", "--layout", "sps100"),
                   "not an sps100 capture")
    assert_refused(cli("ingest", tmp_path / "short.dat", tmp_path / "s.zarr", "--layout", "sps100"),
                   "no whole sps100 frame")
    assert not (tmp_path / "s.zarr").exists()
    # --height/--width of the layout's own size are accepted; --layout dat reads frames of any file's name
    assert cli("-q", "ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--layout", "sps100", "--height", "1000",
               "--width", "1000").exit_code == 0
    os.rename(tmp_path / "c.dat", tmp_path / "c.bin")
    as_dat = cli("-q", "ingest", tmp_path / "c.bin", tmp_path / "d.zarr", "--layout", "dat", "--height", "1000",
                 "--width", "1024")
    assert as_dat.exit_code == 0, as_dat.stderr


def test_a_store_of_the_layout_resumes_only_as_it(cli, tmp_path):
    """``--resume`` compares the layout recorded: the same capture read as ``.dat`` frames is other options."""
    write_capture(tmp_path / "c.dat", spikes(2))
    assert cli("-q", "ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--layout", "sps100").exit_code == 0
    again = cli("-q", "ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--layout", "sps100", "--resume")
    assert again.exit_code == 0, again.stderr
    other = cli("ingest", tmp_path / "c.dat", tmp_path / "s.zarr", "--height", "1000", "--width", "1024", "--resume")
    assert_refused(other, "other options", "layout 'sps100' -> 'dat'")
