"""The CSCSR network on its own: shapes, padding, equivariance, CFA use, alignment, training, weights."""

import numpy as np
import pytest
import torch

from cscsr.network.bayer import cell_masks, split_half
from cscsr.network.config import CONFIGS, named
from cscsr.network.model import CSCSR, pad_keeping_phase
from cscsr.inference.reconstructor import NetworkReconstructor
from cscsr.network.warp import warp
from cscsr.weights.weights_io import load_model, save_weights
from stages.capture.bits import pack_rows
from stages.errors import InputError
from stages.reconstruction.methods import Window
from stages.reconstruction.tiles import tile_grid
from tests.conftest import with_random_heads

FRAMES = 41


def clip(height: int, width: int, batch: int = 1, seed: int = 0) -> torch.Tensor:
    """Spikes of a blocky random scene: (B, 41, H, W) 0/1."""
    g = torch.Generator().manual_seed(seed)
    rate = 0.5 * torch.rand(batch, 1, height // 4 + 1, width // 4 + 1, generator=g)
    rate = rate.repeat_interleave(4, 2).repeat_interleave(4, 3)[..., :height, :width]
    return (torch.rand(batch, FRAMES, height, width, generator=g) < rate).float()


@pytest.fixture(scope="module")
def lite() -> CSCSR:
    torch.manual_seed(0)
    model = CSCSR(CONFIGS["lite"]).eval()
    for decoder in model.motion.flow.decoders:  # untrained flows start at zero: give them motion to carry
        torch.nn.init.normal_(decoder.body[-1].weight, std=0.01)
    return with_random_heads(model)


def run(model, spikes, cfa="rggb", scale=4, **kw):
    with torch.inference_mode():
        return model(spikes, cfa, scale=scale, **kw)


@pytest.mark.parametrize("scale", [2, 4])
@pytest.mark.parametrize("size", [(32, 48), (18, 26), (2, 6)])
def test_output_shapes_any_even_size(lite, scale, size):
    h, w = size
    out = run(lite, clip(h, w, batch=2), scale=scale)
    assert out["image"].shape == (2, 3, scale * h, scale * w)
    assert out["base"].shape == out["image"].shape
    assert all(f.shape == (2, 2, h, w) for f in out["flows"])
    assert torch.isfinite(out["image"]).all()


def test_padding_keeps_the_bayer_phase():
    rows = torch.arange(6, dtype=torch.float32)[:, None].expand(6, 10)[None, None]  # each pixel: its row
    columns = torch.arange(10, dtype=torch.float32)[None, :].expand(6, 10)[None, None]
    for value, axis in ((rows, -2), (columns, -1)):
        padded = pad_keeping_phase(value, 16)
        assert padded.shape[-2:] == (16, 16) and torch.equal(padded[..., :6, :10], value)
        parity = padded % 2  # the parity of the row/column each padded pixel copies ...
        position = torch.arange(16).float() % 2  # ... is the parity of where it sits
        assert torch.equal(parity[0, 0, :, 0] if axis == -2 else parity[0, 0, 0, :], position)


def shift_error(model, size: int, shift: int, margin: int, scale: int = 4) -> tuple[float, float]:
    """Mean |out(shifted input) - shifted out(input)| in the interior, and the mean correction to the base."""
    x = clip(size, size, seed=1)
    a, b = run(model, x, scale=scale), run(model, torch.roll(x, (shift, shift), (2, 3)), scale=scale)
    m, d = margin * scale, shift * scale
    error = (a["image"][..., m : -m - d, m : -m - d] - b["image"][..., m + d : -m, m + d : -m]).abs().mean()
    return error.item(), (a["image"] - a["base"]).abs().mean().item()


@pytest.mark.parametrize("scale", [2, 4])
def test_a_two_pixel_shift_shifts_the_output_by_two_s(scale):
    """Without motion (the untrained flow network's zero flow) every layer is stride 1 on the LR grid:
    away from an 8-px border the output follows a 2-px shift to within 1 % of the network's mean
    correction to its base (measured 0.3 %)."""
    torch.manual_seed(0)
    model = with_random_heads(CSCSR(CONFIGS["lite"]).eval())
    error, correction = shift_error(model, 64, 2, 8, scale)
    assert error < 0.01 * correction


def test_with_motion_the_shift_holds_on_the_flow_networks_grid(lite):
    """The flow network samples every 8 LR px (half resolution, then a 1/4 pyramid): with motion (~0.5 px
    flows), a shift by 8 px is followed to within 5 % of the correction (measured 1.7 %), a 2-px shift
    to within 30 % (measured 16 %: the flows themselves change). 32-px border: the flow network sees far."""
    error8, correction = shift_error(lite, 128, 8, 32)
    error2, _ = shift_error(lite, 128, 2, 32)
    assert run(lite, clip(64, 64, seed=1))["flows"][0].abs().mean() > 0.2  # the motion path is really exercised
    assert error8 < 0.05 * correction and error2 < 0.3 * correction and error8 < error2 / 3


def test_the_cfa_string_changes_the_output(lite):
    x = clip(32, 32)
    outputs = [run(lite, x, cfa)["image"] for cfa in ("rggb", "bggr", "grbg", "gbrg")]
    for i in range(4):
        for j in range(i + 1, 4):
            assert (outputs[i] - outputs[j]).abs().mean() > 1e-3
    with pytest.raises(InputError, match="colour .Bayer. CSCSR network and the clip is mono"):
        run(lite, x, "mono")
    with pytest.raises(InputError, match="needs a Bayer CFA"):
        run(lite, x, "rgbg")


def test_a_batch_of_clips_with_different_cfas_equals_single_clips(lite):
    x = clip(32, 32, batch=2)
    both = run(lite, x, ["rggb", "gbrg"], zero_reset=torch.tensor([True, False]))["image"]
    first = run(lite, x[:1], "rggb", zero_reset=True)["image"]
    second = run(lite, x[1:], "gbrg", zero_reset=False)["image"]
    assert torch.allclose(both, torch.cat([first, second]), atol=1e-5)


def test_split_half_picks_each_channel_without_gaps():
    spikes = torch.arange(4 * 4, dtype=torch.float32).reshape(1, 1, 4, 4) + 1
    half = split_half(spikes, cell_masks(["grbg"], 4, 4))  # (1, 4, 1, 2, 2): R, G1, G2, B
    assert torch.equal(half[0, 0, 0], spikes[0, 0, 0::2, 1::2])  # grbg: R at (0, 1)
    assert torch.equal(half[0, 1, 0], spikes[0, 0, 0::2, 0::2])  # G1 on the red row
    assert torch.equal(half[0, 2, 0], spikes[0, 0, 1::2, 1::2])  # G2 on the blue row
    assert torch.equal(half[0, 3, 0], spikes[0, 0, 1::2, 0::2])  # B at (1, 0)


def test_warping_by_a_constant_flow_moves_features_by_that_flow():
    x = torch.randn(2, 5, 20, 24)
    flow = torch.zeros(2, 2, 20, 24)
    flow[:, 0], flow[:, 1] = 3, -2  # sample 3 px to the right, 2 px up
    warped = warp(x, flow)
    assert torch.allclose(warped[..., 2:, :-3], x[..., :-2, 3:], atol=1e-5)
    half = warp(x, flow / 2)  # 1.5 px right, 1 px up: bilinear between columns
    assert torch.allclose(half[..., 1:, 1:-2], (x[..., :-1, 2:-1] + x[..., :-1, 3:]) / 2, atol=1e-5)
    mask = warp(torch.ones(2, 1, 20, 24), flow, padding="zeros")
    assert mask[..., :, -3:].max() < 1 and mask[..., 2:, :-3].min() > 0.999  # outside the frame: no samples


def test_one_training_step_lowers_the_loss():
    torch.manual_seed(3)
    model = CSCSR(CONFIGS["lite"]).train()
    x = clip(16, 16, batch=2, seed=4)
    target = torch.nn.functional.interpolate(torch.rand(2, 3, 8, 8) * 0.5, size=(64, 64), mode="bilinear")
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)

    def loss():
        return (model(x, ["rggb", "bggr"], scale=4)["image"] - target).abs().mean()

    before = loss()
    before.backward()
    optimiser.step()
    assert loss().item() < before.item() - 1e-4
    assert all(p.grad is not None for p in model.motion.parameters())  # the flow network is in the graph


