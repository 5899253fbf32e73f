"""Training on clips simulated on the fly: reproducible clips, a falling loss, resumable checkpoints."""

import json
import os
import shutil
import stat

import numpy as np
import pytest
import torch

from cscsr.network.model import CSCSR
from cscsr.training.train import TrainOptions, train
from cscsr.training.training_batches import make_batch, to_tensors
from cscsr.training.training_data import TEST_PICTURES, TRAIN_PICTURES, bundled_picture, random_clip
from cscsr.training.training_losses import losses
from cscsr.training.training_state import load_checkpoint
from cscsr.weights.weights_io import load_model
from stages.errors import InputError

TINY = dict(batch=2, lr_side=16, checkpoint_every=2, validate_every=2, validation_clips=1, warmup=2)


# Runs several tests start from, trained once for the module (each costs seconds of CPU): read them as they are, and
# copy one (``copied``) before going on from it.

@pytest.fixture(scope="module")
def two_steps(tmp_path_factory):
    """The folder of a finished run of ``TrainOptions(steps=2, **TINY)``."""
    run = tmp_path_factory.mktemp("two_steps") / "run"
    train(TrainOptions(steps=2, **TINY), run, log=lambda line: None)
    return run


@pytest.fixture(scope="module")
def four_steps(tmp_path_factory):
    """The folder of a finished, uninterrupted run of ``TrainOptions(steps=4, **TINY)``."""
    run = tmp_path_factory.mktemp("four_steps") / "run"
    train(TrainOptions(steps=4, **TINY), run, log=lambda line: None)
    return run


def copied(run, dest):
    """A copy of a shared run's folder, to go on from."""
    shutil.copytree(run, dest)
    return dest


def test_a_clip_is_reproducible_and_consistent():
    a, b = random_clip([7, 1], lr_side=16, scale=4), random_clip([7, 1], lr_side=16, scale=4)
    assert np.array_equal(a.spikes, b.spikes) and np.array_equal(a.truth, b.truth) and np.array_equal(a.flows, b.flows)
    assert a.spikes.shape == (41, 16, 16) and set(np.unique(a.spikes)) <= {0, 1}
    assert a.truth.shape == (3, 64, 64) and 0 <= a.truth.min() and a.truth.max() <= a.alpha + 1e-6
    assert a.flows.shape == (2, 2, 16, 16) and 0.6 <= a.alpha <= 1.0
    # the spikes measure the truth: the mean rate is the mean truth (in rate units), within noise
    assert abs(a.spikes.mean() - a.truth.mean()) < 0.08
    assert not set(TEST_PICTURES) & set(TRAIN_PICTURES)


def test_every_training_picture_is_installed_as_colour():
    pictures = {name: bundled_picture(name) for name in TRAIN_PICTURES}
    for name, picture in pictures.items():
        assert picture.ndim == 3 and picture.shape[2] == 3, name
        assert picture.dtype == np.float32 and 0 <= picture.min() and picture.max() <= 1, name
    # the stereo pair is two viewpoints of one scene, not one picture twice
    left, right = pictures["motorcycle_left"], pictures["motorcycle_right"]
    assert left.shape == right.shape and 0.02 < np.abs(left - right).mean() < 0.3


def test_the_loss_falls_and_the_weights_reload(tmp_path):
    torch.manual_seed(0)
    options = TrainOptions(steps=8, learning_rate=1e-3, distinct_batches=1,  # tiny data: one batch
                           **{**TINY, "checkpoint_every": 4, "validate_every": 4})
    probe = to_tensors(make_batch(1, options, {}))  # the first step's batch, seen again after training

    from cscsr.network.config import named
    from cscsr.network.model import CSCSR

    before, _ = losses(CSCSR(named("lite")).train(), probe, options.flow_weight)  # same seed: the initial weights
    final = train(options, tmp_path / "run", log=lambda line: None)
    model, metadata = load_model(final)
    after, _ = losses(model, probe, options.flow_weight)
    assert after.item() < before.item()
    assert metadata["steps"] == "8" and "dead leaves" in metadata["data"]

    reloaded, _ = load_model(final)
    with torch.inference_mode():
        x = probe["spikes"]
        assert torch.equal(model(x, probe["cfa"], probe["zero_reset"], probe["scale"])["image"],
                           reloaded(x, probe["cfa"], probe["zero_reset"], probe["scale"])["image"])
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [entry["step"] for entry in log] == [4, 8] and all(e["val_psnr"] > 0 for e in log)


