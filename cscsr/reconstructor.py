"""The network behind the pipeline's reconstructor interface (``--method cscsr``).

Loaded once per worker process by the pipeline and reused; windows of the same shape run
as one batch under ``torch.inference_mode``, on the worker's GPU when it has one, else on
one CPU thread per worker (so the bytes do not depend on the number of workers).
"""

import contextlib
from dataclasses import dataclass

import numpy as np
import torch

from cscsr.integration import SCALES
from cscsr.weights_io import default_weights, load_model
from stages.bits import unpack_rows
from stages.cfa import flip_horizontally, flip_vertically, transpose
from stages.colour import expose
from stages.errors import InputError
from stages.reconstruct import Window

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

    @property
    def name(self) -> str:
        """The method's name, as ``--method`` takes it."""
        return "cscsr-ensemble" if self.self_ensemble else "cscsr"

    def check(self, window: int, scale: int, cfa: str) -> None:
        config = self.model.config
        if cfa == "mono":
            raise InputError("the CSCSR network is a colour (Bayer) model and this recording is mono: use tfp or tfi")
        if window != config.frames:
            raise InputError(f"the CSCSR network ({self.weights}) takes windows of {config.frames} frames, "
                             f"not --window {window}")
        if scale not in SCALES:
            raise InputError(f"the CSCSR network upsamples by {' or '.join(map(str, SCALES))}, not --scale {scale}")

    def __call__(self, window: Window) -> np.ndarray:
        return self.many([window])[0]

    def many(self, windows: list[Window]) -> list[np.ndarray]:
        """Windows of one tile (same shape, CFA, reset, gain, scale) -> (s*h, s*w, 3) uint8 each."""
        first = windows[0]
        spikes = np.stack([unpack_rows(w.packed, w.width) for w in windows])  # (B, N, h, w) uint8
        with one_thread_on_cpu(self.device), torch.inference_mode():
            x = torch.from_numpy(spikes).to(self.device, torch.float32)
            views = range(8) if self.self_ensemble else (0,)
            rate = sum(self._seen_under(k, x, first) for k in views) / len(views)  # (B, 3, sH, sW)
            rate = rate.permute(0, 2, 3, 1).float().cpu().numpy()
        return [expose(r, first.gain) for r in rate]

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
        image = self.model(spikes.contiguous(), cfa, window.reset == "zero", window.scale)["image"]
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


def load_reconstructor(weights: str | None, device: str | None = None, *,
                       self_ensemble: bool = False) -> NetworkReconstructor:
    """The network from ``weights`` (default: the shipped ``lite`` weights), on a GPU if there is one;
    with ``self_ensemble``, every window is reconstructed under the 8 flips and quarter turns and averaged."""
    path = weights or str(default_weights("lite"))
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    model, _ = load_model(path, device)
    return NetworkReconstructor(model, device, str(path), self_ensemble=self_ensemble)