def test_parameter_counts_of_the_named_configurations(cli):
    assert 0.9e6 < CSCSR(named("lite")).parameter_counts()["network"] < 1.1e6
    assert 5.3e6 < CSCSR(named("full")).parameter_counts()["network"] < 5.5e6
    result = cli("model-info", "--config", "full")
    assert result.exit_code == 0 and "5.40 M" in result.stdout
    result = cli("model-info", "--config", "lite")
    assert result.exit_code == 0 and "1.01 M" in result.stdout
    assert cli("model-info", "--config", "huge").exit_code == 1


def test_ablation_switches_build_different_networks():
    lite = named("lite")
    assembled = CSCSR(lite.ablate(motion="assembled"))
    unguided = CSCSR(lite.ablate(flow_guidance=False))
    narrow = CSCSR(lite.ablate(length=5, stride=3))
    assert unguided.motion is None and unguided.parameter_counts()["flow"] == 0
    assert narrow.config.time_points == 13 and narrow.config.centres()[6] == 20
    x = clip(16, 16)
    for model in (assembled, unguided, narrow):
        assert run(model.eval(), x)["image"].shape == (1, 3, 64, 64)
    with pytest.raises(InputError, match="middle frame"):
        lite.ablate(length=11, stride=4)
    with pytest.raises(InputError, match="unknown motion"):
        lite.ablate(motion="magic")