def test_a_resumed_run_ends_where_an_uninterrupted_one_does(tmp_path, two_steps, four_steps):
    options = TrainOptions(steps=4, **TINY)
    whole = four_steps / "cscsr-lite.safetensors"  # 4 steps uninterrupted; 2 steps, then resumed to 4:
    resumed = train(options, copied(two_steps, tmp_path / "split"), resume=True, log=lambda line: None)
    a, _ = load_model(whole)
    b, _ = load_model(resumed)
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.allclose(x, y, atol=1e-6), name
    with pytest.raises(InputError, match="already exists"):
        train(options, tmp_path / "split", log=lambda line: None)
    with pytest.raises(InputError, match="other options"):
        train(TrainOptions(steps=6, **{**TINY, "batch": 3}), tmp_path / "split", resume=True, log=lambda line: None)
    said = []  # a resume to fewer steps than were run: it said nothing, simulated a pool for no step, and wrote
    before = resumed.read_bytes()  # its weights file again, recording the options of the call that trained nothing
    train(TrainOptions(steps=2, **{**TINY, "precision": "bf16"}), tmp_path / "split", resume=True, log=said.append)
    assert said == ["already at step 4 of --steps 2: nothing to train (give more --steps to go on)"]
    assert resumed.read_bytes() == before
    mask = os.umask(0)
    os.umask(mask)
    for written in (resumed, tmp_path / "split" / "checkpoint.safetensors"):  # safetensors wrote them 0600
        assert stat.S_IMODE(written.stat().st_mode) == 0o666 & ~mask, written


def test_a_resumed_run_may_anneal_with_a_shorter_decay(tmp_path, four_steps):
    """--decay-every may change on --resume: the rate drops at once to its place on the new schedule."""
    copied(four_steps, tmp_path / "run")  # 4 steps on the 7,500-step decay
    train(TrainOptions(steps=6, decay_every=2, **TINY), tmp_path / "run", resume=True, log=lambda line: None)
    rates = [json.loads(line)["lr"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    base = TrainOptions().learning_rate
    assert rates == pytest.approx([base, base, base * 0.9**3])  # after steps 2, 4 (7,500-step decay), then 6 (2-step)
    with pytest.raises(InputError, match="decay_every must be >= 1"):
        TrainOptions(decay_every=0).check()


def test_a_resumed_run_may_grow_its_pool_but_not_change_its_crops(two_steps):
    """--pool may grow on --resume (fresh clips for a run that has seen its pool many times); --lr-side may not."""
    checkpoint = two_steps / "checkpoint.safetensors"

    def resume(options):
        model = CSCSR(options.network())
        return load_checkpoint(checkpoint, model, torch.optim.Adam(model.parameters()), options)

    assert resume(TrainOptions(steps=4, pool=16, **TINY)) == 2
    with pytest.raises(InputError, match=r"other options \(lr_side\)"):
        resume(TrainOptions(steps=4, **{**TINY, "lr_side": 18}))


def test_a_run_may_start_from_weights_of_the_same_network(tmp_path, two_steps):
    """--init fine-tunes (e.g. on larger crops): the run starts from the file's weights; another network is refused."""
    first = two_steps / "cscsr-lite.safetensors"
    frozen = TrainOptions(steps=2, learning_rate=0.0, init=str(first), seed=5, **{**TINY, "lr_side": 18})
    model, metadata = load_model(train(frozen, tmp_path / "tuned", log=lambda line: None))
    start, _ = load_model(first)
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), start.state_dict().values()))
    assert metadata["initialised_from"] == f"{first} (2 steps)"
    assert (metadata["steps"], metadata["run_steps"]) == ("4", "2")  # every step the weights had, and this run's
    moved, _ = load_model(train(TrainOptions(steps=2, init=str(first), seed=5, **TINY), tmp_path / "moved",
                                log=lambda line: None))
    assert not all(torch.equal(a, b) for a, b in zip(moved.state_dict().values(), start.state_dict().values()))
    other = TrainOptions(steps=2, motion="assembled", init=str(first), **TINY)
    with pytest.raises(InputError, match="cannot start from .* it holds CSCSR 'lite'"):
        train(other, tmp_path / "other", log=lambda line: None)
    with pytest.raises(InputError, match="none.safetensors not found"):
        train(TrainOptions(steps=2, init=str(tmp_path / "none.safetensors"), **TINY), tmp_path / "none",
              log=lambda line: None)
    assert not (tmp_path / "other").exists() and not (tmp_path / "none").exists()


