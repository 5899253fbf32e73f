"""``--overwrite`` replaces only what cscsr wrote, and never loses the old output to a failed run.

Every command that writes (ingest, simulate, reconstruct, make-testset, export to .mp4, to a folder of
PNGs and to .dat) is pointed with ``--overwrite`` at a folder of the user's holding a file, and at an
unrelated regular file: each is refused in one line (``error: ...``, exit 1) and nothing under the
test's folder changes. A store of ours of the other kind is refused too: ``reconstruct`` never replaces
a spike store (a recording), nor ``ingest``/``simulate`` a video store. Our own previous outputs are
still replaced; a run that fails late (a capture with a value of 2 in its last frame) leaves the old
complete output as it was, or a warning names where it is kept (pipeline/stores/outputs.py)."""

import errno
import json
import logging
import os

import imageio.v3 as iio
import numpy as np
import pytest
import zarr

from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from tests.reliability.test_overlap import snapshot
from tests.test_simulate import picture

SIDE, FRAMES = 16, 64


def spikes(seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((FRAMES, SIDE, SIDE)) < 0.2).astype(np.uint8)


@pytest.fixture(scope="module")
def world(tmp_path_factory, client):
    """A capture, its spike store (rggb), a video store made from it, and a picture to simulate from."""
    root = tmp_path_factory.mktemp("ours")
    np.save(root / "c.npy", spikes())
    ingest(str(root / "c.npy"), str(root / "s.zarr"), IngestOptions(cfa="rggb"), progress=False)
    reconstruct(str(root / "s.zarr"), str(root / "v.zarr"), ReconstructOptions(method="tfp", every=2, tile=16),
                client=client, progress=False)
    iio.imwrite(root / "scene.png", picture("astronaut", 4 * SIDE))
    return root


def refused(cli, folder, *args, says: str = "cscsr replaces only its own outputs") -> None:
    """``cscsr ARGS`` exits 1 with one line ``error: ...`` (holding ``says``); nothing under ``folder`` changed."""
    before = snapshot(folder)
    result = cli(*args)
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1 and lines[0].startswith("error: "), (args, result.stderr)
    assert says in lines[0], lines[0]
    assert snapshot(folder) == before, args  # the user's file and folder as they were, nothing added


@pytest.fixture
def user(tmp_path):
    """A folder of the user's holding a thesis, and an unrelated regular file."""
    (tmp_path / "userdir").mkdir()
    (tmp_path / "userdir" / "thesis.tex").write_text("x\n")
    (tmp_path / "notes").write_text("y\n")
    return tmp_path


def test_store_commands_refuse_what_is_not_ours(cli, world, user):
    s, scene = world / "s.zarr", world / "scene.png"
    for target in (user / "userdir", user / "notes"):
        refused(cli, user, "ingest", world / "c.npy", target, "--overwrite")
        refused(cli, user, "ingest", world / "c.npy", target)  # without --overwrite: the same answer
        refused(cli, user, "reconstruct", s, target, "--overwrite", "--every", 2, "--tile", 16, "--workers", 1)
        refused(cli, user, "simulate", scene, target, "--overwrite", "--frames", 41, "--motion", "static",
                "--workers", 1)
        refused(cli, user, "make-testset", target, "--overwrite", "--workers", 1)
    (user / "z.zarr").mkdir()  # a Zarr store, but not one of ours
    (user / "z.zarr" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {}}')
    refused(cli, user, "ingest", world / "c.npy", user / "z.zarr", "--overwrite", says="did not write")
    refused(cli, world, "make-testset", world / "s.zarr", "--overwrite", says="not a test set")  # ours, other kind


def test_a_store_of_the_other_kind_is_refused(cli, world, tmp_path):
    """A spike store is a recording (perhaps the only copy: the raw capture may be gone): ``reconstruct
    --overwrite`` never replaces one, nor ``ingest``/``simulate --overwrite`` a video store."""
    import shutil

    recording, video = tmp_path / "B.zarr", tmp_path / "V.zarr"
    shutil.copytree(world / "s.zarr", recording)
    shutil.copytree(world / "v.zarr", video)
    for extra in (("--overwrite",), ()):
        refused(cli, tmp_path, "reconstruct", world / "s.zarr", recording, *extra, "--every", 2, "--tile", 16,
                "--workers", 1, says=f"output {recording} is a spike store (a recording), not a video store: "
                                     "--overwrite replaces only a video store written by cscsr reconstruct")
        refused(cli, tmp_path, "ingest", world / "c.npy", video, *extra,
                says=f"output {video} is a video store, not a spike store: --overwrite replaces only a spike store")
        refused(cli, tmp_path, "simulate", world / "scene.png", video, *extra, "--frames", 41, "--motion", "static",
                "--workers", 1, says=f"output {video} is a video store, not a spike store")
    # what marks a store as cscsr's is its cscsr_version attribute (every store cscsr wrote has one)
    root = json.loads((recording / "zarr.json").read_text())
    del root["attributes"]["cscsr_version"]
    (recording / "zarr.json").write_text(json.dumps(root))
    refused(cli, tmp_path, "ingest", world / "c.npy", recording, "--overwrite",
            says="a Zarr store that cscsr did not write")


