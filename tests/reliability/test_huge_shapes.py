"""A store whose metadata claims 10⁹ frames (issue #48, item 3).

Editing an array's shape to 10⁹ frames in its ``zarr.json`` (or in the consolidated copy in the group's) made
``export``, ``info`` and ``reconstruct`` build the whole chunk grid in a Python list (24 GB, then the machine's
out-of-memory killer). Now every check over chunks is bounded by what is stored (one listing of the keys, the
grid's size by arithmetic, missing chunks as the runs between stored ones), and a shape that contradicts the
store's own records is refused in one line: ``metadata inconsistent …``.

Each command runs as a user runs it, in a process of its own under a 4 GiB address-space limit
(``RLIMIT_AS``): one line on standard error, a non-zero exit (``info`` of a store that merely lost its chunks
describes it, exit 0), within the subprocess timeout. The healthy stores pass under the same limit, a dry run
of the network (torch, on the CPU) included: 4 GiB leaves torch room.
"""

import json
import os
import resource
import shutil
import subprocess

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from tests.conftest import CSCSR

CLAIMED = 10**9
ADDRESS_SPACE = 4 * 2**30
SECONDS = 60  # generous: each answer takes about a second


def limited() -> None:
    """In the child, before ``cscsr`` starts: at most :data:`ADDRESS_SPACE` bytes of address space."""
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def run_limited(*args, cwd) -> subprocess.CompletedProcess:
    """``cscsr ARGS`` under the limit, on the CPU (CUDA reserves more address space than the limit on a GPU machine)."""
    return subprocess.run([CSCSR, *map(str, args)], capture_output=True, text=True, timeout=SECONDS,
                          preexec_fn=limited, cwd=cwd, env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """(spike store, video store): 205 frames of 16x16 RGGB, and its 5 output frames (TFP, x2)."""
    folder = tmp_path_factory.mktemp("huge")
    np.save(folder / "c.npy", (np.random.default_rng(0).random((205, 16, 16)) < 0.2).astype(np.uint8))
    runner = CliRunner()
    for args in (["ingest", folder / "c.npy", folder / "s.zarr", "--cfa", "rggb"],
                 ["reconstruct", folder / "s.zarr", folder / "v.zarr", "--workers", 1, "--scale", 2]):
        result = runner.invoke(app, [str(a) for a in args])
        assert result.exit_code == 0, result.output
    return folder / "s.zarr", folder / "v.zarr"


def edit(path, change) -> None:
    metadata = json.loads(path.read_text())
    change(metadata)
    path.write_text(json.dumps(metadata))


def claim(store, name: str, *, own: bool = True, consolidated: bool = True, chunk: int | None = None) -> None:
    """Array ``name`` of ``store`` claims :data:`CLAIMED` frames (in chunks of ``chunk`` frames if given): in its own
    ``zarr.json`` (``own``) and in the consolidated copy in the group's (``consolidated``)."""
    def huge(metadata) -> None:
        metadata["shape"][0] = CLAIMED
        if chunk is not None:
            metadata["chunk_grid"]["configuration"]["chunk_shape"][0] = chunk

    if own:
        edit(store / name / "zarr.json", huge)
    if consolidated:
        edit(store / "zarr.json", lambda metadata: huge(metadata["consolidated_metadata"]["metadata"][name]))


def from_before(store, *attributes: str, arrays: tuple[str, ...] = ()) -> None:
    """``store`` as a release before these records wrote it: without ``attributes`` and ``arrays``."""
    def drop(metadata) -> None:
        for name in attributes:
            metadata["attributes"].pop(name)
        for name in arrays:
            metadata["consolidated_metadata"]["metadata"].pop(name)

    edit(store / "zarr.json", drop)
    for name in arrays:
        shutil.rmtree(store / name)


def tampered(stores, tmp_path, kind: str, tamper):
    """A copy of the spike (``kind`` "spikes") or video store, tampered."""
    store = tmp_path / f"{kind}.zarr"
    shutil.copytree(stores[0] if kind == "spikes" else stores[1], store)
    tamper(store)
    return store


VIDEO_ONLY = "'video' is (1000000000, 32, 32, 3) in video/zarr.json but (5, 32, 32, 3) in the consolidated copy"
CASES = [
    # (id, kind, tamper, fragment of the one line)
    ("video-own-zarr-json", "video", lambda s: claim(s, "video", consolidated=False),
     f"metadata inconsistent: {VIDEO_ONLY}"),  # export wrote a 5-frame video from it, exit 0
    ("video-consolidated-copy", "video", lambda s: claim(s, "video", own=False),
     "metadata inconsistent: 'video' is (5, 32, 32, 3) in video/zarr.json but (1000000000, 32, 32, 3) in the "
     "consolidated copy"),  # info read it as healthy
    ("video-every-array-and-copy", "video", lambda s: [claim(s, name) for name in ("video", "frames", "committed")],
     "metadata inconsistent: 'video' has 1000000000 output frames, but the store records spike frames 0 to 205 "
     "(stop excluded), one output frame every 41: at most 5"),  # a 7.45 GiB read of 'frames'
    ("spikes-own-zarr-json", "spikes", lambda s: claim(s, "spikes", consolidated=False),
     "metadata inconsistent: 'spikes' has 1000000000 frames, but the store records 205 (attribute frames)"),
    ("spikes-consolidated-copy", "spikes", lambda s: claim(s, "spikes", own=False),
     "metadata inconsistent: 'spikes' is (205, 16, 2) in spikes/zarr.json but (1000000000, 16, 2) in the "
     "consolidated copy"),
]


def commands(kind: str, store, tmp_path) -> list[list]:
    """Every command that reads ``store``, with an output of its own in ``tmp_path``."""
    if kind == "video":
        return [["info", store], ["export", store, tmp_path / "out.mp4"], ["export", store, tmp_path / "frames"]]
    return [["info", store], ["export", store, tmp_path / "out.dat"],
            ["reconstruct", store, tmp_path / "out.zarr", "--dry-run", "--workers", 1]]


def assert_one_line(result, *fragments) -> str:
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1 and lines[0].startswith("error: "), \
        (result.returncode, result.stderr[-2000:])
    assert "MemoryError" not in lines[0]
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("kind,tamper,fragment", [pytest.param(k, t, f, id=i) for i, k, t, f in CASES])
def test_a_shape_that_contradicts_the_store_is_one_line(stores, tmp_path, kind, tamper, fragment):
    store = tampered(stores, tmp_path, kind, tamper)
    for args in commands(kind, store, tmp_path):
        assert_one_line(run_limited(*args, cwd=tmp_path), f"{'spike' if kind == 'spikes' else 'video'} store {store}",
                        fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == [store.name]  # no output, no claim left


def test_a_video_store_from_before_its_records_claiming_huge_is_damaged_not_listed(stores, tmp_path):
    """No ``start``/``stop`` to compare against: the lost chunks are counted from what is stored."""
    def tamper(store) -> None:
        for name in ("video", "frames", "committed"):
            claim(store, name)
        from_before(store, "start", "stop")

    store = tampered(stores, tmp_path, "video", tamper)
    lost = "999999995 of 1000000000 chunks of video (output frames 5..999999999"
    info = run_limited("info", store, "--json", cwd=tmp_path)
    assert info.returncode == 0 and not info.stderr, info.stderr
    assert json.loads(info.stdout)["state"].startswith(f"damaged: {lost}")
    for dest in (tmp_path / "out.mp4", tmp_path / "frames"):
        assert_one_line(run_limited("export", store, dest, cwd=tmp_path), f"video store {store} is damaged: {lost}",
                        "nothing exported")
    assert sorted(p.name for p in tmp_path.iterdir()) == [store.name]


def test_a_spike_store_from_before_its_records_claiming_huge_is_bounded(stores, tmp_path):
    """No ``frames`` attribute and no task record, 10⁹ frames in chunks of one frame: a grid of 10⁹ chunks, which
    the old check listed in full. ``info`` counts the missing ones, ``export`` and the dry run stop at the first."""
    store = tampered(stores, tmp_path, "spikes", lambda s: (claim(s, "spikes", chunk=1),
                                                            from_before(s, "frames", arrays=("committed",))))
    info = run_limited("info", store, "--json", cwd=tmp_path)
    assert info.returncode == 0 and not info.stderr, info.stderr
    assert json.loads(info.stdout)["missing_chunks"] == ("999999999 of 1000000000 chunks of spikes (frames 1..1, 2..2, "
                                                         "3..3, 4..4, and 999999995 more)")
    assert_one_line(run_limited("export", store, tmp_path / "out.dat", cwd=tmp_path),
                    f"spike store {store}: the chunk of frames 1..1 is missing (lost data)")
    assert_one_line(run_limited("reconstruct", store, tmp_path / "out.zarr", "--dry-run", "--workers", 1, cwd=tmp_path),
                    f"spike store {store}: the chunk of frames", "is missing (lost data)")
    assert sorted(p.name for p in tmp_path.iterdir()) == [store.name]


def test_the_healthy_stores_work_under_the_same_limit(stores, tmp_path):
    spikes, video = stores
    for args in (["info", spikes], ["info", video], ["export", video, tmp_path / "out.mp4"],
                 ["export", spikes, tmp_path / "out.dat"],
                 ["reconstruct", spikes, tmp_path / "out.zarr", "--dry-run", "--workers", 1],
                 ["reconstruct", spikes, tmp_path / "out.zarr", "--dry-run", "--workers", 1, "--method", "cscsr"]):
        result = run_limited(*args, cwd=tmp_path)
        assert result.returncode == 0, (args, result.stderr[-2000:])
    assert (tmp_path / "out.mp4").stat().st_size > 0 and (tmp_path / "out.dat").stat().st_size == 205 * 16 * 16 // 8
