"""The network behind the pipeline's reconstructor interface (``--method cscsr``).

Loaded once per worker process by the pipeline and reused; windows of the same shape run
as one batch under ``torch.inference_mode``, on the worker's GPU when it has one, else on
one CPU thread per worker (so the bytes do not depend on the number of workers). On a GPU
the windows of several tiles of the same shape go through together (:meth:`many_tiles`).
``precision="bf16"`` runs the network under ``torch.autocast`` (bfloat16) on its device;
``backend="onnx"`` runs it on ONNX Runtime instead (CPU, fp32: :mod:`cscsr.inference.onnx_runtime`).

The data path (:meth:`NetworkReconstructor.many`): the packed spike bits go to the device (from
pinned memory on a GPU), and unpacking, the network and exposure to uint8 all run there
(:meth:`~NetworkReconstructor.device_images`, :mod:`cscsr.inference.device_steps`); only the uint8 HR image
comes back. One task at a time uses the device (a lock per loaded network): a GPU worker runs
several tasks at once (``pipeline.compute.cluster.GPU_TASKS_IN_FLIGHT``), so while one task's windows are
on the device the others read their input and write their output. ``fast_gpu`` adds, on a GPU
only, channels-last, cuDNN autotuning and ``torch.compile`` (:func:`load_reconstructor`).
"""

import contextlib
import os
import threading
from dataclasses import dataclass, field

import numpy as np
import torch

from cscsr.network.config import BACKENDS, PRECISIONS
from cscsr.network.integration import NETWORK_SCALES
from cscsr.weights.weights_io import load_model, weights_file, weights_sha256
from cscsr.inference import CACHE
from cscsr.inference.device_steps import expose_uint8, unpack_bits
from stages.reconstruction.cfa import flip_horizontally, flip_vertically, transpose
from stages.errors import InputError
from stages.reconstruction.methods import Window

HALO = 32  # LR pixels: the flow pyramid sees far; tiles agree with the whole frame closely, not exactly