def test_weights_round_trip_and_clear_errors(lite, tmp_path):
    path = tmp_path / "lite.safetensors"
    save_weights(lite, path, steps="0")
    loaded, metadata = load_model(path)
    x = clip(16, 16)
    assert torch.equal(run(lite, x)["image"], run(loaded, x)["image"])
    assert metadata["steps"] == "0" and "top-left 2x2" in metadata["cfa"]
    assert b"pickle" not in path.read_bytes()[:8] and path.read_bytes()[8:9] == b"{"  # a JSON header: safetensors

    with pytest.raises(InputError, match="not found"):
        load_model(tmp_path / "missing.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"\x80\x04not a safetensors file at all")
    with pytest.raises(InputError, match="not a safetensors file"):
        load_model(tmp_path / "junk.safetensors")
    mismatched = tmp_path / "mismatched.safetensors"
    from safetensors.torch import save_file

    state = {k: v.contiguous() for k, v in lite.state_dict().items()}
    save_file(state, str(mismatched), metadata={"format": "cscsr-weights/1", "config": named("full").to_json()})
    with pytest.raises(InputError, match="does not match its configuration 'full'"):
        load_model(mismatched)
    save_file(state, str(mismatched), metadata={"format": "something-else"})
    with pytest.raises(InputError, match="not a cscsr weights file"):
        load_model(mismatched)


def test_tiles_with_the_halo_agree_with_the_whole_frame(lite):
    """The reconstructor's 32-px halo: tiled output within a grey level or so of the whole frame (the
    flow network sees further than the halo, so not exactly). Seams scale with the residual the
    network adds, so the heads are scaled to give the ~16 grey levels these bounds were measured at
    (the random network gives ~28 since its upsampler lost the ReLU after the pixel shuffle)."""
    import copy

    spikes = clip(96, 96, seed=5).numpy().astype(np.uint8)[0]
    packed = pack_rows(spikes)
    model = copy.deepcopy(lite)
    for head in model.integration.heads:
        head.weight.data.mul_(16 / 28)
    method = NetworkReconstructor(model, torch.device("cpu"), "test")
    whole = method(Window(packed, 96, "rggb", "subtract", 2.0, 2))
    tiled = np.zeros_like(whole)
    for row in tile_grid(96, 96, 32, method.halo):
        for t in row:
            part = method(Window(packed[:, t.ry0 : t.ry1, t.rx0 // 8 : -(-t.rx1 // 8)], t.rx1 - t.rx0, "rggb",
                                 "subtract", 2.0, 2))
            tiled[2 * t.y0 : 2 * t.y1, 2 * t.x0 : 2 * t.x1] = part[t.crop(2)]
    difference = np.abs(whole.astype(int) - tiled)
    # measured with ~0.5 px random flows: 97.8 % within 1 grey level, mean 0.25, max 6
    assert np.mean(difference <= 1) > 0.95 and difference.mean() < 0.5 and difference.max() <= 12


def test_the_self_ensemble_turns_with_the_recording(lite):
    """cscsr-ensemble averages the network over the 8 flips and quarter turns: a recording turned a
    quarter (spikes and CFA name together) gives the same picture turned, to rounding; the plain
    network does not (it is not exactly equivariant, which is why averaging helps)."""
    spikes = clip(32, 32, seed=3).numpy().astype(np.uint8)[0]  # (41, 32, 32)
    turned = np.ascontiguousarray(spikes.swapaxes(-1, -2)[..., ::-1])  # a quarter turn: rggb reads grbg

    def pictures(self_ensemble: bool) -> tuple[np.ndarray, np.ndarray]:
        method = NetworkReconstructor(lite, torch.device("cpu"), "test", self_ensemble=self_ensemble)
        upright = method(Window(pack_rows(spikes), 32, "rggb", "subtract", 2.0, 2))
        return np.ascontiguousarray(upright.swapaxes(0, 1)[:, ::-1]), method(
            Window(pack_rows(turned), 32, "grbg", "subtract", 2.0, 2))

    expected, got = pictures(self_ensemble=True)
    assert np.abs(expected.astype(int) - got).max() <= 1
    expected, got = pictures(self_ensemble=False)
    assert np.abs(expected.astype(int) - got).max() > 4


def test_channels_last_gives_the_same_image_and_the_default_layout_stays():
    from cscsr.network.model import use_channels_last

    torch.manual_seed(0)
    model = CSCSR(named("lite")).eval()
    spikes = (torch.rand(2, 41, 20, 34) < 0.25).float()  # not a multiple of 16: padded, then cropped
    with torch.inference_mode():
        default = model(spikes, ["rggb", "gbrg"], True, 4)
        use_channels_last(model)
        conv = next(m for m in model.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3))
        assert conv.weight.is_contiguous(memory_format=torch.channels_last) and not conv.weight.is_contiguous()
        nhwc = model(spikes, ["rggb", "gbrg"], True, 4)
        use_channels_last(model, False)
        again = model(spikes, ["rggb", "gbrg"], True, 4)
    for key in ("image", "base"):
        assert torch.allclose(nhwc[key], default[key], atol=1e-5), key
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(nhwc["flows"], default["flows"]))
    assert torch.equal(again["image"], default["image"]) and conv.weight.is_contiguous()


def test_bssr_s_windows_are_its_3d_convolution_as_one_2d_convolution():
    from cscsr.network.bssr import BSSR

    torch.manual_seed(0)
    bssr = BSSR(features=6, length=11, stride=3, time_points=11)
    spikes = clip(24, 20, batch=2)  # (2, 41, 24, 20)
    mask = (torch.rand(2, 1, 24, 20) < 0.5).float()
    with torch.no_grad():
        by_3d = bssr.window((spikes * mask)[:, None])  # (2, 6, 11, 24, 20): what the weights were trained as
        by_2d = bssr.windows(spikes * mask)
        shifted = bssr.windows(torch.roll(spikes * mask, 3, dims=1))  # one time point later: not the same
    assert by_2d.shape == by_3d.shape == (2, 6, 11, 24, 20)
    torch.testing.assert_close(by_2d, by_3d, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(shifted[:, :, 1:], by_3d[:, :, :-1], rtol=1e-5, atol=1e-5)
    assert not torch.allclose(shifted, by_3d, atol=1e-3)
