"""The network on ONNX Runtime (``--backend onnx``): PyTorch's images within float rounding, the same
bytes from any worker's export, recorded in the output and checked on ``--resume``, refused where it
does not apply. Small inputs, few kinds of input: each kind costs an export (seconds)."""

import pytest
import torch
import zarr

from cscsr.inference.onnx_runtime import OnnxNetwork
from cscsr.weights.weights_io import default_weights, load_model
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from tests.test_bad_input import assert_refused
from tests import test_gpu_workers
from tests.test_gpu_workers import psnr, video
from tests.test_network import clip
from tests.test_simulate import chunk_files

wide = test_gpu_workers.wide  # its 32x96 LR recording, a fixture
CSCSR = dict(method="cscsr", every=20, tile=48)  # 4 frames of the 32x96 recording, 2 tiles of one read shape


def test_onnx_runtime_runs_the_network_s_graph():
    model, _ = load_model(default_weights("lite"))
    spikes = clip(32, 48, batch=2)
    network, elsewhere = OnnxNetwork(model), OnnxNetwork(model)  # elsewhere: as another worker builds it
    with torch.inference_mode():  # as the reconstructor calls it
        expected = model(spikes, "gbrg", True, 4)["image"]
        image = network(spikes, "gbrg", True, 4)
        again, there = network(spikes, "gbrg", True, 4), elsewhere(spikes, "gbrg", True, 4)
    assert image.shape == expected.shape == (2, 3, 128, 192)
    torch.testing.assert_close(image, expected, rtol=1e-4, atol=1e-4)
    assert len(network.sessions) == 1  # one graph per kind of input, kept
    assert torch.equal(again, image) and torch.equal(there, image)  # the same bytes from a fresh export


def test_reconstruct_on_onnx_runtime(wide, cli, tmp_path):
    by_torch, one = (str(tmp_path / f"{name}.zarr") for name in ("torch", "onnx"))
    reconstruct(wide, by_torch, ReconstructOptions(**CSCSR), workers=1, progress=False)
    # one worker: that another worker's export gives the same bytes is tested above
    reconstruct(wide, one, ReconstructOptions(**CSCSR, backend="onnx"), workers=1, progress=False)
    group = zarr.open_group(one, mode="r")
    assert group.attrs["backend"] == "onnx" and group.attrs["state"] == "complete"
    assert zarr.open_group(by_torch, mode="r").attrs["backend"] == "torch"
    assert psnr(video(one), video(by_torch)) > 45  # the same network, rounded differently
    assert video(one).std() > 10  # real pictures, not a blank
    before = chunk_files(one)
    assert_refused(cli("reconstruct", wide, one, "--method", "cscsr", "--every", 20, "--tile", 48, "--resume",
                       "--workers", 1), "backend 'onnx' -> 'torch'")
    assert chunk_files(one) == before


@pytest.mark.parametrize("args,fragment", [
    (["--method", "cscsr", "--backend", "tensorrt"], "--backend must be torch or onnx"),
    (["--method", "tfp", "--backend", "onnx"], "--backend onnx is for the network"),
    (["--method", "cscsr", "--backend", "onnx", "--precision", "bf16"], "--backend onnx runs the network in fp32"),
])
def test_backend_refusals(cli, wide, tmp_path, args, fragment):
    out = tmp_path / "out.zarr"
    assert_refused(cli("reconstruct", wide, out, *args, "--workers", 1), fragment)
    assert not out.exists()
