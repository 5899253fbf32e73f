"""Tampered metadata is refused (issue #48, item 6).

A spike array cut from 205 to 100 frames by editing its ``zarr.json`` (and the consolidated copy in the
group's), or a ``format_version`` this release does not know, used to pass ``info``, ``export`` and
``reconstruct`` without a word. The opener (:func:`pipeline.stores.spike_store.open_spike_store`) now compares what the
store records of itself, metadata only: ``format_version``, the ``frames`` attribute, ``spike_count``, the
consolidated copy and an ingested store's task record. Each refusal is one line ``error: ...`` naming the store
and the problem, exit status 1, nothing created; an untampered store, a store from before the ``frames``
attribute and a store still being written read as before. The video store's opener does the same for its
``format_version`` and its arrays' frame counts.
"""

import json
import os
import shutil

import numpy as np
import pytest
import zarr

from pipeline.stores import spike_store
from tests.reliability.test_fuzz_readers import run_on_store as run

FRAMES, HEIGHT, WIDTH, TASK_FRAMES = 205, 16, 16, 40  # 5 frames a chunk (small_chunks), 6 tasks
COMMANDS = ("info", "export", "reconstruct")


@pytest.fixture
def small_chunks(monkeypatch):
    """Chunks of 160 packed bytes (5 frames of 16x16), so that the store has several ingest tasks."""
    monkeypatch.setattr(spike_store, "TARGET_CHUNK_BYTES", 160)


@pytest.fixture
def store(cli, tmp_path, small_chunks):
    """A complete 205-frame 16x16 RGGB spike store, ingested in tasks of 40 frames."""
    capture = tmp_path / "c.npy"
    np.save(capture, (np.random.default_rng(0).random((FRAMES, HEIGHT, WIDTH)) < 0.2).astype(np.uint8))
    path = tmp_path / "s.zarr"
    result = cli("ingest", capture, path, "--cfa", "rggb", "--task-frames", TASK_FRAMES)
    assert result.exit_code == 0, result.stderr
    return path


def edit(path, change) -> None:
    """Edit a ``zarr.json`` as a user could: read the JSON, ``change`` it, write it back."""
    metadata = json.loads(path.read_text())
    change(metadata)
    path.write_text(json.dumps(metadata))


def attributes(**changes):
    return lambda metadata: metadata["attributes"].update(changes)


def without(name):
    return lambda metadata: metadata["attributes"].pop(name)


