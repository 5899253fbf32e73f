"""The GPU path's network (#53, item 3), checked on the CPU: channel counts padded to multiples of 8 compute the
same function, every activation is channels-last, and the bf16 pass runs in bf16 end to end with no casts."""

import copy
import hashlib
import sys
from pathlib import Path

import pytest
import torch

from cscsr.inference.reconstructor import precision_context, prepare_model
from cscsr.network.config import CONFIGS
from cscsr.network.model import CSCSR, use_channels_last
from cscsr.network.padding import pad_channels
from cscsr.weights.weights_io import default_weights, load_model
from tests.conftest import with_random_heads
from tests.test_network import clip

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _traffic import count  # noqa: E402

CONFIGURATIONS = ["lite", "full", "lite-mono", "assembled", "unguided"]


def network(name: str) -> CSCSR:
    """A randomly initialised network of configuration ``name`` whose every part shows in the output."""
    config = {"assembled": CONFIGS["lite"].ablate(motion="assembled"),
              "unguided": CONFIGS["lite"].ablate(flow_guidance=False)}.get(name) or CONFIGS[name]
    torch.manual_seed(0)
    model = CSCSR(config).eval()
    if model.motion is not None:
        for decoder in model.motion.flow.decoders:  # untrained flows are zero: give them motion to carry
            torch.nn.init.normal_(decoder.body[-1].weight, std=0.01)
    return with_random_heads(model)


def cfa_of(model) -> str:
    return "mono" if model.config.mono else "gbrg"


@pytest.mark.parametrize("name", CONFIGURATIONS)
def test_padded_channels_compute_the_same_function_in_fp32(name):
    model = network(name)
    spikes = clip(32, 32, batch=2)  # two clips: the broadcast joins split the batch
    padded = pad_channels(copy.deepcopy(model))
    convs = [m for m in padded.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Conv3d))]
    assert all(c.in_channels % 8 == 0 and c.out_channels % 8 == 0 for c in convs if c.in_channels > 1)
    assert padded.bssr[0].window.out_channels == -(-model.config.colour_features // 8) * 8
    with torch.inference_mode():
        expected = model(spikes, cfa_of(model), True, 4)
        for layout in (False, True):  # padded alone, and as the GPU path runs it (channels-last, no concatenations)
            use_channels_last(padded, layout)
            got = padded(spikes, cfa_of(model), True, 4)
            torch.testing.assert_close(got["image"], expected["image"], rtol=0, atol=1e-5)
            if expected["flows"] is not None:
                torch.testing.assert_close(got["flows"][1], expected["flows"][1], rtol=0, atol=1e-5)


@pytest.mark.parametrize("scale", [2, 4])
def test_the_gpu_path_s_heads_before_the_pixel_shuffle_and_lite_s_wider_features_compute_the_same_function(scale):
    """lite's 24 colour features leave no padded channel for the warped mask: the BSSR writes 32 (the refinement's
    first convolution split, no concatenation); each head reads the upsampling conv's output before its pixel
    shuffle."""
    model = network("lite")
    padded = use_channels_last(pad_channels(copy.deepcopy(model)))
    assert padded.bssr[0].width == 32 and padded.temporal[0].mask_slot == 24
    assert [h.out_channels for h in padded.integration.shuffled_heads] == [16, 16]
    spikes = clip(32, 32, batch=2)
    with torch.inference_mode():
        got, expected = (m(spikes, "gbrg", True, scale)["image"] for m in (padded, model))
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-5)


def test_the_shipped_weights_load_padded_for_the_gpu_and_their_files_stay_as_they_are():
    path = default_weights("lite")
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    model, _ = load_model(path)
    reference = copy.deepcopy(model)
    prepare_model(model, "cuda", "fp32")  # what a GPU worker does after loading (fp32: no bf16 weights)
    assert model.channels_last and model.bssr[0].window.out_channels == 24
    spikes = clip(32, 32)
    with torch.inference_mode():
        torch.testing.assert_close(model(spikes, "rggb", False, 4)["image"],
                                   reference(spikes, "rggb", False, 4)["image"], rtol=0, atol=1e-5)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before


@pytest.mark.parametrize("name", ["full", "lite-mono"])
def test_the_bf16_gpu_path_runs_in_bf16_with_no_casts_on_nhwc_aligned_convolutions(name):
    model = network(name)
    reference = copy.deepcopy(model)
    prepare_model(model, "cuda", "bf16")  # padded, channels-last, bf16 weights: as a GPU worker runs bf16
    assert model.dtype == torch.bfloat16
    # 16x16: the same operations as any size (benchmarks/_traffic.py extrapolates from two), and bf16 on a CPU
    # without native bfloat16 is emulated, slowly (full at 32x32: 32 s a pass on AVX2)
    spikes = clip(16, 16).to(torch.bfloat16)  # the device path unpacks the bits straight into the network's dtype
    images = []

    def run():
        with torch.inference_mode(), precision_context("cpu", "bf16", model):  # no autocast for a bf16 network
            images.append(model(spikes, cfa_of(model), False, 4)["image"])

    ops = count(run)  # the counted pass is the pass checked below: counting passes every op through as it is
    assert [(o.name, o.dtype, o.shape) for o in ops if o.cast] == []  # not even a constant's, nor float -> int
    convs = [o for o in ops if o.conv_nhwc is not None]  # every one: the base image's demosaicking included
    assert len(convs) > 50 and all(o.conv_nhwc and o.conv_aligned for o in convs), \
        [o.shape for o in convs if not (o.conv_nhwc and o.conv_aligned)]
    (image,) = images
    with torch.inference_mode():
        expected = reference(spikes.float(), cfa_of(model), False, 4)["image"]
    assert image.dtype == torch.bfloat16
    assert (image.float() - expected).abs().mean() < 2e-3  # bf16's rounding, not another function