def test_export_refuses_what_is_not_ours(cli, world, user):
    v, s = world / "v.zarr", world / "s.zarr"
    refused(cli, user, "export", v, f"{user / 'userdir'}/", "--overwrite")  # used to wipe the whole folder
    refused(cli, user, "export", v, user / "notes", "--overwrite")  # a folder of PNGs onto a file
    (user / "video.mp4").write_text("not a video\n")
    refused(cli, user, "export", v, user / "video.mp4", "--overwrite", says="a file that is not MP4")
    (user / "folder.mp4").mkdir()
    (user / "folder.mp4" / "thesis.tex").write_text("x\n")
    refused(cli, user, "export", v, user / "folder.mp4", "--overwrite", says="a folder holding thesis.tex")
    (user / "folder.dat").mkdir()
    (user / "folder.dat" / "thesis.tex").write_text("x\n")
    refused(cli, user, "export", s, user / "folder.dat", "--overwrite", says="a folder holding thesis.tex")
    refused(cli, user, "export", s, user / "userdir" / "thesis.tex", "--overwrite", says="expected a .dat")
    (user / "frames").mkdir()  # our frames beside a file of the user's: not only ours
    (user / "frames" / "frame_00000020.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    (user / "frames" / "notes.txt").write_text("mine\n")
    refused(cli, user, "export", v, user / "frames", "--overwrite", says="a folder holding frame_00000020.png")
    (user / "photo.png").write_text("not a picture\n")
    refused(cli, user, "preview", s, user / "photo.png", "--overwrite", says="a file that is not PNG")


def test_export_and_preview_never_replace_what_the_store_was_made_from(cli, world, tmp_path):
    """A capture is a .dat and a picture a PNG, the very kinds export and preview write: ``--overwrite`` onto the
    capture a store was ingested from (or the picture it was simulated from) destroyed the only copy. The store
    records its ``source``, which is an input of theirs too."""
    capture = tmp_path / "capture.dat"
    capture.write_bytes(np.packbits(spikes(1).astype(bool), axis=-1).tobytes())
    assert cli("ingest", capture, tmp_path / "c.zarr", "--height", SIDE, "--width", SIDE).exit_code == 0
    refused(cli, tmp_path, "export", tmp_path / "c.zarr", capture, "--overwrite", says="is the same as input")
    picture = tmp_path / "scene.png"
    picture.write_bytes((world / "scene.png").read_bytes())
    assert cli("simulate", picture, tmp_path / "s.zarr", "--frames", 41, "--motion", "static",
               "--workers", 1).exit_code == 0
    refused(cli, tmp_path, "preview", tmp_path / "s.zarr", picture, "--overwrite", says="is the same as input")
    import zarr  # a source this machine cannot name (no backend for its protocol) is no output's: export goes on

    zarr.open_group(str(tmp_path / "c.zarr"), mode="r+", use_consolidated=False).attrs["source"] = "nobackend://c.dat"
    exported = cli("export", tmp_path / "c.zarr", tmp_path / "again.dat")
    assert exported.exit_code == 0 and (tmp_path / "again.dat").read_bytes() == capture.read_bytes(), exported.stderr


def test_an_empty_path_is_refused_not_taken_for_the_current_folder(cli, world, tmp_path, monkeypatch):
    """fsspec reads "" as the current folder: ``simulate "" OUT`` simulated whatever picture lay there, and an
    empty OUT was refused as "contains input"."""
    monkeypatch.chdir(world)  # scene.png lies here
    for args in (("simulate", "", tmp_path / "out.zarr", "--frames", 41, "--motion", "static", "--workers", 1),
                 ("simulate", "scene.png", "", "--frames", 41, "--motion", "static", "--workers", 1),
                 ("ingest", "", tmp_path / "out.zarr"), ("export", "", tmp_path / "out.mp4")):
        refused(cli, tmp_path, *args, says="a path is empty ('')")


def asides(folder) -> list[str]:
    return [name for name in os.listdir(folder) if ".old-" in name]


def test_our_own_outputs_are_still_replaced(cli, world, tmp_path, client):
    out = tmp_path / "s.zarr"
    assert cli("ingest", world / "c.npy", out).exit_code == 0
    (tmp_path / ".s.zarr.old-0123456789ab").mkdir()  # what a run killed during an --overwrite leaves
    np.save(tmp_path / "other.npy", spikes(seed=1))
    assert cli("ingest", tmp_path / "other.npy", out, "--cfa", "rggb", "--overwrite").exit_code == 0
    group = zarr.open_group(str(out), mode="r")
    assert group.attrs["state"] == "complete" and group.attrs["spike_count"] == int(spikes(seed=1).sum())
    assert asides(tmp_path) == []  # the old store, and the one a killed run left, are gone once the new one is complete

    video = tmp_path / "v.zarr"
    args = ("reconstruct", out, video, "--every", 2, "--tile", 16, "--scheduler", client.scheduler.address)
    assert cli(*args, "--method", "tfi").exit_code == 0
    result = cli(*args, "--method", "tfp", "--overwrite")
    assert result.exit_code == 0, result.stderr
    assert zarr.open_group(str(video), mode="r").attrs["method"] == "tfp" and asides(tmp_path) == []

    for dest in ("v.mp4", "frames", "x.dat"):
        store = world / ("s.zarr" if dest.endswith(".dat") else "v.zarr")
        assert cli("export", store, tmp_path / dest).exit_code == 0
        result = cli("export", store, tmp_path / dest, "--overwrite")
        assert result.exit_code == 0, result.stderr
    assert (tmp_path / "v.mp4").read_bytes()[4:8] == b"ftyp"
    assert sorted(os.listdir(tmp_path / "frames")) == [f"frame_{20 + 2 * j:08d}.png" for j in range(12)]
    assert (tmp_path / "x.dat").read_bytes() == np.packbits(spikes().reshape(FRAMES, -1), axis=-1,
                                                           bitorder="little").tobytes()
    assert asides(tmp_path) == [] and not os.path.exists(tmp_path / "x.dat.partial")


def test_make_testset_replaces_only_a_test_set(world, tmp_path, monkeypatch):
    """make-testset --overwrite onto a test set of ours (simulation stubbed: the claim is what is tested)."""
    import pipeline.jobs.testset as testset
    from pipeline.stores.outputs import TESTSET, mark_folder

    def fake_simulate(source, store, options, **kwargs):
        ingest(str(world / "c.npy"), store, IngestOptions(cfa="rggb"), progress=False)

    monkeypatch.setattr(testset, "simulate", fake_simulate)
    out = tmp_path / "set"
    mark_folder(str(out), TESTSET)
    (out / "old.txt").write_text("from the last test set\n")
    assert testset.make_testset(str(out), overwrite=True, progress=False, only=["coffee_a0.8"])
    assert sorted(os.listdir(out)) == [".cscsr-output", "coffee_a0.8.zarr", "manifest.json", "sources"]

    def failing(source, store, options, **kwargs):
        raise RuntimeError("simulation failed")

    monkeypatch.setattr(testset, "simulate", failing)
    before = snapshot(tmp_path)
    with pytest.raises(RuntimeError, match="simulation failed"):
        testset.make_testset(str(out), overwrite=True, progress=False, only=["coffee_a0.8"])
    assert snapshot(tmp_path) == before  # the old test set back, as it was


def test_a_failed_overwrite_keeps_the_old_output(cli, world, tmp_path):
    out = tmp_path / "s.zarr"
    assert cli("ingest", world / "c.npy", out).exit_code == 0
    before = snapshot(tmp_path)
    bad = spikes(seed=2)
    bad[-1, -1, -1] = 2  # found only when the last block is read, after the new store exists
    np.savez(tmp_path / "bad.npz", spk=bad)
    result = cli("ingest", tmp_path / "bad.npz", out, "--overwrite")
    assert result.exit_code == 1 and "found 2 at frame 63" in result.stderr, result.stderr
    after = snapshot(tmp_path)
    after.pop("bad.npz")
    assert after == before  # the old complete store, byte for byte; no new store, nothing set aside


def test_object_stores_refuse_too(cli, world):
    """On memory:// (no rename) the same rules: a user's object refused, our own store replaced."""
    import fsspec

    fs = fsspec.filesystem("memory")
    fs.pipe_file("/ours-test/userdir/thesis.tex", b"x\n")
    refused(cli, world, "ingest", world / "c.npy", "memory://ours-test/userdir", "--overwrite")
    assert fs.cat_file("/ours-test/userdir/thesis.tex") == b"x\n"
    assert cli("ingest", world / "c.npy", "memory://ours-test/s.zarr").exit_code == 0
    assert cli("ingest", world / "c.npy", "memory://ours-test/s.zarr", "--overwrite").exit_code == 0
    fs.rm("/ours-test", recursive=True)


def test_a_failed_reconstruct_overwrite_keeps_both(world, tmp_path, client):
    """A reconstruct --overwrite whose tasks fail keeps its new store for --resume and the old one aside; the
    resume that completes the new one removes the old one."""
    import glob
    import shutil

    from pipeline.jobs.reconstruct import JobIncomplete

    recording, video = str(tmp_path / "s.zarr"), str(tmp_path / "v.zarr")
    shutil.copytree(world / "s.zarr", recording)
    options = ReconstructOptions(method="tfp", every=2, tile=16)
    reconstruct(recording, video, options, client=client, progress=False)
    old = snapshot(video)
    chunk = sorted(glob.glob(f"{recording}/spikes/c/*/*/*"))[0]
    original = open(chunk, "rb").read()
    with open(chunk, "wb") as f:
        f.write(b"\x00garbage, not zstd")
    from stages.errors import InputError

    with pytest.raises(InputError, match="a chunk is damaged"):  # the automatic gain fails: no new store yet
        reconstruct(recording, video, ReconstructOptions(method="tfi", every=2, tile=16, overwrite=True),
                    client=client, progress=False)
    assert snapshot(video) == old and asides(tmp_path) == []  # the old one put back
    with pytest.raises(JobIncomplete):  # the tasks fail: the new store exists
        reconstruct(recording, video, ReconstructOptions(method="tfi", every=2, tile=16, gain=1.0, overwrite=True),
                    client=client, progress=False)
    [aside] = asides(tmp_path)
    assert snapshot(tmp_path / aside) == old  # the old video, whole, beside the new one
    assert zarr.open_group(video, mode="r").attrs["state"] == "writing"
    with open(chunk, "wb") as f:
        f.write(original)
    reconstruct(recording, video, ReconstructOptions(method="tfi", every=2, tile=16, gain=1.0, resume=True),
                client=client, progress=False)
    assert zarr.open_group(video, mode="r").attrs["method"] == "tfi" and asides(tmp_path) == []


def test_a_failed_restore_says_where_the_old_output_is(tmp_path, monkeypatch, caplog):
    """If the new output cannot be removed and the old one cannot be renamed back, a warning names where the
    old one is kept (it was silent)."""
    import pipeline.stores.outputs as outputs

    out = tmp_path / "v.mp4"
    out.write_bytes(b"\x00\x00\x00\x18ftypisom old video")
    rename = os.rename

    def failing_rename(source, target):
        if ".old-" in os.path.basename(source):
            raise OSError(errno.EACCES, "Permission denied")
        return rename(source, target)

    def failing_remove(url):
        raise OSError(errno.EBUSY, "Device or resource busy")

    monkeypatch.setattr(outputs.os, "rename", failing_rename)
    monkeypatch.setattr(outputs, "remove", failing_remove)
    with caplog.at_level(logging.WARNING, logger="cscsr.outputs"), pytest.raises(RuntimeError, match="late"):
        with outputs.new_output(str(out), overwrite=True, kind=".mp4"):
            out.write_bytes(b"half a video")
            raise RuntimeError("failed late")
    [aside] = asides(tmp_path)
    assert (tmp_path / aside).read_bytes() == b"\x00\x00\x00\x18ftypisom old video"
    assert f"the old {out} could not be put back (Permission denied; the new, unfinished {out} could not be " \
           f"removed (Device or resource busy)): it is kept as {tmp_path / aside}" in caplog.text


def test_any_complete_output_removes_what_a_killed_run_set_aside(tmp_path):
    """A run killed during an --overwrite leaves the old output as .NAME.old-<id>; the next job that completes
    an output at NAME removes it, --overwrite or not (docs/reliability.md, Known gaps)."""
    from pipeline.stores.outputs import new_output

    (tmp_path / ".v.mp4.old-0123456789ab").write_bytes(b"\x00\x00\x00\x18ftypisom old video")
    (tmp_path / ".v.mp4.other").write_text("not set aside by cscsr\n")
    with new_output(str(tmp_path / "v.mp4"), overwrite=False, kind=".mp4"):
        (tmp_path / "v.mp4").write_bytes(b"\x00\x00\x00\x18ftypisom new video")
    assert sorted(os.listdir(tmp_path)) == [".v.mp4.other", "v.mp4"]
