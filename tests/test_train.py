"""Training on clips simulated on the fly: reproducible clips, a falling loss, resumable checkpoints."""

import json

import numpy as np
import pytest
import torch

from cscsr.train import TrainOptions, losses, make_batch, to_tensors, train
from cscsr.training_data import TEST_PICTURES, TRAIN_PICTURES, random_clip
from cscsr.weights_io import load_model
from stages.errors import InputError

TINY = dict(batch=2, lr_side=16, checkpoint_every=2, validate_every=2, validation_clips=1)


def test_a_clip_is_reproducible_and_consistent():
    a, b = random_clip([7, 1], lr_side=16, scale=4), random_clip([7, 1], lr_side=16, scale=4)
    assert np.array_equal(a.spikes, b.spikes) and np.array_equal(a.truth, b.truth) and np.array_equal(a.flows, b.flows)
    assert a.spikes.shape == (41, 16, 16) and set(np.unique(a.spikes)) <= {0, 1}
    assert a.truth.shape == (3, 64, 64) and 0 <= a.truth.min() and a.truth.max() <= a.alpha + 1e-6
    assert a.flows.shape == (2, 2, 16, 16) and 0.6 <= a.alpha <= 1.0
    # the spikes measure the truth: the mean rate is the mean truth (in rate units), within noise
    assert abs(a.spikes.mean() - a.truth.mean()) < 0.08
    assert not set(TEST_PICTURES) & set(TRAIN_PICTURES)


def test_the_loss_falls_and_the_weights_reload(tmp_path):
    torch.manual_seed(0)
    options = TrainOptions(steps=12, learning_rate=1e-3, distinct_batches=1, **TINY)  # tiny data: one batch
    probe = to_tensors(make_batch(1, options, {}))  # the first step's batch, seen again after training

    from cscsr.config import named
    from cscsr.network import CSCSR

    before, _ = losses(CSCSR(named("lite")).train(), probe, options.flow_weight)  # same seed: the initial weights
    final = train(options, tmp_path / "run", log=lambda line: None)
    model, metadata = load_model(final)
    after, _ = losses(model, probe, options.flow_weight)
    assert after.item() < before.item()
    assert metadata["steps"] == "12" and "dead leaves" in metadata["data"]

    reloaded, _ = load_model(final)
    with torch.inference_mode():
        x = probe["spikes"]
        assert torch.equal(model(x, probe["cfa"], probe["zero_reset"], probe["scale"])["image"],
                           reloaded(x, probe["cfa"], probe["zero_reset"], probe["scale"])["image"])
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [entry["step"] for entry in log] == [2, 4, 6, 8, 10, 12] and all(e["val_psnr"] > 0 for e in log)


def test_a_resumed_run_ends_where_an_uninterrupted_one_does(tmp_path):
    options = TrainOptions(steps=4, **TINY)
    torch.manual_seed(0)
    whole = train(options, tmp_path / "whole", log=lambda line: None)
    train(TrainOptions(steps=2, **TINY), tmp_path / "split", log=lambda line: None)
    resumed = train(options, tmp_path / "split", resume=True, log=lambda line: None)
    a, _ = load_model(whole)
    b, _ = load_model(resumed)
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.allclose(x, y, atol=1e-6), name
    with pytest.raises(InputError, match="already exists"):
        train(options, tmp_path / "whole", log=lambda line: None)
    with pytest.raises(InputError, match="other options"):
        train(TrainOptions(steps=6, **{**TINY, "batch": 3}), tmp_path / "whole", resume=True, log=lambda line: None)


def test_export_weights_from_a_checkpoint(tmp_path, cli):
    train(TrainOptions(steps=2, **TINY), tmp_path / "run", log=lambda line: None)
    result = cli("export-weights", tmp_path / "run", tmp_path / "w.safetensors")
    assert result.exit_code == 0 and "after 2 steps" in result.stdout
    exported, metadata = load_model(tmp_path / "w.safetensors")
    final, _ = load_model(tmp_path / "run" / "cscsr-lite.safetensors")
    assert metadata["steps"] == "2"
    assert all(torch.equal(a, b) for a, b in zip(exported.state_dict().values(), final.state_dict().values()))
    assert cli("export-weights", tmp_path, tmp_path / "x.safetensors").exit_code == 1
