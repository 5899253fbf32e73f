"""Streaming: bounded memory whatever the capture size, and no output left by a failed ingest."""

import tracemalloc

import numpy as np
import pytest

from pipeline.jobs import ingest as ingest_module
from pipeline.stores import spike_store, spike_writes
from pipeline.stores.captures import open_capture
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.stores.spike_store import open_spike_store
from stages.capture.bits import unpack_rows
from tests.conftest import write_dat


def _ingest_peak_bytes(tmp_path, frames: int) -> int:
    """Peak traced allocation while ingesting a 1000x1000 capture of ``frames`` frames."""
    frame = np.zeros((1000, 1000), np.uint8)
    frame[::7, ::3] = 1
    packed = np.packbits(frame.reshape(-1), bitorder="little").tobytes()
    with open(tmp_path / f"{frames}.dat", "wb") as capture:
        for _ in range(frames):
            capture.write(packed)
    tracemalloc.start()
    ingest(str(tmp_path / f"{frames}.dat"), str(tmp_path / f"{frames}.zarr"), IngestOptions(1000, 1000), progress=False)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert open_spike_store(str(tmp_path / f"{frames}.zarr")).spike_count == frames * 143 * 334
    return peak


def test_ingest_memory_does_not_grow_with_the_capture(tmp_path, monkeypatch):
    """8x the frames, about the same peak: memory is set by the block size, not the capture's.

    A block here is one 4 MiB chunk; reader, queue and writer hold a few blocks at a time,
    how many depending on timing, so the bound allows two blocks of jitter.
    """
    monkeypatch.setattr(ingest_module, "BLOCK_BYTES", 2**20)  # rounds up to one chunk per block
    block = spike_store.chunk_frames_for(spike_store.SpikeMeta(1000, 1000), 10**6) * 125_000
    short, long = _ingest_peak_bytes(tmp_path, 132), _ingest_peak_bytes(tmp_path, 1056)  # 16.5 MB and 132 MB
    assert long < short + 2 * block, f"peak {short / 2**20:.1f} MiB -> {long / 2**20:.1f} MiB"
    assert long < 0.2 * 1056 * 125_000


def test_blocks_cover_the_capture_exactly(tmp_path):
    bits = (np.random.default_rng(3).random((100, 6, 24)) < 0.3).astype(np.uint8)
    write_dat(tmp_path / "c.dat", bits)
    capture = open_capture(str(tmp_path / "c.dat"), height=6, width=24)
    starts, parts = zip(*capture.blocks(frames_per_block=32))
    assert starts == (0, 32, 64, 96)
    np.testing.assert_array_equal(unpack_rows(np.concatenate(parts), 24), bits)


def test_interrupted_ingest_leaves_nothing(tmp_path, monkeypatch):
    bits = (np.random.default_rng(4).random((200, 8, 16)) < 0.3).astype(np.uint8)
    write_dat(tmp_path / "c.dat", bits)
    monkeypatch.setattr(spike_store, "TARGET_CHUNK_BYTES", 20 * 8 * 2)  # 20-frame chunks
    monkeypatch.setattr(ingest_module, "BLOCK_BYTES", 64)  # one chunk per block: 10 blocks
    calls = []

    def fail_on_third(packed):
        calls.append(packed.shape[0])
        if len(calls) == 3:
            assert (tmp_path / "s.zarr" / "spikes" / "c" / "1").exists()  # two blocks are on disk
            raise KeyboardInterrupt
        return 0

    monkeypatch.setattr(spike_writes, "count_spikes", fail_on_third)  # each task's count, once its frames are stored
    with pytest.raises(KeyboardInterrupt):
        ingest(str(tmp_path / "c.dat"), str(tmp_path / "s.zarr"), IngestOptions(8, 16), progress=False)
    assert calls == [20, 20, 20] and not (tmp_path / "s.zarr").exists()


def test_prefetched_keeps_order_and_passes_errors_on():
    from stages.prefetch import prefetched

    assert list(prefetched(iter(range(50)), depth=3)) == list(range(50))

    def failing():
        yield 1
        raise ValueError("bad block")

    seen = []
    with pytest.raises(ValueError, match="bad block"):
        for item in prefetched(failing()):
            seen.append(item)
    assert seen == [1]
