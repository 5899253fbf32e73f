"""Issue 34, points 6 and 7: outputs replaced without --overwrite, lost video chunks exported as black
frames, and numbers without an upper bound (or checked only once the output existed).

Every case is the reproduction from the issue, through the real CLI (in-process): an existing output is
refused in one line unless --overwrite, and then only if it is ours; a video store with a chunk lost is
called damaged by ``info`` and refused by ``export``, naming the frames; a number out of its bounds is
refused in one line, exit 1, before any output exists. No training step runs here.
"""

import json
import os

import numpy as np
import pytest
import torch
import zarr

from tests.reliability.test_numbers import assert_nothing_made, fingerprint
from tests.reliability.test_answers import store  # noqa: F401 - the fixture: a store with ground truth
from tests.test_bad_input import assert_refused


def user_folder(parent):
    """A folder of the user's, holding their thesis."""
    folder = parent / "userdir"
    folder.mkdir()
    (folder / "thesis.tex").write_text("my thesis")
    return folder


def assert_untouched(folder) -> None:
    assert os.listdir(folder) == ["thesis.tex"] and (folder / "thesis.tex").read_text() == "my thesis"


# --- export-weights: an existing DEST --------------------------------------------------------------

def checkpoint_at(run, step: int) -> None:
    """A training folder whose checkpoint is at ``step`` (random weights, no optimiser step: no training)."""
    from cscsr.network.model import CSCSR
    from cscsr.training.train import TrainOptions
    from cscsr.training.training_state import save_checkpoint

    run.mkdir(exist_ok=True)
    options = TrainOptions()
    torch.manual_seed(step)
    model = CSCSR(options.network())
    save_checkpoint(run / "checkpoint.safetensors", model, torch.optim.Adam(model.parameters()), step, options)


def test_export_weights_onto_an_existing_file_is_refused_unless_overwrite(cli, tmp_path):
    from cscsr.weights.weights_io import read_metadata

    run, dest = tmp_path / "run", tmp_path / "x.safetensors"
    checkpoint_at(run, 3)
    assert cli("export-weights", run, dest).exit_code == 0
    earlier = dest.read_bytes()
    checkpoint_at(run, 5)
    # before: exit 0 and the step-3 weights silently replaced
    assert_refused(cli("export-weights", run, dest), f"output {dest} already exists (pass --overwrite to replace it)")
    assert dest.read_bytes() == earlier and read_metadata(dest)["steps"] == "3"
    (tmp_path / "x.safetensors.partial").write_text("the user's own file")  # never written over nor removed
    result = cli("export-weights", run, dest, "--overwrite")
    assert result.exit_code == 0, result.stderr
    assert read_metadata(dest)["steps"] == "5"
    # written aside under a name of its own, then swapped: nothing of it left, the user's file as it was
    assert sorted(os.listdir(tmp_path)) == ["run", "x.safetensors", "x.safetensors.partial"]
    assert (tmp_path / "x.safetensors.partial").read_text() == "the user's own file"

    thesis = tmp_path / "thesis.safetensors"  # not a weights file: never replaced, --overwrite or not
    thesis.write_text("\\documentclass{article} my thesis")
    for extra in ((), ("--overwrite",)):
        assert_refused(cli("export-weights", run, thesis, *extra), f"output {thesis} already exists and is not a "
                       "weights file", "cscsr replaces only its own outputs")
        assert thesis.read_text() == "\\documentclass{article} my thesis"


def test_export_weights_portable_onto_existing_parts_is_refused_unless_overwrite(cli, tmp_path):
    run, carried = tmp_path / "run", tmp_path / "carried"
    checkpoint_at(run, 3)
    assert cli("export-weights", run, carried, "--portable").exit_code == 0
    before = fingerprint(carried)
    assert_refused(cli("export-weights", run, carried, "--portable"),
                   f"output {carried} already holds a portable checkpoint's parts (pass --overwrite to replace them)")
    assert fingerprint(carried) == before
    assert cli("export-weights", run, carried, "--portable", "--overwrite").exit_code == 0


# --- evaluate: an existing --out -------------------------------------------------------------------

