"""Clips synthesised in torch (cscsr.training.synthesis, for a GPU) agree with the numpy simulator of record."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from cscsr.training.synthesis import SensorDraws, fire, increments, prepare, synthesise
from cscsr.training.training_data import FRAMES, random_plan, run_plan
from stages.simulation import sensor as simulator
from stages.capture.bits import unpack_rows
from stages.reconstruction.cfa import BAYER_PATTERNS
from stages.simulation.camera_path import CameraPath


def plans_covering_every_case() -> list:
    """Seeds whose clips between them hold both resets, noise and none, deformed paths and all four CFA phases."""
    plans = [random_plan([5, seed], lr_side=16, scale=4) for seed in range(16)]
    kinds = {(p.sensor.reset, p.sensor.noise, bool(p.path.deformation)) for p in plans}
    assert {("zero", "realistic"), ("subtract", "none")} <= {k[:2] for k in kinds}
    assert any(k[2] for k in kinds) and {p.cfa for p in plans} == set(BAYER_PATTERNS)
    return plans


def test_torch_clips_are_the_simulators_clips():
    for plan in plans_covering_every_case():
        clip = run_plan(plan)
        made = synthesise(prepare([plan]), "cpu")
        spikes = made["spikes"][0].numpy().astype(np.uint8)
        # rendering: grid_sample where the simulator uses cv2.remap; the spikes agree on (nearly) every pixel
        assert (spikes == clip.spikes).mean() > 0.999, plan.cfa
        assert np.abs(spikes.sum(0).astype(int) - clip.spikes.sum(0)).max() <= 1
        assert np.abs(made["truth"][0].numpy() - clip.truth).max() < 1e-3
        assert np.array_equal(made["flows"][0].numpy(), clip.flows)  # the same path, the same exact flows
        assert made["cfa"] == [clip.cfa] and bool(made["zero_reset"][0]) == clip.zero_reset
        assert made["alpha"][0].item() == pytest.approx(clip.alpha) and made["scale"] == clip.scale


def test_the_sensor_fires_exactly_as_the_simulator_on_a_still_scene():
    """Same intensities in: the same increments and spikes out, bit for bit, both resets, with and without noise."""
    scene = np.random.default_rng(0).random((1, 12, 10), dtype=np.float32).repeat(FRAMES, 0)  # (41, H, W) still
    plan = random_plan([5, 0], lr_side=12, scale=4)
    for reset in simulator.RESETS:
        for noise in simulator.NOISES:
            model = simulator.SensorModel(brightness=0.7, reset=reset, noise=noise, seed=9)
            noisy = noise != "none"
            draws = SensorDraws(simulator.initial_state(model, 12, 10),
                                simulator.dark_increments(model, 12, 10) if noisy else None,
                                np.stack([np.random.default_rng([9, 2, t]).standard_normal((12, 10), np.float32)
                                          for t in range(FRAMES)]) if noisy else None)
            q = increments(torch.from_numpy(scene)[None], [replace(plan, sensor=model)], [draws], torch.device("cpu"))
            expected_q = simulator.increments(model, scene, 0)
            assert np.array_equal(q[0].numpy(), expected_q), (reset, noise)
            spikes = fire(q, torch.from_numpy(draws.state)[None], torch.tensor([reset == "zero"]))[0].numpy()
            fired = simulator.fire(expected_q, draws.state, reset=reset)
            assert np.array_equal(spikes, unpack_rows(fired.packed, 10).astype(bool)), (reset, noise)
            assert spikes.sum() == fired.spikes > 0


def test_a_still_clip_is_bit_identical_for_every_cfa_phase():
    base = random_plan([6, 1], lr_side=16, scale=4)
    still = CameraPath(base.path.height, base.path.width, FRAMES)
    for cfa in BAYER_PATTERNS:
        for reset in ("zero", "subtract"):
            plan = replace(base, path=still, cfa=cfa, sensor=replace(base.sensor, reset=reset))
            clip = run_plan(plan)
            made = synthesise(prepare([plan]), "cpu")
            assert np.array_equal(made["spikes"][0].numpy().astype(np.uint8), clip.spikes), (cfa, reset)


def test_a_batch_is_its_clips_made_one_by_one():
    plans = [random_plan([7, i], lr_side=16, scale=2) for i in range(3)]
    batch = synthesise(prepare(plans), "cpu")
    for i, plan in enumerate(plans):
        alone = synthesise(prepare([plan]), "cpu")
        for key in ("spikes", "truth", "flows", "zero_reset", "alpha"):
            assert torch.equal(batch[key][i], alone[key][0]), key
    with pytest.raises(ValueError, match="one scale"):
        prepare([plans[0], random_plan([7, 9], lr_side=16, scale=4)])