def test_an_ablation_run_trains_and_records_the_switched_network(tmp_path, cli):
    """--motion assembled / --no-flow-guidance train that network; the weights rebuild it; resume keeps it."""
    result = cli("train", tmp_path / "noflow", "--steps", "2", "--batch", "2", "--lr-side", "16",
                 "--validate-every", "2", "--validation-clips", "1", "--warmup", "2", "--no-flow-guidance",
                 "--threads", "1")
    assert result.exit_code == 0, result.stdout
    model, metadata = load_model(tmp_path / "noflow" / "cscsr-lite.safetensors")
    assert model.config.flow_guidance is False and model.motion is None
    assert json.loads(metadata["options"])["flow_guidance"] is False
    assert metadata["command"] == (f"cscsr train {tmp_path / 'noflow'} --steps 2 --batch 2 --lr-side 16 --warmup 2 "
                                   "--no-flow-guidance --validate-every 2 --validation-clips 1 "
                                   "--threads 1")  # options in --help's order
    options = TrainOptions(steps=2, motion="assembled", **TINY)
    model, _ = load_model(train(options, tmp_path / "assembled", log=lambda line: None))
    assert model.config.motion == "assembled" and model.config.flow_guidance
    with pytest.raises(InputError, match=r"other options \(motion\)"):
        train(TrainOptions(steps=4, **TINY), tmp_path / "assembled", resume=True, log=lambda line: None)
    assert cli("train", tmp_path / "bad", "--motion", "sideways").exit_code == 1 and not (tmp_path / "bad").exists()


def test_export_weights_from_a_checkpoint(tmp_path, cli, two_steps):
    result = cli("export-weights", two_steps, tmp_path / "w.safetensors")
    assert result.exit_code == 0 and "after 2 steps" in result.stdout
    exported, metadata = load_model(tmp_path / "w.safetensors")
    final, _ = load_model(two_steps / "cscsr-lite.safetensors")
    assert metadata["steps"] == "2"
    assert all(torch.equal(a, b) for a, b in zip(exported.state_dict().values(), final.state_dict().values()))
    assert cli("export-weights", tmp_path, tmp_path / "x.safetensors").exit_code == 1
    result = cli("export-weights", two_steps, tmp_path / "carried", "--portable", "--half")
    assert result.exit_code == 0 and "after 2 steps in 1 part" in result.stdout
    assert [p.name for p in (tmp_path / "carried").iterdir()] == ["checkpoint.part-1-of-1.safetensors"]


def warp_error(clip, flows) -> float:
    """How well ``flows`` (middle -> frame 11) carry the spikes around frame 11 onto those around frame 20."""
    from cscsr.network.warp import warp

    spikes = torch.from_numpy(clip.spikes).float()
    middle, early = spikes[16:25].mean(0)[None, None], spikes[7:16].mean(0)[None, None]
    moved = warp(early, torch.from_numpy(np.ascontiguousarray(flows[0]))[None])
    return float((moved - middle).abs()[..., 4:-4, 4:-4].mean())