def test_the_gpu_path_s_demosaicking_and_sample_count_are_the_same_sums_without_small_convolutions():
    """The base image's two 3-channel grouped convolutions as one of 8 channels, and the partial convolution's
    1-channel sample count as a sum pool: the same values (0/1 masks: exact sums)."""
    import torch.nn.functional as F

    from cscsr.network.base_image import aligned_kernel, demosaic
    from cscsr.network.bayer import cell_masks, colour_masks

    g = torch.Generator().manual_seed(0)
    rate = torch.rand(2, 1, 20, 28, generator=g)
    colours = colour_masks(cell_masks(["rggb", "bggr"], 20, 28))
    torch.testing.assert_close(demosaic(rate, colours, aligned_kernel().contiguous(memory_format=torch.channels_last)),
                               demosaic(rate, colours), rtol=0, atol=1e-6)
    mask = colours[:, :1]
    assert torch.equal(F.avg_pool2d(mask, 3, 1, 1, divisor_override=1), F.conv2d(mask, torch.ones(1, 1, 3, 3), padding=1))


def test_the_gpu_path_picks_the_half_resolution_channels_out_as_the_masks_and_pooling_do():
    """The joint motion's four half-resolution channels: a gather of each channel's pixel of every 2x2 cell, the
    same values as masking and 2x2 max pooling (0/1 spikes), for every pattern and mono, in a mixed batch."""
    from cscsr.network.bayer import cell_masks, pick_half, split_half
    from stages.reconstruction.cfa import BAYER_PATTERNS

    spikes = (torch.rand(len(BAYER_PATTERNS), 41, 16, 24, generator=torch.Generator().manual_seed(0)) < 0.3).float()
    for dtype in (torch.float32, torch.bfloat16):
        x = spikes.to(dtype).contiguous(memory_format=torch.channels_last)
        for cfas in (list(BAYER_PATTERNS), ["mono"] * len(BAYER_PATTERNS)):
            cells = cell_masks(cfas, 16, 24, dtype=dtype)
            assert torch.equal(pick_half(x, cells), split_half(x, cells))


@pytest.mark.parametrize("path", ["default", "gpu-bf16"])
def test_the_network_traces_as_one_graph_with_no_breaks(path):
    """torch._dynamo.explain on the whole pass: 0 graph breaks, as the CPU runs it and as the GPU path runs it."""
    import torch._dynamo

    model, _ = load_model(default_weights("lite"))
    spikes = clip(32, 32)
    if path == "gpu-bf16":
        prepare_model(model, "cuda", "bf16")
        spikes = spikes.to(torch.bfloat16)
    torch._dynamo.reset()
    with torch.inference_mode():
        explained = torch._dynamo.explain(model)(spikes, "rggb", False, 4)
    assert explained.graph_break_count == 0, [b.reason for b in explained.break_reasons]
    assert explained.graph_count == 1


def test_fast_gpu_compiles_each_repeated_block_once_per_shape():
    """--fast-gpu compiles per block (dynamic=False): full's 21 ResBlocks share one graph, and a second pass of the
    same tile shape compiles nothing (the eager backend here: the same tracing, no code generation)."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    from cscsr.inference.reconstructor import compiled

    model = prepare_model(network("full"), "cuda", "bf16")
    torch._dynamo.reset()
    counters.clear()
    compiled(model, backend="eager")
    spikes = clip(16, 16).to(torch.bfloat16)  # small: bf16 on a CPU without native bfloat16 is emulated, slowly
    with torch.inference_mode():
        first = model(spikes, "rggb", False, 4)["image"]
        graphs = counters["stats"]["unique_graphs"]
        again = model(spikes, "rggb", False, 4)["image"]
    assert 4 <= graphs <= 8, graphs  # BSSR, temporal pixels (the first colour's, then the shared plan's), ResBlock,
    assert counters["stats"]["unique_graphs"] == graphs  # the flow network: not 21 + 3 + 3 + 1
    assert torch.equal(first, again)
    torch._dynamo.reset()


def test_the_onnx_export_has_what_a_tensorrt_build_needs():
    """GridSample at opset >= 16 (the warp), a 5-D Conv (the BSSR's 3D convolution), DepthToSpace (the pixel
    shuffle); at the GPU run's tile shape in benchmarks/onnx_operators.py, here at a small one."""
    from cscsr.inference.onnx_runtime import export, operator_check

    model, _ = load_model(default_weights("lite"))
    check = operator_check(export(model.eval(), (1, 41, 32, 48), "rggb", False, 4))
    assert check["ok"], check["problems"]
    assert check["opset"] >= 16 and check["operators"]["GridSample"] == 10 and check["conv3d"] == 3
    assert check["operators"]["DepthToSpace"] == 2