@dataclass
class NetworkReconstructor:
    model: torch.nn.Module
    device: torch.device
    weights: str
    halo: int = HALO
    batch: int = 4  # windows per forward pass (frames of one tile)
    self_ensemble: bool = False  # average over the 8 flips and quarter turns, as in training (8x the time): the
    # network is not exactly equivariant, and its errors under different turns partly cancel (EDSR's "+")
    precision: str = "fp32"  # or "bf16": torch.autocast on the device
    join_tiles: bool | None = None  # tiles of one shape in one pass (many_tiles); None: on a GPU only
    backend: str = "torch"  # or "onnx": ONNX Runtime on the CPU
    weights_sha256: str | None = None  # of the file the model was loaded from: what an output records
    forward: object = None  # what runs the model: the model itself, or its torch.compile'd twin (fast_gpu)
    _device_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)

    def __post_init__(self):
        from cscsr.inference.onnx_runtime import OnnxNetwork

        self._onnx = OnnxNetwork(self.model) if self.backend == "onnx" else None
        if self.forward is None:  # not `or`: a torch.compile'd module has a __len__ that nn.Module refuses
            self.forward = self.model

    @property
    def name(self) -> str:
        """The method's name, as ``--method`` takes it."""
        return "cscsr-ensemble" if self.self_ensemble else "cscsr"

    def check(self, window: int, scale: int, cfa: str, recording: str = "this recording") -> None:
        config = self.model.config
        if cfa == "mono" and not config.mono:
            raise InputError(f"weights {self.weights} hold a colour (Bayer) CSCSR network and {recording} is mono: "
                             "use the mono weights (--weights lite-mono, the default for a mono recording), or tfp or tfi")
        if cfa != "mono" and config.mono:
            raise InputError(f"weights {self.weights} hold a mono CSCSR network and {recording} is colour (Bayer "
                             f"{cfa}): use colour weights (--weights lite or full, the defaults for a colour recording)")
        if window != config.frames:
            raise InputError(f"the CSCSR network ({self.weights}) takes windows of {config.frames} frames, "
                             f"not --window {window}")
        if scale not in NETWORK_SCALES:
            raise InputError(f"the CSCSR network upsamples by {' or '.join(map(str, NETWORK_SCALES))}, not --scale {scale}")

    def __call__(self, window: Window) -> np.ndarray:
        return self.many([window])[0]

    def many(self, windows: list[Window]) -> list[np.ndarray]:
        """Windows of one tile (same shape, CFA, reset, gain, scale) -> (s*h, s*w, 3) uint8 each.

        Only the packed bits go to the device and only uint8 comes back; the device is used by one
        call at a time (other tasks of the worker read and write meanwhile)."""
        packed = np.stack([w.packed for w in windows])  # (B, N, h, ceil(w/8)) uint8: one bit per spike
        with self._device_lock, one_thread_on_cpu(self.device), torch.inference_mode():
            images = self.device_images(self._to_device(packed), windows[0])  # (B, sH, sW, 3) uint8
            return list(self._to_host(images))

    def device_images(self, packed: torch.Tensor, window: Window) -> torch.Tensor:
        """On the device: packed bits (B, N, h, ceil(w/8)) uint8 -> exposed images (B, sH, sW, 3) uint8
        (unpack, the network, under each of the 8 orientations for the self-ensemble, exposure)."""
        spikes = unpack_bits(packed, window.width).to(getattr(self.model, "dtype", torch.float32))  # (B, N, h, w) 0/1
        with self._autocast():
            views = range(8) if self.self_ensemble else (0,)
            rate = sum(self._seen_under(k, spikes, window) for k in views) / len(views)  # (B, 3, sH, sW)
        return expose_uint8(rate.permute(0, 2, 3, 1).float(), window.gain)

    def _to_device(self, packed: np.ndarray) -> torch.Tensor:
        host = torch.from_numpy(packed)
        if self.device.type != "cuda":
            return host
        return host.pin_memory().to(self.device, non_blocking=True)  # page-locked: a DMA copy, no staging

    def _to_host(self, images: torch.Tensor) -> np.ndarray:
        if self.device.type != "cuda":
            return images.numpy()
        host = torch.empty(images.shape, dtype=images.dtype, pin_memory=True)  # torch caches pinned blocks
        host.copy_(images, non_blocking=True)
        torch.cuda.current_stream(self.device).synchronize()
        return host.numpy()

    def many_tiles(self, tiles: list[list[Window]], most: int | None = None) -> list[list[np.ndarray]]:
        """The windows of several tiles (each tile's as :meth:`many` takes them) -> each tile's images.

        On a GPU the windows of all tiles of the same shape go through the network together, at most
        ``most`` windows a pass (default: all), in tile order: fewer, fuller passes. On the CPU each
        tile is one pass, exactly as :meth:`many` runs it alone, because torch's CPU kernels can round
        differently for another batch size, and the bytes must not depend on how tasks are cut.
        """
        join = self.device.type != "cpu" if self.join_tiles is None else self.join_tiles
        if not join:
            return [self.many(windows) for windows in tiles]
        images: list[list] = [[None] * len(windows) for windows in tiles]
        by_shape: dict[tuple, list[tuple[int, int]]] = {}  # same input shape and reading -> (tile, frame) slots
        for i, windows in enumerate(tiles):
            for j, w in enumerate(windows):
                by_shape.setdefault((w.packed.shape, w.width, w.cfa, w.reset, w.gain, w.scale), []).append((i, j))
        for slots in by_shape.values():
            step = most or len(slots)
            for start in range(0, len(slots), step):
                chunk = slots[start : start + step]
                for (i, j), image in zip(chunk, self.many([tiles[i][j] for i, j in chunk])):
                    images[i][j] = image
        return images

    def _autocast(self):
        """bfloat16 autocast on the network's device for ``precision="bf16"``; nothing for fp32."""
        return precision_context(self.device.type, self.precision, self.model)

    def _seen_under(self, orientation: int, spikes: torch.Tensor, window: Window) -> torch.Tensor:
        """The network's output for the windows turned by ``orientation`` (bits as in training:
        transpose, flip left-right, flip upside down), turned back. (B, N, h, w) -> (B, 3, sH, sW)."""
        cfa = window.cfa
        if orientation & 1:
            spikes, cfa = spikes.transpose(-1, -2), transpose(cfa)
        if orientation & 2:
            spikes, cfa = spikes.flip(-1), flip_horizontally(cfa, spikes.shape[-1])
        if orientation & 4:
            spikes, cfa = spikes.flip(-2), flip_vertically(cfa, spikes.shape[-2])
        zero_reset = window.reset == "zero"
        if self._onnx is not None:
            image = self._onnx(spikes.contiguous(), cfa, zero_reset, window.scale)
        else:
            image = self.forward(spikes.contiguous(), cfa, zero_reset, window.scale)["image"]
        if orientation & 4:
            image = image.flip(-2)
        if orientation & 2:
            image = image.flip(-1)
        return image.transpose(-1, -2) if orientation & 1 else image


@contextlib.contextmanager
def one_thread_on_cpu(device: torch.device):
    """Run torch on one thread: its CPU kernels split sums differently for other thread counts, so
    the output would depend on how many workers share the machine. Parallelism comes from workers."""
    if device.type != "cpu":
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def load_reconstructor(weights: str | None, device: str | None = None, *, self_ensemble: bool = False,
                       precision: str = "fp32", channels_last: bool = False,
                       backend: str = "torch", fast_gpu: bool = False) -> NetworkReconstructor:
    """The network from ``weights`` (a file, or "lite" or "full" for the shipped ones; default lite, the
    faster on a CPU), on a GPU if there is one; with ``self_ensemble``, every window is reconstructed
    under the 8 flips and quarter turns and averaged; ``precision`` fp32, or bf16 (autocast);
    ``channels_last`` runs the convolutions on NHWC tensors (``cscsr.network.model.use_channels_last``);
    ``backend`` "onnx" runs the network on ONNX Runtime (CPU, fp32); ``fast_gpu``, on a GPU only
    (a CPU ignores it): channels-last, cuDNN autotuning and ``torch.compile`` (:func:`compiled`)."""
    check_backend(backend, precision)
    path = weights_file(weights)
    digest = weights_sha256(path)  # before loading: a file replaced during the load reads as changed
    if backend == "onnx":
        device = "cpu"
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    model, _ = load_model(path, device)
    fast = fast_gpu and device.type == "cuda"
    model = prepare_model(model, device.type, precision, channels_last=channels_last or fast)
    return NetworkReconstructor(model, device, str(path), self_ensemble=self_ensemble, precision=precision,
                                backend=backend, weights_sha256=digest, forward=compiled(model) if fast else None)


