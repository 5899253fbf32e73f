"""``lazy.open_capture`` (#56): a raw capture as lazy spikes, the spikes ``cscsr ingest`` stores from it.

For a ``.dat`` (the bundled sample and a small one with header columns), a ``.npy`` and an sps100 capture (begun
mid-frame, ended in a frame cut short): ``to_spikes(open_capture(...))`` writes the store's bytes ``ingest`` writes
with the same options (every chunk, the commit record's counts, every attribute, the capture's fingerprint and
options that ``committed`` records for a resume), and TFP of its windows is TFP of the ingested
store's. Bad input refused in one line, in Python words, with no graph and nothing written."""

import json
import logging
import os
import re

import dask
import numpy as np
import pytest

from cscsr import lazy
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.stores import spike_store
from stages.capture.sps100 import CaptureDamaged
from stages.errors import InputError, InputTypeError
from tests.conftest import write_dat
from tests.test_docs import PAGES, documented_outputs
from tests.test_parallel_ingest import store_files
from tests.test_sps100 import FB, spikes as sps100_spikes, write_capture

SAMPLE = os.path.join(os.path.dirname(lazy.__file__), "..", "..", "cscsr", "samples",
                      "synthetic_reds_200_part1_250x400.dat")
def assert_same_store(written, ingested) -> None:
    """Every file alike, the record of the capture in ``committed`` included (what a resume compares)."""
    ours, theirs = store_files(written), store_files(ingested)
    assert sorted(ours) == sorted(theirs)
    for name in ours:
        if name.endswith("zarr.json"):
            assert json.loads(ours[name]) == json.loads(theirs[name]), name
        else:
            assert ours[name] == theirs[name], name
    assert {"capture", "options"} <= set(json.loads(ours["committed/zarr.json"])["attributes"])


