"""The network on ONNX Runtime (``--backend onnx``): on a CPU, the same network about 1.3x as fast.

PyTorch's tracing exporter fixes what Python computes from the input (the padding to a multiple
of 16, the CFA masks, the reset mode, the scale) as constants of the graph, so one graph serves
one kind of input: (batch, frames, height, width), CFA, reset and scale. The first window of each
kind exports the network (16 s for a 256x256 tile of ``lite`` on this project's CPU) and keeps the
graph on disk (``CSCSR_ONNX_CACHE``, default :data:`EXPORT_CACHE`; named by the network's weights and
every input of the export), where the node's other workers and later jobs open it (0.8 s); each
worker keeps its sessions for its later tasks. A session runs on one thread, like PyTorch on the
CPU here, so the bytes do not depend on the number of workers. Outputs agree with PyTorch's within
float rounding (about 1e-6), not bit for bit.
"""

import contextlib
import hashlib
import io
import os
import tempfile
import warnings

import numpy as np
import torch

from cscsr.inference import CACHE
from stages.errors import InputError


def check_available() -> None:
    """An InputError naming the missing package if ONNX Runtime cannot be used here."""
    for module in ("onnx", "onnxruntime"):
        try:
            __import__(module)
        except ImportError:
            raise InputError(f"--backend onnx needs the {module} package: pip install 'cscsr[onnx]'") from None


class _Image(torch.nn.Module):
    """The network with everything but the spikes fixed: (B, N, H, W) -> (B, 3, sH, sW)."""

    def __init__(self, model: torch.nn.Module, cfa: str, zero_reset: bool, scale: int):
        super().__init__()
        self.model, self.cfa, self.zero_reset, self.scale = model, cfa, zero_reset, scale

    def forward(self, spikes: torch.Tensor) -> torch.Tensor:
        return self.model(spikes, self.cfa, self.zero_reset, self.scale)["image"]


class OnnxNetwork:
    """Calls like the network's image: ``(spikes, cfa, zero_reset, scale) -> (B, 3, sH, sW)``, on ONNX Runtime."""

    def __init__(self, model: torch.nn.Module):
        check_available()
        if getattr(getattr(model, "config", None), "motion", "joint") != "joint":  # refused before any work
            raise InputError("--backend onnx runs the joint-motion network only: these weights estimate motion per "
                             "channel (--motion assembled), whose export ONNX Runtime cannot run (an Unsqueeze of "
                             "axis 4); use --backend torch")
        self.model = model
        self.sessions: dict[tuple, object] = {}
        self._weights: str | None = None  # the SHA-256 of the model's tensors, once a graph is looked up

    def __call__(self, spikes: torch.Tensor, cfa: str, zero_reset: bool, scale: int) -> torch.Tensor:
        kind = (tuple(spikes.shape), cfa, bool(zero_reset), int(scale))
        if kind not in self.sessions:
            self.sessions[kind] = self._session(*kind)
        (image,) = self.sessions[kind].run(None, {"spikes": spikes.detach().cpu().numpy().astype(np.float32)})
        return torch.from_numpy(image)

    def _session(self, shape: tuple, cfa: str, zero_reset: bool, scale: int):
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1
        options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
        options.log_severity_level = 3  # errors only
        path = self._cached(shape, cfa, zero_reset, scale)
        if path is not None and os.path.exists(path):
            try:
                return onnxruntime.InferenceSession(path, options, providers=["CPUExecutionProvider"])
            except Exception:  # noqa: BLE001 - a damaged file (a disk fault): exported again, replaced below
                pass
        graph = export(self.model, shape, cfa, zero_reset, scale)
        if path is not None:
            _keep(path, graph)
        return onnxruntime.InferenceSession(graph, options, providers=["CPUExecutionProvider"])

    def _cached(self, shape: tuple, cfa: str, zero_reset: bool, scale: int) -> str | None:
        """Where the export for this kind of input is kept: a file named by the SHA-256 of the network's weights
        and configuration, the kind, the opset and the versions of torch and this module's export; None where
        the cache folder cannot be made (a read-only home: then every worker exports, as without it)."""
        folder = os.path.expanduser(os.environ.get("CSCSR_ONNX_CACHE") or EXPORT_CACHE)
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError:
            return None
        if self._weights is None:
            digest = hashlib.sha256(repr(getattr(self.model, "config", None)).encode())
            for name, tensor in self.model.state_dict().items():
                digest.update(name.encode())
                digest.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
            self._weights = digest.hexdigest()
        key = repr((self._weights, shape, cfa, zero_reset, scale, OPSET, EXPORT_VERSION, torch.__version__))
        return os.path.join(folder, f"{hashlib.sha256(key.encode()).hexdigest()}.onnx")


EXPORT_CACHE = f"{CACHE}/onnx"  # exported graphs, kept between worker processes and jobs
EXPORT_VERSION = 1  # of export() below: a change to what it exports makes it 2, so no older file is opened


def _keep(path: str, graph: bytes) -> None:
    """Write ``graph`` to ``path`` whole or not at all (a temporary file renamed: workers exporting the same kind at
    once each write a whole file, the last one kept); a full or read-only disk keeps nothing."""
    try:
        handle, temporary = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".partial")
    except OSError:
        return
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(graph)
        os.replace(temporary, path)
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(temporary)


OPSET = 18


def export(model: torch.nn.Module, shape: tuple, cfa: str, zero_reset: bool, scale: int) -> bytes:
    """The network's graph for one kind of input, (B, N, H, W) spikes -> (B, 3, sH, sW) image, as ONNX bytes."""
    graph = io.BytesIO()
    with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tracer's notes on Python-side shapes: fixed on purpose
        example = torch.zeros(shape)
        torch.onnx.export(_Image(model, cfa, zero_reset, scale), (example,), graph, input_names=["spikes"],
                          output_names=["image"], opset_version=OPSET, dynamo=False)
    return graph.getvalue()


# what an ONNX -> TensorRT build of the network needs to find in the graph (#53): the warp as GridSample (opset 16
# or later), the BSSR's 3D convolution as a 5-D Conv, the pixel shuffle as DepthToSpace
NEEDED = {"GridSample": "the warp (grid_sample)", "DepthToSpace": "the pixel shuffle", "Conv": "the convolutions"}


def operator_check(graph: bytes) -> dict:
    """The operators of an exported graph, and what an ONNX -> TensorRT build needs of them: ``ok`` and
    ``problems`` (GridSample at opset >= 16, a 5-D Conv for the 3D convolution, DepthToSpace)."""
    import onnx

    model = onnx.load_from_string(graph)
    opset = max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
    counts: dict[str, int] = {}
    for node in model.graph.node:
        counts[node.op_type] = counts.get(node.op_type, 0) + 1
    weights = {t.name: len(t.dims) for t in model.graph.initializer}
    conv3d = sum(1 for n in model.graph.node if n.op_type == "Conv" and weights.get(n.input[1]) == 5)
    problems = [f"no {op} ({what})" for op, what in NEEDED.items() if op not in counts]
    if "GridSample" in counts and opset < 16:
        problems.append(f"GridSample needs opset 16 or later, the graph has {opset}")
    if not conv3d:
        problems.append("no 5-D Conv (the BSSR's 3D convolution)")
    return {"opset": opset, "operators": dict(sorted(counts.items())), "conv3d": conv3d, "nodes": len(model.graph.node),
            "ok": not problems, "problems": problems}