def cut(store, frames: int, *, consolidated: bool = True) -> None:
    """``spikes`` cut to ``frames`` frames in its own ``zarr.json`` and (``consolidated``) in the group's copy."""
    shape = [frames, HEIGHT, WIDTH // 8]
    edit(store / "spikes" / "zarr.json", lambda metadata: metadata.update(shape=shape))
    if consolidated:
        edit(store / "zarr.json", lambda metadata: metadata["consolidated_metadata"]["metadata"]["spikes"].update(
            shape=shape))


def assert_refused(result, out, *fragments) -> None:
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1, (result.exit_code, result.stderr)
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    assert out is None or not os.path.exists(out)
    assert out is None or not os.path.exists(f"{out}.partial")


CASES = [
    # (id, tamper(store), fragments)
    ("format-version-99", lambda s: edit(s / "zarr.json", attributes(format_version=99)),
     ["format_version 99 is not one this cscsr", "reads (1..1)", "metadata inconsistent: it records cscsr"]),
    ("format-version-text", lambda s: edit(s / "zarr.json", attributes(format_version="1")),
     ["metadata inconsistent: format_version '1' is not a format version (1..1)"]),
    ("format-version-zero", lambda s: edit(s / "zarr.json", attributes(format_version=0)),
     ["format_version 0 is not a format version"]),
    ("frames-cut-in-both-copies", lambda s: cut(s, 100),
     ["metadata inconsistent: 'spikes' has 100 frames, but the store records 205 (attribute frames)"]),
    ("frames-attribute-text", lambda s: edit(s / "zarr.json", attributes(frames="205")),
     ["attribute frames must be an integer, got '205'"]),
    # a store from before the frames attribute: the consolidated copy, the task record, the spike count
    ("frames-cut-in-the-array-only",
     lambda s: (edit(s / "zarr.json", without("frames")), cut(s, 100, consolidated=False)),
     ["metadata inconsistent: 'spikes' is (100, 16, 2) in spikes/zarr.json but (205, 16, 2) in the consolidated copy"]),
    ("frames-cut-against-the-task-record", lambda s: (edit(s / "zarr.json", without("frames")), cut(s, 100)),
     ["metadata inconsistent: 'spikes' has 100 frames, but 'committed' records 6 ingest tasks of 40 frames "
      "(3 for 100 frames)"]),
    ("frames-cut-against-the-spike-count", lambda s: (edit(s / "zarr.json", attributes(frames=20)), cut(s, 20)),
     ["metadata inconsistent: spike_count", "is more than its 20 frames of 16x16 pixels can hold (5120)"]),
]


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("tamper,fragments", [pytest.param(t, f, id=i) for i, t, f in CASES])
def test_tampered_store_is_refused_in_one_line(cli, store, tmp_path, command, tamper, fragments):
    tamper(store)
    result, out = run(cli, command, store, tmp_path)
    assert_refused(result, out, f"spike store {store}", *fragments)


def test_untampered_store_still_works(cli, store, tmp_path):
    group = zarr.open_group(str(store), mode="r", use_consolidated=False)
    assert group.attrs["frames"] == FRAMES and group.attrs["format_version"] == 1
    assert group["committed"].shape == (6,)
    info = cli("info", store, "--json")
    assert info.exit_code == 0, info.stderr
    assert json.loads(info.stdout)["frames"] == FRAMES
    for command in ("export", "reconstruct"):
        result, out = run(cli, command, store, tmp_path)
        assert result.exit_code == 0, result.stderr
        assert os.path.exists(out)
    assert os.path.getsize(tmp_path / "out.dat") == FRAMES * HEIGHT * WIDTH // 8


def test_store_from_before_the_checks_still_works(cli, store, tmp_path):
    """No ``frames`` attribute, no consolidated copy, no ``format_version``: nothing to compare, read as before."""
    old = tmp_path / "old.zarr"
    shutil.copytree(store, old)
    edit(old / "zarr.json", lambda metadata: (metadata.pop("consolidated_metadata"),
                                              metadata["attributes"].pop("frames"),
                                              metadata["attributes"].pop("format_version")))
    assert cli("info", old).exit_code == 0
    for source, out in ((old, tmp_path / "old.dat"), (store, tmp_path / "new.dat")):
        result = cli("export", source, out)
        assert result.exit_code == 0, result.stderr
    assert (tmp_path / "old.dat").read_bytes() == (tmp_path / "new.dat").read_bytes()


def test_store_being_written_is_still_resumed(cli, store, tmp_path):
    """An interrupted ingest (state "writing", tasks not committed, not yet counted or consolidated) is no
    contradiction: ``info`` shows it, readers call it incomplete, ``ingest --resume`` finishes it."""
    group = zarr.open_group(str(store), mode="r+", use_consolidated=False)
    reference = dict(group.attrs)
    group.attrs["state"] = "writing"
    group["committed"][3:] = -1
    edit(store / "zarr.json", lambda metadata: (metadata.pop("consolidated_metadata", None),  # dropped already
                                                metadata["attributes"].pop("spike_count"),
                                                metadata["attributes"].pop("identity")))
    info = cli("info", store, "--json")
    assert info.exit_code == 0 and json.loads(info.stdout)["state"] == "writing", info.stderr
    result, out = run(cli, "export", store, tmp_path)
    assert_refused(result, out, "incomplete (state 'writing')")
    result = cli("-q", "ingest", tmp_path / "c.npy", store, "--cfa", "rggb", "--task-frames", TASK_FRAMES, "--resume")
    assert result.exit_code == 0 and "(3 tasks run, 3 already committed)" in result.stdout, result.stderr
    assert dict(zarr.open_group(str(store), mode="r", use_consolidated=False).attrs) == reference
    assert cli("info", store).exit_code == 0


@pytest.fixture
def video(cli, store, tmp_path):
    out = tmp_path / "video.zarr"
    result = cli("reconstruct", store, out, "--workers", 1)
    assert result.exit_code == 0, result.stderr
    return out


def test_tampered_video_store_is_refused(cli, video, tmp_path):
    pristine = tmp_path / "pristine.zarr"
    shutil.copytree(video, pristine)
    assert cli("info", video).exit_code == 0
    cases = [
        (lambda v: edit(v / "zarr.json", attributes(format_version=99)), "format_version 99 is not one this cscsr"),
        (lambda v: edit(v / "zarr.json", attributes(format_version="one")),
         "format_version 'one' is not a format version"),
        (lambda v: (edit(v / "video" / "zarr.json", lambda m: m["shape"].__setitem__(0, 2)),
                    edit(v / "zarr.json",
                         lambda m: m["consolidated_metadata"]["metadata"]["video"]["shape"].__setitem__(0, 2))),
         "metadata inconsistent: its arrays disagree on the number of output frames ('video' 2, 'frames' 5, "
         "'committed' 5)"),
    ]
    for tamper, fragment in cases:
        shutil.rmtree(video)
        shutil.copytree(pristine, video)
        tamper(video)
        assert_refused(cli("info", video), None, f"video store {video}", fragment)
        out = tmp_path / "frames"
        assert_refused(cli("export", video, f"{out}/"), out, f"video store {video}", fragment)
