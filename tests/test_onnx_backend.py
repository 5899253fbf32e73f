"""The network on ONNX Runtime (``--backend onnx``): PyTorch's images within float rounding, the same
bytes from any worker's export, recorded in the output and checked on ``--resume``, refused where it
does not apply. Small inputs, few kinds of input: each kind costs an export (seconds)."""

import copy

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


def test_onnx_runtime_runs_the_network_s_graph(tmp_path, monkeypatch):
    model, _ = load_model(default_weights("lite"))
    spikes = clip(32, 48, batch=2)
    here, elsewhere = tmp_path / "here", tmp_path / "elsewhere"  # the export caches of two machines
    monkeypatch.setenv("CSCSR_ONNX_CACHE", str(here))
    network = OnnxNetwork(model)
    with torch.inference_mode():  # as the reconstructor calls it
        expected = model(spikes, "gbrg", True, 4)["image"]
        image = network(spikes, "gbrg", True, 4)
        again = network(spikes, "gbrg", True, 4)
        monkeypatch.setenv("CSCSR_ONNX_CACHE", str(elsewhere))
        there = OnnxNetwork(model)(spikes, "gbrg", True, 4)  # another machine's worker: a fresh export
    assert image.shape == expected.shape == (2, 3, 128, 192)
    torch.testing.assert_close(image, expected, rtol=1e-4, atol=1e-4)
    assert len(network.sessions) == 1  # one graph per kind of input, kept
    assert torch.equal(again, image) and torch.equal(there, image)  # the same bytes from a fresh export
    kept = sorted(here.iterdir())
    assert [path.suffix for path in kept] == [".onnx"]  # one kind, kept whole (no .partial left)
    assert kept[0].read_bytes() == next(elsewhere.iterdir()).read_bytes()


def test_a_kept_export_is_opened_not_made_again_and_only_for_its_own_network(tmp_path, monkeypatch):
    """A later worker on the machine opens the kept graph (no export); other weights or another kind of input are
    exported afresh; a damaged file is exported again and replaced."""
    from cscsr.inference import onnx_runtime

    model, _ = load_model(default_weights("lite"))
    spikes = clip(16, 16, batch=1)
    monkeypatch.setenv("CSCSR_ONNX_CACHE", str(tmp_path))
    exports = []
    real_export = onnx_runtime.export

    def counted(*args):
        exports.append(args[1:])
        return real_export(*args)

    monkeypatch.setattr(onnx_runtime, "export", counted)
    with torch.inference_mode():
        first = OnnxNetwork(model)(spikes, "rggb", False, 4)
        later = OnnxNetwork(model)(spikes, "rggb", False, 4)  # another worker process, the same machine
        assert len(exports) == 1 and torch.equal(later, first)
        (kept,) = tmp_path.iterdir()
        graph = kept.read_bytes()
        kept.write_bytes(graph[: len(graph) // 2])  # damaged
        # from here on an export is counted, not made (seconds each): what is asked of it is what is tested
        monkeypatch.setattr(onnx_runtime, "export", lambda *args: exports.append(args[1:]) or graph)
        mended = OnnxNetwork(model)(spikes, "rggb", False, 4)
        assert len(exports) == 2 and torch.equal(mended, first) and kept.read_bytes() == graph
        other = copy.deepcopy(model)
        with torch.no_grad():
            next(other.parameters()).add_(1e-3)
        OnnxNetwork(other)(spikes, "rggb", False, 4)  # other weights: not served this network's graph
        OnnxNetwork(model)(spikes, "rggb", True, 4)  # another kind of input (the reset): exported, not opened
    assert [shape_and_kind[1:] for shape_and_kind in exports] == [("rggb", False, 4)] * 3 + [("rggb", True, 4)]
    assert len(list(tmp_path.iterdir())) == 3


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


def test_weights_with_assembled_motion_are_refused_before_any_work(cli, wide, tmp_path):
    """Their export fails in ONNX Runtime (an Unsqueeze of axis 4): every task failed, a 25-line traceback, and a
    store of blank frames was left. Refused in one line, nothing made; torch runs them."""
    from cscsr.network.config import named
    from cscsr.network.model import CSCSR
    from cscsr.weights.weights_io import save_weights

    weights = tmp_path / "assembled.safetensors"
    save_weights(CSCSR(named("lite").ablate(motion="assembled")), weights)
    out = tmp_path / "out.zarr"
    assert_refused(cli("reconstruct", wide, out, "--method", "cscsr", "--backend", "onnx", "--weights", weights,
                       "--workers", 1), "--backend onnx runs the joint-motion network only")
    assert not out.exists()