def test_evaluate_onto_an_existing_out_is_refused_unless_overwrite(cli, tmp_path, store):
    from pipeline.stores.outputs import EVALUATION, mark_folder

    out = tmp_path / "ev"
    mark_folder(str(out), EVALUATION)  # an earlier evaluation
    (out / "metrics.csv").write_text("method,frame,psnr,ssim\nearlier,20,1.0,0.1\n")
    (out / "tfp.zarr").mkdir()
    before = fingerprint(out)
    # before: exit 0, tfp.zarr and metrics.csv written over the earlier ones
    assert_refused(cli("evaluate", store, "--methods", "tfp", "--out", out, "--workers", 1),
                   f"output {out} already exists (pass --overwrite to replace it)")
    assert fingerprint(out) == before

    result = cli("evaluate", store, "--methods", "tfp", "--out", out, "--workers", 1, "--overwrite")
    assert result.exit_code == 0, result.stderr
    assert "earlier" not in (out / "metrics.csv").read_text()
    assert zarr.open_group(str(out / "tfp.zarr"), mode="r").attrs["state"] == "complete"
    assert not [name for name in os.listdir(tmp_path) if name.startswith(".ev.old-")]  # the old one is gone


def test_evaluate_overwrite_never_replaces_a_folder_that_is_not_an_evaluation(cli, tmp_path, store):
    out = user_folder(tmp_path)
    assert_refused(cli("evaluate", store, "--methods", "tfp", "--out", out, "--workers", 1, "--overwrite"),
                   f"output {out} already exists and is not an evaluation")
    assert_untouched(out)


def test_evaluate_testset_onto_an_existing_out_is_refused_unless_overwrite(cli, tmp_path, store, monkeypatch):
    """evaluate-testset replaced an earlier evaluation without being asked; it now has --overwrite like evaluate.
    Only the claim is tested: no evaluation runs (the cluster is stubbed to stop the job once OUT is claimed)."""
    import shutil

    import pipeline.jobs.testset as testset
    from pipeline.stores.outputs import EVALUATION, mark_folder

    tset = tmp_path / "set"  # a test set of one item: the 100-frame store
    tset.mkdir()
    shutil.copytree(store, tset / "coffee_a0.8.zarr")
    (tset / "manifest.json").write_text(json.dumps({"items": [{"picture": "coffee", "alpha": 0.8, "seed": 1011,
                                                               "store": "coffee_a0.8.zarr"}]}))
    out = tmp_path / "ev"
    mark_folder(str(out), EVALUATION)  # an earlier evaluation
    (out / "summary.csv").write_text("method,alpha,psnr,ssim,seconds_per_image\nearlier,all,1.0,0.1,1.0\n")
    before = fingerprint(out)
    # before: exit 0, the earlier evaluation replaced
    assert_refused(cli("evaluate-testset", tset, "--methods", "tfp", "--out", out, "--workers", 1),
                   f"output {out} already exists (pass --overwrite to replace it)")
    assert fingerprint(out) == before

    user = user_folder(tmp_path)
    assert_refused(cli("evaluate-testset", tset, "--methods", "tfp", "--out", user, "--workers", 1, "--overwrite"),
                   f"output {user} already exists and is not an evaluation")
    assert_untouched(user)

    def stop(**kwargs):
        raise RuntimeError("stopped once OUT is claimed")

    monkeypatch.setattr(testset, "dask_client", stop)
    with pytest.raises(RuntimeError, match="stopped once OUT is claimed"):  # --overwrite: past the claim
        testset.evaluate_testset(str(tset), ["tfp"], str(out), workers=1, progress=False, overwrite=True)
    assert fingerprint(out) == before and not [name for name in os.listdir(tmp_path) if ".old-" in name]
    with pytest.raises(TypeError, match="--overwrite must be True or False"):
        testset.evaluate_testset(str(tset), ["tfp"], str(out), overwrite="no")


# --- a video store with a lost chunk: info says damaged, export refuses ------------------------------

