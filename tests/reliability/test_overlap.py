"""An output that is, is inside, or contains an input is refused by every command that writes, before
anything is created or deleted, whatever the spelling (a symbolic link, ``file://``, a trailing slash).

Each case runs the real command line (in-process, or the installed console command) on real stores
and checks: exit status 1, one line naming both paths, and every byte under the test's folder
unchanged, nothing added (no claim file, no empty output folder)."""

import hashlib
import json
import os

import imageio.v3 as iio
import numpy as np
import pytest

from cscsr import samples
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from pipeline.jobs.simulate import SimulateOptions, simulate
from pipeline.stores.storage import check_apart
from stages.errors import InputError
from tests.conftest import integrate_and_fire, smooth_rate, write_dat
from tests.test_simulate import picture

SIDE = 16  # LR pixels of the capture


@pytest.fixture(scope="module")
def world(tmp_path_factory, client):
    """A raw capture, its spike store, a simulated store with truth and a video store, all real."""
    root = tmp_path_factory.mktemp("overlap")
    write_dat(root / "x.dat", integrate_and_fire(smooth_rate(SIDE, SIDE), 101))
    ingest(str(root / "x.dat"), str(root / "s.zarr"), IngestOptions(SIDE, SIDE, cfa="rggb"), progress=False)
    iio.imwrite(root / "scene.png", picture("astronaut", 4 * SIDE))
    simulate(str(root / "scene.png"), str(root / "sim.zarr"), SimulateOptions(scale=4, frames=41, motion="static"),
             scheduler=client.scheduler.address, progress=False)
    reconstruct(str(root / "sim.zarr"), str(root / "v.zarr"), ReconstructOptions(method="tfp", tile=16),
                client=client, progress=False)
    return root


def snapshot(folder) -> dict:
    """Every file and folder under ``folder`` (symbolic links not followed): its bytes' hash, or a marker."""
    seen = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            path = os.path.join(root, name)
            key = os.path.relpath(path, folder)
            if os.path.islink(path):
                seen[key] = "link -> " + os.readlink(path)
            elif os.path.isdir(path):
                seen[key] = "folder"
            else:
                seen[key] = hashlib.sha256(open(path, "rb").read()).hexdigest()
    return seen


def refused(run, folder, output: str, source: str, *args, relation: str = "") -> None:
    """``run(*args)`` exits 1 with one line naming ``output`` and ``source``; nothing under ``folder`` changed."""
    before = snapshot(folder)
    result = run(*args)
    code = result.returncode if hasattr(result, "returncode") else result.exit_code  # a process, or in-process
    lines = result.stderr.strip().splitlines()
    assert code == 1 and len(lines) == 1, (args, result.stderr)
    assert lines[0].startswith(f"error: output {output} ") and f" input {source}" in lines[0], lines[0]
    assert relation in lines[0], lines[0]
    assert snapshot(folder) == before, args  # the input's bytes unchanged, nothing created


def test_ingest_into_its_own_capture(world, cli, cli_process, tmp_path):
    x = str(world / "x.dat")
    size = ("--height", SIDE, "--width", SIDE, "--overwrite")
    refused(cli, world, x, x, "ingest", x, x, *size, relation="is the same as")
    refused(cli, world, f"file://{x}", x, "ingest", x, f"file://{x}", *size, relation="is the same as")
    refused(cli, world, str(world), x, "ingest", x, str(world), *size, relation="contains")
    os.symlink(x, tmp_path / "link.dat")  # a symbolic link to the capture, through the installed command
    refused(cli_process, world, str(tmp_path / "link.dat"), x, "ingest", x, tmp_path / "link.dat", *size,
            relation=f"is the same as input {x} (both are {os.path.realpath(x)})")


def test_reconstruct_into_its_own_spike_store(world, cli, cli_process, tmp_path):
    s = str(world / "s.zarr")
    refused(cli, world, s, s, "reconstruct", s, s, "--overwrite", relation="is the same as")
    refused(cli, world, f"{s}/spikes", s, "reconstruct", s, f"{s}/spikes", "--overwrite", relation="is inside")
    refused(cli, world, f"{s}/", s, "reconstruct", s, f"{s}/", "--resume", relation="is the same as")
    refused(cli, world, str(world), s, "reconstruct", s, str(world), "--overwrite", relation="contains")
    os.symlink(world, tmp_path / "linked")  # the store's folder under another name
    refused(cli, world, str(tmp_path / "linked" / "s.zarr"), s, "reconstruct", s, tmp_path / "linked" / "s.zarr",
            "--overwrite", relation="is the same as")
    refused(cli_process, world, f"file://{s}", s, "reconstruct", s, f"file://{s}", "--overwrite",
            relation="is the same as")
    weights = str(world / "x.dat")  # --weights is an input too
    refused(cli, world, weights, weights, "reconstruct", s, weights, "--method", "cscsr", "--weights", weights,
            "--overwrite", relation="is the same as")