def prepare_model(model: torch.nn.Module, device_type: str, precision: str, *, channels_last: bool = False):
    """The loaded network as it runs on a ``device_type`` ("cuda" or "cpu") in ``precision``: what
    :func:`load_reconstructor` does to it after loading, a function of its own so that a CPU can prepare (and
    count, ``benchmarks/network_traffic.py``) the very network a GPU worker runs.

    The GPU path (#53): channel counts zero-padded to multiples of 8 (``cscsr.network.padding``: the same
    function), every activation channels-last (NDHWC for the 3D convolution), and for bf16 the weights
    themselves in bfloat16, so the pass runs in bf16 end to end with no casts (no autocast; sampling positions
    stay float32). On a CPU only ``channels_last`` applies: its outputs keep their bytes."""
    from cscsr.network.model import use_channels_last
    from cscsr.network.padding import pad_channels

    if device_type == "cuda":
        pad_channels(model)
        channels_last = True
        if precision == "bf16":
            model.to(torch.bfloat16)
    if channels_last:
        use_channels_last(model)
    return model


def precision_context(device_type: str, precision: str, model: torch.nn.Module | None = None):
    """What the network's forward pass runs under for ``precision`` on a ``device_type``: bfloat16 autocast for
    bf16 with float32 weights, nothing for fp32 or for a network whose weights are bf16 already (the GPU path)."""
    if precision == "fp32" or getattr(model, "dtype", torch.float32) != torch.float32:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device_type, dtype=torch.bfloat16)


COMPILE_CACHE = f"{CACHE}/torchinductor"  # torch.compile's kernels, kept between worker processes


def compiled_blocks() -> tuple:
    """The network's repeated blocks, each compiled on its own by :func:`compiled`: the colour branches' BSSR and
    temporal pixels (3 of each, 1 for mono), the trunk's ResBlocks (21 in ``full``), the flow network (4 calls)."""
    from cscsr.network.blocks import ResBlock
    from cscsr.network.bssr import BSSR
    from cscsr.network.spike_flow import SpikeFlowNet
    from cscsr.network.temporal_pixels import TemporalPixels

    return BSSR, TemporalPixels, ResBlock, SpikeFlowNet


def compiled(model: torch.nn.Module, backend: str = "inductor"):
    """``model`` with each of its repeated blocks (:func:`compiled_blocks`) under ``torch.compile`` (``dynamic=False``:
    one graph per block and tile shape) and cuDNN autotuning, for a GPU; the glue between blocks runs eagerly. A
    block's copies share one compiled graph (their weights are the graph's inputs), so ``full`` compiles a
    handful of small graphs, not one graph of 40 layers: bounded time. The first pass of each tile shape
    compiles, later passes reuse it; the compiled kernels are cached on disk (``TORCHINDUCTOR_CACHE_DIR``,
    default :data:`COMPILE_CACHE`, shared by a node's workers and by later runs), so a worker that starts
    again pays the compile once per shape per machine. Outputs stay within the network's float tolerance, not
    bit for bit: autotuning may pick other kernels in another process. Returns ``model`` (compiled in place)."""
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", os.path.expanduser(COMPILE_CACHE))
    os.environ.setdefault("TORCHINDUCTOR_FX_GRAPH_CACHE", "1")
    torch.backends.cudnn.benchmark = True
    blocks = compiled_blocks()
    for module in model.modules():
        if isinstance(module, blocks):
            module.compile(dynamic=False, backend=backend)
    return model


def check_backend(backend: str, precision: str = "fp32") -> None:
    """The backend and precision, checked together (ONNX Runtime runs the network in fp32, on the CPU)."""
    if precision not in PRECISIONS:
        raise InputError(f"--precision must be {' or '.join(PRECISIONS)}, got {precision!r}")
    if backend not in BACKENDS:
        raise InputError(f"--backend must be {' or '.join(BACKENDS)}, got {backend!r}")
    if backend == "onnx":
        if precision != "fp32":
            raise InputError(f"--backend onnx runs the network in fp32 on the CPU: --precision {precision} is for torch")
        from cscsr.inference.onnx_runtime import check_available

        check_available()
