"""bf16 at production sizes (issue #53, item 1): sampling positions stay float32 whatever the dtype, so bf16
against fp32 holds at tiles past 256 px, where a bfloat16 pixel grid stops being exact (integers above 256)."""

import numpy as np
import pytest
import skimage.data
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from cscsr.network.warp import SharedFlow, sample, sampling_plan, warp
from cscsr.weights.weights_io import default_weights, load_model
from stages.reconstruction.cfa import BAYER_PATTERNS
from stages.reconstruction.colour import expose

# bf16 against fp32 through the shipped `lite` on a tile over 256 px (uint8 after exposure); docs/gpu.md
BF16_PSNR_DB, BF16_MEAN_LEVELS = 40.0, 1.0


def exact_in_bf16(shape, seed=0):
    """Features that bf16 holds exactly (integers 0..255), and flows in quarter pixels within +-4 px."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randint(0, 256, shape, generator=g).float()
    flow = torch.randint(-16, 17, (shape[0], 2, *shape[2:]), generator=g).float() / 4
    return x, flow


@pytest.mark.parametrize("padding", ["border", "zeros"])
def test_warp_at_lr_1008_samples_the_same_positions_in_bf16_as_in_fp32(padding):
    x, flow = exact_in_bf16((1, 2, 1008, 1008))
    expected = warp(x, flow, padding)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # as the network runs under --precision bf16
        autocast = warp(x.bfloat16(), flow.bfloat16(), padding)
    assert torch.equal(autocast.float(), expected)  # the same positions, sampled in fp32: the same values
    pure = warp(x.bfloat16(), flow.bfloat16(), padding)  # bf16 features and flows, no autocast (the GPU path)
    assert pure.dtype == torch.bfloat16
    # only the output's rounding to bf16 (values below 256: at most half a unit), and grid_sample's own float32
    # rounding of its normalised positions in the reference (up to 0.013 levels here)
    torch.testing.assert_close(pure.float(), expected, rtol=0, atol=0.55)


def test_the_bf16_warp_is_grid_sample_s_bilinear_sampling():
    g = torch.Generator().manual_seed(1)
    x, flow = torch.randn(2, 3, 24, 40, generator=g), 6 * torch.randn(2, 2, 24, 40, generator=g)  # some outside
    for padding in ("border", "zeros"):
        expected = warp(x, flow, padding)
        got = sample(x, sampling_plan(flow, 24, 40, padding, torch.float32))  # the GPU path's sampler, in fp32
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-4)
        shared = SharedFlow(flow)
        assert torch.equal(shared.warp(x.bfloat16(), padding), warp(x.bfloat16(), flow, padding))  # one plan, reused
        assert torch.equal(shared.warp(x.bfloat16(), padding), warp(x.bfloat16(), flow, padding))



def test_the_compiled_sampler_picks_the_same_corners_as_the_eager_one():
    """Under torch.compile the sampler's corners come from floor and clamp, not bucketize (inductor in torch 2.11
    failed to lower bucketize over a slice on CUDA: the H200 lease of 2026-11-27); both give the same indices."""
    from cscsr.network.warp import sampling_indices

    g = torch.Generator().manual_seed(2)
    flow = 9 * torch.randn(2, 2, 12, 20, generator=g)  # many positions outside the frame
    flow[0, 0, 0, :4] = torch.tensor([-0.0, 3.0, 19.0, -1.0])  # exact integers, on and beyond the edges
    eager = sampling_indices(flow, 12, 20)
    traced = torch.compile(lambda f: sampling_indices(f, 12, 20), backend="aot_eager", dynamic=False)(flow)
    assert torch.equal(traced[0], eager[0])
    for got, expected in zip([*traced[1], *traced[2]], [*eager[1], *eager[2]]):
        assert torch.equal(got, expected)

class Bf16ConvolutionsAsOnAGpu(TorchDispatchMode):
    """bf16 convolutions computed as a GPU's are: bf16 inputs and weights (exact in float32), float32 accumulation,
    the output rounded to bf16. A CPU without native bf16 (AVX2) runs them in aten's reference loops instead, 50x
    slower than float32 (13 s a strip); everything else (the warp, the masks, the adds) still runs in bf16."""

    CONVOLUTIONS = (torch.ops.aten.conv2d, torch.ops.aten.conv3d, torch.ops.aten.convolution)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func.overloadpacket in self.CONVOLUTIONS and args[0].dtype == torch.bfloat16:
            widened = [a.float() if isinstance(a, torch.Tensor) else a for a in args]
            return func(*widened, **(kwargs or {})).to(torch.bfloat16)
        return func(*args, **(kwargs or {}))


def natural_clip(side: int, cfa: str = "grbg", frames: int = 41, seed: int = 0, width: int | None = None) -> torch.Tensor:
    """(1, 41, side, width or side) spikes of a still natural picture (chelsea, the cat) through a Bayer CFA."""
    width = width or side
    picture = skimage.data.chelsea()[:side, :width].astype(np.float32) / 255  # (300, 451, 3) -> side x width
    channel = {"r": 0, "g": 1, "b": 2}
    mosaic = np.empty((side, width), np.float32)
    for (dy, dx), c in zip([(0, 0), (0, 1), (1, 0), (1, 1)], cfa):
        mosaic[dy::2, dx::2] = picture[dy::2, dx::2, channel[c]]
    g = torch.Generator().manual_seed(seed)
    rate = 0.05 + 0.6 * torch.from_numpy(mosaic)
    return (torch.rand(1, frames, side, width, generator=g) < rate).float()


@pytest.mark.parametrize("height, width", [(288, 16), (16, 288)])
def test_a_network_pass_on_a_288_tile_in_bf16_is_within_the_stated_tolerance_of_fp32(height, width):
    """The shipped `lite` on an LR tile 288 px long (past 256: a bf16 pixel grid there was off by up to 1 px) in
    each direction, bf16 autocast against fp32, uint8 after exposure: at least 40 dB and at most 1 level on average
    (docs/gpu.md). Strips 16 px wide, a ninth of a 288x288 tile's work; convolutions as a GPU computes them in bf16
    (:class:`Bf16ConvolutionsAsOnAGpu`: the same bytes as native bf16 within a unit of bf16's last place)."""
    assert "grbg" in BAYER_PATTERNS
    model, _ = load_model(default_weights("lite"))
    spikes = natural_clip(height, width=width)
    with torch.inference_mode():
        fp32 = model(spikes, "grbg", False, 4)["image"]
        with torch.autocast("cpu", dtype=torch.bfloat16), Bf16ConvolutionsAsOnAGpu():
            bf16 = model(spikes, "grbg", False, 4)["image"]
    assert bf16.dtype == torch.bfloat16
    a, b = (expose(i[0].permute(1, 2, 0).float().numpy(), 1.5).astype(np.float64) for i in (fp32, bf16))
    assert a.std() > 20  # a picture, not a blank
    difference = np.abs(a - b)
    psnr = 10 * np.log10(255**2 / (difference**2).mean())
    assert psnr >= BF16_PSNR_DB and difference.mean() <= BF16_MEAN_LEVELS, (psnr, difference.mean())