def test_a_reoriented_clip_is_the_clip_of_the_turned_scene():
    from cscsr.training.training_data import batch_arrays, dead_leaves, reoriented, simulate_clip
    from cscsr.training.training_losses import psnr_intensity

    rng = np.random.default_rng(5)
    grey = np.repeat(dead_leaves(rng, 4 * 48).mean(2, keepdims=True), 3, 2)  # grey: the mosaic is one image
    clip = simulate_clip(grey, rng, lr_side=32, scale=4, alpha=0.9, cfa="rggb", zero_reset=False, noise="none",
                         speed=0.15)
    colourful = random_clip([3, 1], lr_side=16, scale=4)
    model_base = None
    for orientation in range(8):
        turned = reoriented(clip, orientation)
        # the flows still say where the picture went: better than no flow, negated or with x and y swapped
        right = warp_error(turned, turned.flows)
        assert right == pytest.approx(warp_error(clip, clip.flows), abs=1e-6)
        assert right < 0.9 * min(warp_error(turned, 0 * turned.flows), warp_error(turned, -turned.flows),
                                 warp_error(turned, turned.flows[:, ::-1]))
        # the CFA name follows the turn: the demosaicked base image is exactly as good
        probe = to_tensors(batch_arrays([reoriented(colourful, orientation)]))
        from cscsr.network.model import CSCSR
        from cscsr.network.config import named

        model_base = model_base or CSCSR(named("lite")).eval()
        with torch.inference_mode():
            base = model_base(probe["spikes"], probe["cfa"], probe["zero_reset"], 4)["base"]
        score = psnr_intensity(base, probe["truth"], probe["alpha"])
        reference = score if orientation == 0 else reference
        assert score == pytest.approx(reference, abs=1e-4)
    assert reoriented(reoriented(colourful, 1), 1).cfa == colourful.cfa
    assert np.array_equal(reoriented(reoriented(colourful, 6), 6).truth, colourful.truth)


def test_a_pool_is_reproducible_and_batches_come_from_it():
    from cscsr.training.training_batches import clip_pool

    options = TrainOptions(pool=3, scale4_share=1.0, **TINY)
    pool = clip_pool(options)  # simulated in worker processes
    assert len(pool[4]) == 3 and not pool[2]
    # clip i is the clip of seed [seed, 997, i], simulated here again: a resumed run rebuilds the same pool
    again = [random_clip([options.seed, 997, i], lr_side=options.lr_side, scale=4) for i in range(3)]
    assert all(np.array_equal(a.spikes, b.spikes) and np.array_equal(a.truth, b.truth) for a, b in zip(pool[4], again))
    first, repeat = make_batch(5, options, {}, pool), make_batch(5, options, {}, pool)
    assert np.array_equal(first["spikes"], repeat["spikes"]) and first["cfa"] == repeat["cfa"]
    sums = {float(c.truth.sum()) for c in pool[4]}
    assert all(round(float(t.sum()), 2) in {round(s, 2) for s in sums} for t in first["truth"])  # turned, not new


# --- the GPU path, tested on the CPU ---------------------------------------------------------

def test_on_device_synthesis_trains_on_the_same_clips():
    numpy_batch = to_tensors(make_batch(3, TrainOptions(**TINY), {}))
    torch_batch = to_tensors(make_batch(3, TrainOptions(synthesis="torch", **TINY), {}))
    assert (numpy_batch["spikes"] == torch_batch["spikes"]).float().mean() > 0.999
    assert torch.allclose(numpy_batch["truth"], torch_batch["truth"], atol=1e-3)
    assert torch.equal(numpy_batch["flows"], torch_batch["flows"]) and numpy_batch["cfa"] == torch_batch["cfa"]


def test_a_time_budget_stops_cleanly_and_resume_goes_on(tmp_path):
    """A budget too short for a second step: the run stops after one, checkpointed, validated, with weights."""
    lines = []
    options = TrainOptions(steps=3, time_budget=1.0, synthesis="torch", precision="bf16", **TINY)
    final = train(options, tmp_path / "run", log=lines.append)
    assert any("stopped at step 1 of 3" in line for line in lines)
    assert load_model(final)[1]["steps"] == "1"
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [e["step"] for e in log] == [1]
    # the device, precision, synthesis and budget may change on --resume: the run moves between machines
    final = train(TrainOptions(steps=3, **TINY), tmp_path / "run", resume=True, log=lines.append)
    assert load_model(final)[1]["steps"] == "3"