def video_store(path, state: str = "complete"):
    """A 4-frame video store of 2x1 tiles (16x8 HR pixels each), every tile written and committed."""
    from pipeline.stores.video_store import TileWriter, create_video_store

    create_video_store(str(path), centres=[20, 30, 40, 50], hr_size=(16, 16), tile_hr=(16, 8), tiles=(1, 2),
                       attrs={"method": "tfp", "every": 10, "window": 41}, fps=2000.0)
    writer = TileWriter(str(path))
    rng = np.random.default_rng(0)
    for j in range(4):
        for tx in range(2):
            writer.write(j, (0, tx), (0, 8 * tx), rng.integers(1, 255, (16, 8, 3), np.uint8))
    zarr.open_group(str(path), mode="r+").attrs["state"] = state


def test_a_lost_video_chunk_is_damage_in_info_and_export_refuses(cli, tmp_path):
    path = tmp_path / "v.zarr"
    video_store(path)
    whole = json.loads(cli("info", path, "--json").stdout)
    assert whole["state"] == "complete" and whole["missing_chunks"] is None and whole["tiles_committed"] == "8 of 8"

    os.remove(path / "video" / "c" / "1" / "0" / "1" / "0")  # frame 1's right tile, still marked committed
    os.remove(path / "video" / "c" / "2" / "0" / "0" / "0")
    lost = "2 of 8 chunks of video (output frames 1..2 (spike frames 30..40))"
    info = json.loads(cli("info", path, "--json").stdout)
    assert info["state"] == f"damaged: {lost} missing (lost data)"  # before: "complete"
    assert info["missing_chunks"] == lost
    assert "damaged" in cli("info", path).stdout

    before, unchanged = set(os.listdir(tmp_path)), fingerprint(path)
    for dest in (tmp_path / "v.mp4", tmp_path / "frames"):  # before: exit 0, frames 1 and 2 partly black
        assert_refused(cli("export", path, dest), f"video store {path} is damaged: {lost} missing (lost data)",
                       "nothing exported")
        assert_nothing_made(tmp_path, before, dest)
    assert fingerprint(path) == unchanged


def test_an_unfinished_video_store_with_a_committed_tile_lost_is_damaged(cli, tmp_path):
    path = tmp_path / "v.zarr"
    video_store(path, state="writing")
    assert json.loads(cli("info", path, "--json").stdout)["state"] == "writing"
    zarr.open_group(str(path), mode="r+")["committed"][3, 0, 1] = 0  # not done yet: absent, not lost
    os.remove(path / "video" / "c" / "3" / "0" / "1" / "0")
    assert json.loads(cli("info", path, "--json").stdout)["state"] == "writing"
    os.remove(path / "video" / "c" / "0" / "0" / "0" / "0")  # done (committed) and gone: --resume would not redo it
    info = json.loads(cli("info", path, "--json").stdout)
    assert info["state"] == ("damaged: 1 of 8 chunks of video (output frame 0 (spike frame 20)) missing (lost data); "
                             "state writing")


# --- train: numbers refused in one line before OUT exists ---------------------------------------------

@pytest.mark.parametrize("args,fragment", [
    (["--learning-rate", "nan"], "--learning-rate must be >= 0, got nan"),  # was refused by Adam after OUT existed
    (["--learning-rate", "-1"], "--learning-rate must be >= 0, got -1.0"),
    (["--learning-rate", "inf"], "--learning-rate must be a finite number, got inf"),  # trained to a NaN checkpoint
    (["--learning-rate", "0"], "--learning-rate must be > 0, got 0.0: at 0 the run would ship its random initial "
                               "weights untrained"),
    (["--learning-rate", "1"], "--learning-rate must be <= 0.1 (Adam moves every weight by up to the rate"),
    (["--batch", "100000"], "batch 100000 of LR 32x32 clips needs at least 1,562.5 GiB for one step"),
    (["--lr-side", "100000"], "batch 8 of LR 100000x100000 clips needs at least"),
    (["--lr-side", "33"], "--lr-side must be even and >= 16, got 33"),
    (["--pool", "-1"], "--pool must be >= 0, got -1"),  # was truthy: a pool of no clips
    (["--pool", "1000000000"], "pool 1000000000 of LR 32x32 clips needs at least"),
    (["--batch", "0"], "--batch must be >= 1, got 0"),
    (["--validation-clips", "0"], "--validation-clips must be >= 1, got 0"),  # a mean of no clips: NaN PSNR lines
    (["--seed", "-1"], "--seed must be >= 0, got -1"),  # numpy refused it after OUT existed, the option unnamed
    (["--threads", "0"], "--threads must be >= 1, got 0"),  # was taken for "every core"
    (["--threads", "-3"], "--threads must be >= 1, got -3"),  # torch's RuntimeError
])
def test_train_numbers_refused_before_out_exists(cli, tmp_path, args, fragment):
    out = tmp_path / "run"
    assert_refused(cli("train", out, *args), fragment)
    assert not out.exists()