def test_export_into_its_own_store(world, cli):
    v, s = str(world / "v.zarr"), str(world / "s.zarr")
    refused(cli, world, f"{v}/", v, "export", v, f"{v}/", "--overwrite", relation="is the same as")
    refused(cli, world, f"{v}/video.mp4", v, "export", v, f"{v}/video.mp4", "--overwrite", relation="is inside")
    refused(cli, world, f"{s}/spikes.dat", s, "export", s, f"{s}/spikes.dat", "--overwrite", relation="is inside")


def test_preview_into_its_own_store(world, cli):
    s = str(world / "s.zarr")
    refused(cli, world, s, s, "preview", s, s, "--overwrite", relation="is the same as")
    refused(cli, world, f"{s}/p.png", s, "preview", s, f"{s}/p.png", relation="is inside")


def test_simulate_into_its_own_source(world, cli, tmp_path):
    scene = str(world / "scene.png")
    refused(cli, world, scene, scene, "simulate", scene, scene, "--overwrite", relation="is the same as")
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(2):
        iio.imwrite(frames / f"{k}.png", picture("astronaut", 4 * SIDE))
    refused(cli, tmp_path, f"{frames}/out.zarr", str(frames), "simulate", frames, f"{frames}/out.zarr",
            relation="is inside")


def test_evaluate_into_its_own_store(world, cli):
    sim = str(world / "sim.zarr")
    refused(cli, world, sim, sim, "evaluate", sim, "--out", sim, relation="is the same as")
    refused(cli, world, str(world), sim, "evaluate", sim, "--out", world, relation="contains")
    refused(cli, world, f"{sim}/evaluation", sim, "evaluate", sim, "--out", f"{sim}/evaluation", relation="is inside")


def test_evaluate_testset_into_its_test_set(cli, tmp_path):
    testset = tmp_path / "testset"
    testset.mkdir()
    (testset / "manifest.json").write_text(json.dumps({"items": []}))
    refused(cli, tmp_path, str(testset), str(testset), "evaluate-testset", testset, "--out", testset,
            relation="is the same as")
    refused(cli, tmp_path, f"{testset}/results", str(testset), "evaluate-testset", testset, "--out",
            f"{testset}/results", relation="is inside")


def test_watch_with_overlapping_boxes(world, cli, tmp_path):
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    (inbox / "x.dat").write_bytes((world / "x.dat").read_bytes())
    refused(cli, tmp_path, str(inbox), str(inbox), "watch", inbox, inbox, "--once", relation="is the same as")
    refused(cli, tmp_path, f"{inbox}/out", str(inbox), "watch", inbox, f"{inbox}/out", "--once", relation="is inside")
    refused(cli, tmp_path, str(tmp_path), str(inbox), "watch", inbox, tmp_path, "--once", relation="contains")


def test_train_and_export_weights_onto_their_inputs(cli, tmp_path):
    pictures = tmp_path / "pictures"
    pictures.mkdir()
    iio.imwrite(pictures / "a.png", picture("astronaut", 64))
    refused(cli, tmp_path, str(pictures), str(pictures), "train", pictures, "--pictures", pictures, "--steps", 1,
            relation="is the same as")
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.safetensors").write_bytes(b"a checkpoint: bytes that must survive")
    refused(cli, tmp_path, str(run), str(run / "w.safetensors"), "train", run, "--init", run / "w.safetensors",
            relation="contains")
    checkpoint = os.path.join(run, "checkpoint.safetensors")
    refused(cli, tmp_path, checkpoint, checkpoint, "export-weights", run, checkpoint, relation="is the same as")
    refused(cli, tmp_path, str(run), checkpoint, "export-weights", run, run, relation="contains")


def test_demo_into_the_bundled_samples(cli):
    folder = os.path.dirname(samples.path(samples.REDS_DAT))
    refused(cli, folder, folder, samples.path(samples.REDS_DAT), "demo", "--out", folder, relation="contains")


def test_other_url_schemes():
    """memory:// and s3:// outputs compare by scheme and normalised path, with a trailing-slash-aware prefix."""
    def apart(output, source) -> bool:
        try:
            check_apart(output, source)
            return True
        except InputError:
            return False

    assert not apart("memory://a/b/", "memory:///a/b")
    assert not apart("memory://a/b/c.zarr", "memory://a/b")
    assert not apart("s3://bucket/k", "s3://bucket/k/spikes")
    assert not apart("s3://bucket/k", "s3a://bucket/k/")
    assert apart("s3://bucket/k", "s3://bucket/k2") and apart("s3://bucket/k2", "s3://bucket/k")
    assert apart("memory://a/b", "/a/b") and apart("s3://a/b", "memory://a/b")
    assert apart("/tmp/a.zarr", "/tmp/a.zarr.partial") and apart("out", None)
    assert np.all([apart(f"memory://x/{n}", "memory://x/y") for n in ("y2", "yy", "z/y")])