def test_training_pictures_come_from_folders_but_never_the_test_pictures(tmp_path, cli):
    import imageio.v3 as iio
    from skimage import data

    pictures = tmp_path / "pictures"
    (pictures / "sequence").mkdir(parents=True)
    iio.imwrite(pictures / "rocket.png", data.rocket())
    iio.imwrite(pictures / "sequence" / "frame_1.jpg", data.stereo_motorcycle()[0])
    final = train(TrainOptions(steps=2, pictures=str(pictures), dead_leaves=0.0, **TINY), tmp_path / "run",
                  log=lambda line: None)
    assert str(pictures) in load_model(final)[1]["data"]

    import cv2

    leak = tmp_path / "leak"
    leak.mkdir()
    astronaut = cv2.resize(data.astronaut(), (300, 300), interpolation=cv2.INTER_AREA)  # resized, re-encoded
    iio.imwrite(leak / "a.jpg", astronaut)
    result = cli("train", tmp_path / "refused", "--pictures", pictures, "--pictures", leak, "--steps", "2")
    assert result.exit_code != 0 and "test picture 'astronaut'" in result.stderr
    assert not (tmp_path / "refused").exists()  # refused before any output
    result = cli("train", tmp_path / "refused", "--pictures", tmp_path / "nowhere")
    assert result.exit_code != 0 and "does not exist" in result.stderr


@pytest.mark.parametrize("change, message", [
    ({"precision": "fp16"}, "unknown precision"), ({"device": "tpu"}, "unknown device"),
    ({"synthesis": "jax"}, "unknown synthesis"), ({"time_budget": float("nan")}, "time_budget"),
    ({"dead_leaves": 1.5}, "dead_leaves"), ({"pool": 4, "synthesis": "torch"}, "--pool"),
])
def test_bad_gpu_options_are_refused(change, message):
    with pytest.raises(InputError, match=message):
        TrainOptions(**{**TINY, **change}).check()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without a GPU")
def test_cuda_without_a_gpu_is_refused(tmp_path):
    with pytest.raises(InputError, match="no CUDA GPU"):
        train(TrainOptions(device="cuda", **TINY), tmp_path / "run", log=lambda line: None)
    assert not (tmp_path / "run").exists()