def test_train_refuses_an_out_that_is_not_a_training_run(cli, tmp_path):
    """A file was a raw NotADirectoryError; a folder of other things was told to pass --resume, as a run is."""
    (tmp_path / "notes.txt").write_text("mine\n")
    assert_refused(cli("train", tmp_path / "notes.txt"), "notes.txt is a file, not a training folder")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("x\n")
    assert_refused(cli("train", tmp_path / "mine"), "holds files of another kind, not a training run")
    (tmp_path / "pictures.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    assert_refused(cli("train", tmp_path / "run", "--pictures", tmp_path / "pictures.png"),
                   "picture folder " + str(tmp_path / "pictures.png") + " is a file: give the folder that holds it")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "notes.txt", "pictures.png"]
    assert os.listdir(tmp_path / "mine") == ["thesis.tex"]


def test_train_options_are_checked_in_the_python_api_too():
    from cscsr.training.train import TrainOptions
    from stages.errors import InputError

    for change, message in (({"learning_rate": float("nan")}, "learning_rate must be >= 0"),
                            ({"batch": 8.5}, "batch must be an integer, got 8.5"),
                            ({"lr_side": 32.0}, "lr_side must be an integer"),
                            ({"pool": True}, "pool must be an integer, got True")):
        with pytest.raises(InputError, match=message):
            TrainOptions(**change).check()
    TrainOptions(learning_rate=0.0, init="weights.safetensors").check()  # 0 keeps the weights it starts from


# --- simulate --frames, and --gain: refused up front ----------------------------------------------------

@pytest.fixture
def still(tmp_path):
    import imageio.v3 as iio

    path = tmp_path / "still.png"
    iio.imwrite(path, np.random.default_rng(1).integers(0, 255, (32, 32, 3), np.uint8))
    return path


@pytest.mark.parametrize("args,fragment", [
    (["--frames", 10**12], "--frames must be <= 1e+09 (13.9 hours at 20,000 fps), got 1000000000000"),  # MemoryError
    (["--frames", 10**9, "--truth-every", 1], "gives 999,999,960 truth frames, more than 33,554,432"),
    (["--truth-every", 0], "--truth-every must be >= 1, got 0"),
    (["--brightness", "1e-30"], "the recorded gain θ/α (--threshold / --brightness) must be <= 1e+06"),
])
def test_simulate_sizes_refused_up_front(cli, tmp_path, still, args, fragment):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(tmp_path)
    out = tmp_path / "sim.zarr"
    assert_refused(cli("simulate", still, out, "--motion", "static", "--workers", 1, *args), fragment)
    assert_nothing_made(tmp_path, before, out)
    assert fingerprint(tmp_path) == unchanged


GAIN_REFUSED = "--gain must be <= 1e+06 (at that gain one spike in a million frames is already full white), got 1e+30"


def test_a_gain_of_1e30_is_refused(cli, tmp_path, store):
    before, unchanged = set(os.listdir(tmp_path)), fingerprint(store)
    out, image = tmp_path / "o.zarr", tmp_path / "p.png"
    assert_refused(cli("reconstruct", store, out, "--gain", "1e30", "--workers", 1), GAIN_REFUSED)  # was white frames
    assert_refused(cli("preview", store, image, "--gain", "1e30"), GAIN_REFUSED)
    assert_nothing_made(tmp_path, before, out, image)
    assert fingerprint(store) == unchanged