def check_against_ingest(tmp_path, src, options: IngestOptions, **kwargs) -> None:
    """``to_spikes(open_capture(src, **kwargs))`` and ``ingest(src, options)``: the same store; the same spikes,
    coordinates and attributes as ``open_spikes`` of it; the same TFP."""
    ingest(str(src), str(tmp_path / "ingested.zarr"), options, progress=False)
    spikes = lazy.open_capture(src, **kwargs)
    stored = lazy.open_spikes(tmp_path / "ingested.zarr")
    assert spikes.dims == stored.dims and spikes.shape == stored.shape and spikes.dtype == stored.dtype
    assert spikes.data.chunks == stored.data.chunks  # the store's chunks: one byte-range read each
    assert all(np.array_equal(spikes[name].values, stored[name].values) for name in ("t", "frame", "y", "x"))
    only_store = {"store", "state", "spike_count", "identity"}
    assert spikes.attrs == {k: v for k, v in stored.attrs.items() if k not in only_store}
    assert np.array_equal(spikes.values, stored.values)
    done = lazy.to_spikes(spikes, tmp_path / "written.zarr", task_frames=options.task_frames)
    assert done["attrs"]["identity"] == stored.attrs["identity"]
    assert_same_store(tmp_path / "written.zarr", tmp_path / "ingested.zarr")
    length = min(41, spikes.sizes["t"] - 1 + spikes.sizes["t"] % 2)  # odd, at most the recording
    every = max(1, spikes.sizes["t"] // 3)
    if spikes.sizes["y"] <= 256:  # whole frames, the automatic gain
        ours, theirs = (lazy.tfp(lazy.windows(s, length=length, every=every)) for s in (spikes, stored))
    else:  # a crop of a megapixel capture (not from a store: its gain given)
        ours, theirs = (lazy.tfp(lazy.windows(s.isel(y=slice(0, 64), x=slice(0, 64)), length=length, every=every),
                                 gain=1.0) for s in (spikes, stored))
    assert ours.sizes["t"] >= 1 and np.array_equal(ours.values, theirs.values)


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(spike_store, "TARGET_CHUNK_BYTES", 160)  # 5 frames of 16x16 a chunk


def test_the_bundled_dat_is_what_ingest_stores(tmp_path):
    check_against_ingest(tmp_path, SAMPLE, IngestOptions(250, 400, flip=True, task_frames=100),
                         height=250, width=400, flip=True)


@pytest.mark.parametrize("width,head", [(20, 4), (40, 8)])
def test_a_small_dat_with_header_columns_is_what_ingest_stores(tmp_path, small_chunks, width, head):
    bits = (np.random.default_rng(width).random((63, 16, width + head)) < 0.2).astype(np.uint8)
    write_dat(tmp_path / "c.dat", bits, flip=True)
    spikes = lazy.open_capture(tmp_path / "c.dat", height=16, width=width, head_columns=head, flip=True, cfa="rggb")
    assert np.array_equal(spikes.values, bits[:, :, :width].astype(bool))
    check_against_ingest(tmp_path, tmp_path / "c.dat",
                         IngestOptions(16, width, cfa="rggb", flip=True, head_columns=head, task_frames=10),
                         height=16, width=width, head_columns=head, flip=True, cfa="rggb")


def test_a_npy_is_what_ingest_stores(tmp_path, small_chunks):
    bits = (np.random.default_rng(1).random((50, 16, 24)) < 0.2).astype(np.uint8)
    np.save(tmp_path / "a.npy", bits)
    check_against_ingest(tmp_path, tmp_path / "a.npy", IngestOptions(cfa="bggr", fps=1000, reset="zero", task_frames=12),
                         cfa="bggr", fps=1000, reset="zero")


def test_on_one_client_ingest_runs_the_tasks_of_to_spikes_of_open_capture_reading_packed_bytes(
        client, tmp_path, small_chunks):
    """``cscsr ingest`` is a front door to ``to_spikes(open_capture(...))``: on one client both run the same tasks
    (``to-spikes``, one per task of frames: each reads its frames by one byte range and writes them packed, so no
    unpacked bits are made or moved between workers, where ``open_capture``'s blocks of bits were), into the same
    store; a selection of the frames is written through the bits, as any lazy spikes are."""
    from dask.utils import key_split
    from distributed import get_task_stream

    bits = (np.random.default_rng(7).random((50, 16, 24)) < 0.2).astype(np.uint8)
    write_dat(tmp_path / "c.dat", bits)
    with dask.config.set(scheduler=client), get_task_stream(client) as job:
        ingest(str(tmp_path / "c.dat"), str(tmp_path / "ingested.zarr"), IngestOptions(16, 24, task_frames=10),
               progress=False, client=client)
    spikes = lazy.open_capture(tmp_path / "c.dat", height=16, width=24)
    with dask.config.set(scheduler=client), get_task_stream(client) as graph:
        done = lazy.to_spikes(spikes, tmp_path / "written.zarr", task_frames=10)
    ran = {name: sorted((key_split(r["key"]), r["key"][1]) for r in stream.data)
           for name, stream in (("job", job), ("graph", graph))}
    assert ran["job"] == ran["graph"] == [("to-spikes", index) for index in range(5)], ran  # chunks of 5, tasks of 10
    assert done["tasks_run"] == 5 and done["spikes"] == int(bits.sum())
    assert_same_store(tmp_path / "written.zarr", tmp_path / "ingested.zarr")
    with dask.config.set(scheduler=client), get_task_stream(client) as selected:
        lazy.to_spikes(spikes.isel(t=slice(0, 40)), tmp_path / "part.zarr", task_frames=10)
    names = {key_split(r["key"]) for r in selected.data}
    assert "to-spikes" in names and names - {"to-spikes", "finalize-hlgfinalizecompute"}, names  # the bits read
    assert np.array_equal(lazy.open_spikes(tmp_path / "part.zarr").values, bits[:40].astype(bool))


def cut_short_of_tasks(store, committed_tasks: int) -> None:
    """``store`` as a run stopped after its first ``committed_tasks`` tasks leaves it (their record kept)."""
    import zarr

    group = zarr.open_group(str(store), mode="r+", use_consolidated=False)
    group.attrs["state"] = "writing"
    group["committed"][committed_tasks:] = -1


def test_ingest_and_to_spikes_of_open_capture_each_finish_the_other_s_store_and_refuse_another_capture(
        tmp_path, small_chunks):
    """Both record the capture alike (its size, a SHA-256 of its ends, how it was read): ``cscsr ingest --resume``
    finishes a store ``to_spikes(open_capture(...))`` began and the converse, to the bytes of an uninterrupted
    ingest, and ``to_spikes(resume=True)`` refuses another capture, as ingest does (it took any spikes' word)."""
    import shutil

    bits = (np.random.default_rng(3).random((50, 16, 24)) < 0.2).astype(np.uint8)
    write_dat(tmp_path / "c.dat", bits)
    recorded = (tmp_path / "c.dat").read_bytes()
    replaced = bytearray(recorded)
    replaced[-1] ^= 1  # the same size, one bit of the last MiB: another recording landed under the same name
    reference, begun_lazily, begun_by_ingest = (tmp_path / f"{name}.zarr" for name in ("ref", "lazy", "ingest"))
    ingest(str(tmp_path / "c.dat"), str(reference), IngestOptions(16, 24, task_frames=10), progress=False)

    lazy.to_spikes(lazy.open_capture(tmp_path / "c.dat", height=16, width=24), begun_lazily, task_frames=10)
    cut_short_of_tasks(begun_lazily, 2)
    done = ingest(str(tmp_path / "c.dat"), str(begun_lazily), IngestOptions(16, 24, resume=True), progress=False)
    assert done["state"] == "complete"
    assert store_files(begun_lazily) == store_files(reference)

    shutil.copytree(reference, begun_by_ingest)
    cut_short_of_tasks(begun_by_ingest, 3)
    before = store_files(begun_by_ingest)
    opened_before = lazy.open_capture(tmp_path / "c.dat", height=16, width=24)
    (tmp_path / "c.dat").write_bytes(bytes(replaced))
    with pytest.raises(InputError, match=r"c\.dat is not the capture it was ingested from \(the same size, but "
                                         r"its first or last MiB differ\): .*overwrite=True"):
        lazy.to_spikes(lazy.open_capture(tmp_path / "c.dat", height=16, width=24), begun_by_ingest, resume=True)
    with pytest.raises(InputError, match=r"c\.dat changed since lazy.open_capture opened it \(the same size, but "
                                         r"its first or last MiB differ\): open it again"):
        lazy.to_spikes(opened_before, begun_by_ingest, resume=True)  # its record is of the bytes it was opened on
    with pytest.raises(InputError, match="changed since lazy.open_capture opened it"):
        lazy.to_spikes(opened_before, tmp_path / "new.zarr")
    assert store_files(begun_by_ingest) == before and not (tmp_path / "new.zarr").exists()  # nothing written
    (tmp_path / "c.dat").write_bytes(recorded)
    done = lazy.to_spikes(lazy.open_capture(tmp_path / "c.dat", height=16, width=24), begun_by_ingest, resume=True)
    assert (done["tasks_run"], done["tasks_skipped"]) == (2, 3)
    assert store_files(begun_by_ingest) == store_files(reference)


def test_a_resume_takes_the_store_s_chunks_and_checks_its_cut_in_the_callers_words(cli, tmp_path, small_chunks):
    """``to_spikes(resume=True, task_frames=8)`` of a store written in chunks of 4 (not the default 5) resumes: its
    cut is the store's (8 frames, two chunks), not 8 rounded to the default chunks; ``cscsr ingest --resume`` of it
    refuses the other cut in the command line's words (it has no ``--chunk-frames``)."""
    write_dat(tmp_path / "c.dat", (np.random.default_rng(5).random((100, 16, 16)) < 0.2).astype(np.uint8))
    whole, resumed = tmp_path / "whole.zarr", tmp_path / "resumed.zarr"
    for url in (whole, resumed):
        lazy.to_spikes(lazy.open_capture(tmp_path / "c.dat", height=16, width=16), url, chunk_frames=4, task_frames=8)
    cut_short_of_tasks(resumed, 1)
    result = cli("ingest", tmp_path / "c.dat", resumed, "--height", 16, "--width", 16, "--resume")
    assert result.exit_code == 1 and "its arrays do not match the capture (100 frames in chunks of 4, 13 tasks): " \
        "start again with --overwrite" in result.stderr and "chunk_frames" not in result.stderr, result.stderr
    done = lazy.to_spikes(lazy.open_capture(tmp_path / "c.dat", height=16, width=16), resumed, task_frames=8,
                          resume=True)
    assert (done["tasks_run"], done["tasks_skipped"]) == (12, 1)
    assert store_files(resumed) == store_files(whole)


def test_an_sps100_capture_cut_short_is_what_ingest_stores(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(spike_store, "TARGET_CHUNK_BYTES", 2 * 1000 * 125)  # 2 frames a chunk
    tail = 64 * 700 + 32
    write_capture(tmp_path / "c.dat", sps100_spikes(3, seed=6), lead=64 * 5, tail=tail)
    with caplog.at_level(logging.WARNING, logger="cscsr.lazy"):
        spikes = lazy.open_capture(tmp_path / "c.dat", layout="sps100", cfa="rggb")
    assert [r.getMessage() for r in caplog.records if r.name == "cscsr.lazy"] == [
        f"{tmp_path / 'c.dat'}: its first 320 bytes, before frame 0, are a frame the capture began inside of: not "
        f"read", f"{tmp_path / 'c.dat'}: its last {tail:,} bytes, after frame 2, are a frame cut short (its packets "
        f"in sequence): not read"]
    assert spikes.shape == (3, 1000, 1000)
    check_against_ingest(tmp_path, tmp_path / "c.dat", IngestOptions(cfa="rggb", layout="sps100", task_frames=2),
                         layout="sps100", cfa="rggb")


def test_damage_in_the_frames_is_refused_naming_its_offset_when_read(client, tmp_path):
    """A corrupted tag mid-capture: the graph is built (nothing read), and computing the block that holds it
    says where, in ingest's words; a packet dropped (the capture then ends in a partial frame, checked up front
    with the last whole frame) or dropped from the frame cut short at the end is refused by open_capture."""
    lead = 100
    data = write_capture(tmp_path / "ok.dat", sps100_spikes(4, seed=3), lead=lead)
    half_line = lead + 2 * FB + 300 * 64
    corrupted = bytearray(data)
    corrupted[half_line + 505 // 8] ^= 1 << (505 % 8)
    (tmp_path / "c.dat").write_bytes(bytes(corrupted))
    spikes = lazy.open_capture(tmp_path / "c.dat", layout="sps100", chunk_frames=1)
    assert spikes[:2].values.shape == (2, 1000, 1000)  # the frames before it read
    with pytest.raises(CaptureDamaged, match=f"at byte {half_line + 48}: half-line 300 of frame 2"):
        spikes[2].values
    for on in ("threads", "client"):  # ingest's tasks find it, and remove the new store as ingest does (the damage
        with dask.config.set(scheduler=client if on == "client" else "threads"):  # stays: a resume cannot help)
            with pytest.raises(CaptureDamaged, match=f"at byte {half_line + 48}: half-line 300 of frame 2"):
                lazy.to_spikes(spikes, tmp_path / "c.zarr", chunk_frames=1)
        assert not (tmp_path / "c.zarr").exists()
    (tmp_path / "e.dat").write_bytes(data[:half_line + 16] + data[half_line + 32:])
    with pytest.raises(CaptureDamaged, match=f"at byte {half_line + 48}: half-line 300 of frame 2"):
        lazy.open_capture(tmp_path / "e.dat", layout="sps100")
    last = lead + 3 * FB + 700 * 64
    (tmp_path / "d.dat").write_bytes(data[:last + 16] + data[last + 32:])
    with pytest.raises(CaptureDamaged, match=f"at byte {last + 48}: half-line 700 of frame 3"):
        lazy.open_capture(tmp_path / "d.dat", layout="sps100")


def test_layout_dat_reads_raw_frames_whatever_the_name_but_an_array_file(tmp_path):
    """"--layout dat reads any name as .dat frames": raw frames named .npy were refused as a .npy array; a real
    .npy (told by its first bytes) still is."""
    frames = (np.random.default_rng(1).random((3, 8, 16)) < 0.5).astype(np.uint8)
    raw = np.packbits(frames, axis=-1, bitorder="little").tobytes()
    (tmp_path / "raw.npy").write_bytes(raw)
    np.testing.assert_array_equal(lazy.open_capture(tmp_path / "raw.npy", layout="dat", height=8, width=16).values,
                                  frames.astype(bool))
    np.save(tmp_path / "real.npy", frames)
    with pytest.raises(InputError, match=r"real.npy is a .npy array: leave (--)?layout out"):
        lazy.open_capture(tmp_path / "real.npy", layout="dat", height=8, width=16)


def test_spike_values_other_than_0_and_1_remove_the_new_store_as_ingest_does(client, cli, tmp_path):
    """A 2 at frame 5 of a .npy: to_spikes left the store and said "call to_spikes again with resume=True", which
    finds the 2 again, and a fixed file is then refused as another capture; ``cscsr ingest`` removed its store.
    Now each way removes it, in one line naming the value and where it is."""
    frames = (np.random.default_rng(0).random((40, 16, 24)) < 0.3).astype(np.uint8)
    frames[5, 3, 4] = 2
    np.save(tmp_path / "two.npy", frames)
    said = "spike values must be 0 or 1: found 2 at frame 5, row 3, column 4"
    for on in ("threads", "client"):
        with dask.config.set(scheduler=client if on == "client" else "threads"):
            with pytest.raises(CaptureDamaged, match=said):
                lazy.to_spikes(lazy.open_capture(tmp_path / "two.npy"), tmp_path / "lazy.zarr", chunk_frames=8)
        assert not (tmp_path / "lazy.zarr").exists()
    for workers in ([], ["--workers", 1]):
        result = cli("-q", "ingest", tmp_path / "two.npy", tmp_path / "job.zarr", *workers)
        assert result.exit_code == 1 and result.stderr.strip().splitlines() == [f"error: {said}"], result.stderr
        assert not (tmp_path / "job.zarr").exists()


def test_bad_input_is_refused_in_one_line_in_python_words_and_nothing_is_written(tmp_path):
    write_dat(tmp_path / "c.dat", np.zeros((4, 8, 16), np.uint8))
    (tmp_path / "cut.dat").write_bytes((tmp_path / "c.dat").read_bytes()[:-3])
    np.save(tmp_path / "a.npy", np.zeros((3, 8, 16), np.uint8))
    np.savez(tmp_path / "a.npz", spk=np.zeros((3, 8, 16), np.uint8))
    write_capture(tmp_path / "s.dat", sps100_spikes(1))
    cases = [
        ((tmp_path / "cut.dat",), dict(height=8, width=16), InputError, "13 bytes too many, or 3 missing"),
        ((tmp_path / "c.dat",), dict(height=8), InputError, "give both height and width"),
        ((tmp_path / "c.dat",), dict(height=7, width=16), InputError, "not a multiple of the frame size"),
        ((tmp_path / "c.dat",), dict(height=8, width=16, layout="sps1000"), InputError,
         "unknown raw layout 'sps1000': expected one of dat, sps100"),
        ((tmp_path / "a.npy",), dict(width=17), InputError, "width=17 is inconsistent with the array's width 16"),
        ((tmp_path / "a.npy",), dict(layout="sps100"), InputError, "layout sps100 names a raw capture's layout"),
        ((tmp_path / "a.npy",), dict(head_columns=8), InputError, "head_columns applies to .dat captures only"),
        ((tmp_path / "a.npz",), {}, InputError, "save the array as .npy"),
        ((tmp_path / "s.dat",), dict(layout="sps100", height=500), InputError,
         "height=500 is inconsistent with the sps100 layout's fixed 1000x1000 frames: leave height out"),
        ((tmp_path / "c.dat",), dict(height="8", width=16), InputTypeError, "height must be an integer"),
        ((tmp_path / "c.dat",), dict(height=8, width=16, cfa="rgbw"), InputError, "unknown CFA 'rgbw'"),
        ((tmp_path / "c.dat",), dict(height=8, width=16, chunk_frames=0), InputError, "chunk_frames must be"),
        ((tmp_path / "none.dat",), dict(height=8, width=16), InputError, "no such file"),
        ((None,), {}, InputTypeError, "path must be a path or URL"),
    ]
    before = sorted(os.listdir(tmp_path))
    for args, kwargs, kind, fragment in cases:
        with pytest.raises(kind) as refused:
            lazy.to_spikes(lazy.open_capture(*args, **kwargs), tmp_path / "out.zarr")
        line = str(refused.value)
        assert fragment in line and "\n" not in line and not re.search(r"(?<![\w-])--[a-z]", line), (kwargs, line)
    assert sorted(os.listdir(tmp_path)) == before


def test_the_docs_example_prints_what_the_page_says(tmp_path, monkeypatch, capsys):
    """docs/python.md's raw-capture example, run in an empty folder: every line it prints as its comment says."""
    code = re.search(r"### Raw captures.*?```python\n(.*?)```", PAGES["docs/python.md"], re.S)[1]
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "example", "exec"), {"__name__": "__main__"})
    printed, expected = capsys.readouterr().out.splitlines(), documented_outputs(code)
    assert len(expected) >= 2 and len(printed) == len(expected), printed
    for line, documented in zip(printed, expected):
        assert re.fullmatch(".*".join(map(re.escape, documented.split("..."))), line), (line, documented)