def test_half_weights_are_half_the_size_and_load_as_float32(tmp_path):
    from cscsr.network.config import named
    from cscsr.weights.weights_io import read_metadata, save_weights

    model = CSCSR(named("lite"))
    save_weights(model, tmp_path / "full.safetensors")
    save_weights(model, tmp_path / "half.safetensors", storage="float16")
    assert (tmp_path / "half.safetensors").stat().st_size < 0.52 * (tmp_path / "full.safetensors").stat().st_size
    assert read_metadata(tmp_path / "half.safetensors")["storage"] == "float16"
    loaded, _ = load_model(tmp_path / "half.safetensors")
    for (name, a), (_, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert b.dtype == a.dtype and torch.equal(b, a.half().float()), name
    with torch.no_grad():
        next(model.parameters()).view(-1)[0] = 1e6  # beyond float16's range
    with pytest.raises(InputError, match="does not fit in float16"):
        save_weights(model, tmp_path / "overflow.safetensors", storage="float16")


# --- a portable checkpoint: carried back from a GPU lease, continued on a fresh machine ----------

def test_a_portable_checkpoint_in_small_parts_resumes_close_to_the_exact_one(tmp_path, two_steps):
    from cscsr.weights.portable_checkpoint import portable_parts
    from cscsr.training.train import export_portable
    from cscsr.training.training_state import read_checkpoint

    copied(two_steps, tmp_path / "run")  # 2 steps, to be carried and resumed
    at_two, _ = read_checkpoint(tmp_path / "run" / "checkpoint.safetensors")
    limit = 2**20  # 1 MiB parts, for the test: lite's 10.5 MB of checkpoint needs at least 11
    step, parts = export_portable(tmp_path / "run", tmp_path / "carried", part_bytes=limit)
    assert step == 2 and len(parts) >= 11 and parts == portable_parts(tmp_path / "carried")
    assert all(0.5 * limit < p.stat().st_size <= limit for p in parts[:-1]) and parts[-1].stat().st_size <= limit
    total = sum(p.stat().st_size for p in parts)
    exact_bytes = (tmp_path / "run" / "checkpoint.safetensors").stat().st_size
    assert total == pytest.approx(exact_bytes * (4 + 2 + 2) / (4 + 4 + 4), rel=0.01)  # moments in bfloat16
    _, halves = export_portable(tmp_path / "run", tmp_path / "halves", weights="float16")
    assert sum(p.stat().st_size for p in halves) == pytest.approx(exact_bytes / 2, rel=0.01)  # and float16 weights
    with pytest.raises(InputError, match="alone .* does not fit"):
        export_portable(tmp_path / "run", tmp_path / "tiny", part_bytes=2**14)

    # a fresh machine: the parts alone, then --resume; the exact run goes on beside it
    shutil.copytree(tmp_path / "carried", tmp_path / "fresh")
    lines = []
    portable = load_model(train(TrainOptions(steps=4, **TINY), tmp_path / "fresh", resume=True, log=lines.append))[0]
    exact = load_model(train(TrainOptions(steps=4, **TINY), tmp_path / "run", resume=True, log=lambda line: None))[0]
    assert any("resumed at step 2 from the portable checkpoint" in line for line in lines)
    steps = [json.loads(line)["step"] for line in (tmp_path / "fresh" / "log.jsonl").read_text().splitlines()]
    assert steps == [4]
    # close: the difference rounding made is a small fraction of what the two further steps moved
    moved = sum((w - at_two[f"model.{k}"]).abs().sum().item() for k, w in exact.state_dict().items())
    apart = sum((w - portable.state_dict()[k]).abs().sum().item() for k, w in exact.state_dict().items())
    assert 0 < apart < 0.01 * moved  # measured: 0.0009

    parts[3].unlink()  # a part lost on the way is refused, before any output
    (tmp_path / "lost").mkdir()
    for p in parts:
        if p.exists():
            shutil.copy(p, tmp_path / "lost")
    with pytest.raises(InputError, match="incomplete or mixed: missing checkpoint.part-4-of"):
        train(TrainOptions(steps=4, **TINY), tmp_path / "lost", resume=True, log=lambda line: None)
    assert not (tmp_path / "lost" / "log.jsonl").exists()


def test_channels_last_trains_the_same_network_within_rounding(tmp_path, two_steps):
    default = load_model(two_steps / "cscsr-lite.safetensors")[0]
    nhwc = load_model(train(TrainOptions(steps=2, channels_last=True, **TINY), tmp_path / "nhwc",
                            log=lambda line: None))[0]
    # Adam moves a weight by up to the learning rate a step whatever its gradient's size: where a gradient is near
    # zero, rounding (NHWC kernels sum in another order; which, depends on the CPU and its threads) can flip its
    # sign, so such a weight may differ by up to 2 steps x the rate; every other weight agrees within rounding
    bound = 2 * TrainOptions().learning_rate
    for (name, a), (_, b) in zip(default.state_dict().items(), nhwc.state_dict().items()):
        gap = (a.float() - b.float()).abs()
        assert gap.max() <= bound and (gap > 1e-5).float().mean() <= 1e-3, (name, gap.max().item())


def test_an_interrupted_checkpoint_save_leaves_no_partial_file(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM while a checkpoint is written: the interrupt goes on, and no half-written file stays."""
    import safetensors.torch

    from cscsr.network.config import named
    from cscsr.network.model import CSCSR
    from cscsr.training.training_state import save_checkpoint

    def interrupted(tensors, filename, metadata=None):
        open(filename, "wb").write(b"half a checkpoint")
        raise KeyboardInterrupt

    monkeypatch.setattr(safetensors.torch, "save_file", interrupted)
    model = CSCSR(named("lite"))
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path / "checkpoint.safetensors", model, torch.optim.Adam(model.parameters()), 1,
                        TrainOptions(**TINY))
    assert list(tmp_path.iterdir()) == []
