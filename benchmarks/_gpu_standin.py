"""The stand-in network of ``gpu_pipeline.py --stand-in S``: it only sleeps, and says so.

A measuring instrument, never a product path: :class:`StandInDevice` takes the network's place in
the GPU worker (:func:`install_stand_in`, through :func:`stand_in_plugin`) with the same input and
output shapes; a pass of n windows sleeps n * S seconds, leaving the CPU free as a GPU kernel does,
and returns a fixed, natural-looking HR picture made once from the recording
(:func:`stand_in_picture`), so that compressing it costs what real output costs. Each pass is
logged, for the device's busy share (:func:`stand_in_passes`).
"""

import threading
import time
from pathlib import Path

import numpy as np
from _gpu_recording import SCALE, WINDOW


def stand_in_picture(store_url: str) -> Path:
    """The stand-in's output picture, made once per recording and saved beside it: the first window's TFP
    image (``stages.reconstruction.tfp.tfp_image``) at the store's gain, enlarged x4 to HR, (4H, 4W, 3) uint8."""
    path = Path(store_url).parent / "stand_in_picture.npy"
    if not path.exists():
        from pipeline.stores.spike_store import open_spike_store
        from stages.reconstruction.tfp import tfp_image

        store = open_spike_store(store_url)
        meta = store.meta
        image, _ = tfp_image(store.read(0, WINDOW), width=meta.width, cfa=meta.cfa, gain=meta.gain, scale=SCALE,
                             reset=meta.reset)
        np.save(path, image)
    return path


class StandInDevice:
    """A measuring instrument standing in for the network on a GPU (``--stand-in S``), never a product path.

    Same input and output shapes as what it replaces; a pass of n windows sleeps n * S seconds without
    using the CPU (as a GPU kernel leaves it free) and returns the fixed picture (:func:`stand_in_picture`,
    cropped to the tile's HR size), from buffers made once per shape, so that the output costs the CPU
    what the device's output costs it: nothing until the pipeline compresses and writes it.

    :meth:`device_images` replaces ``NetworkReconstructor.device_images`` (the device-side path: packed
    bits in, uint8 HR images out); :meth:`model` replaces the model of the old path ({"image": float
    rates}, exposed to the picture by the store's gain). Each pass is logged (start, stop, windows)."""

    def __init__(self, seconds: float, picture: str):
        self.seconds = seconds
        self.picture_path = picture
        self._picture = None
        self._buffers = {}
        self._lock = threading.RLock()  # _buffer makes a buffer from picture() while holding it
        self.passes = []  # (perf_counter at start, at stop, windows)

    def picture(self) -> np.ndarray:
        with self._lock:
            if self._picture is None:
                self._picture = np.load(self.picture_path)
            return self._picture

    def _sleep(self, windows: int) -> None:
        start = time.perf_counter()
        time.sleep(windows * self.seconds)
        self.passes.append((start, time.perf_counter(), windows))

    def _buffer(self, key, make):
        with self._lock:
            if key not in self._buffers:
                self._buffers[key] = make()
            return self._buffers[key]

    def device_images(self, packed, window):
        """(B, N, h, ceil(w/8)) uint8 tensor -> (B, s*h, s*w, 3) uint8 tensor, after B * S seconds."""
        import torch

        batch, height, width = packed.shape[0], packed.shape[2] * window.scale, window.width * window.scale
        self._sleep(batch)
        return self._buffer(("uint8", batch, height, width), lambda: torch.from_numpy(
            np.ascontiguousarray(np.broadcast_to(self.picture()[:height, :width], (batch, height, width, 3)))))

    def model(self, spikes, cfa, zero_reset, scale, gain):
        """(B, N, h, w) float tensor -> {"image": (B, 3, s*h, s*w) float32 rates}, after B * S seconds."""
        import torch

        batch, height, width = spikes.shape[0], spikes.shape[-2] * scale, spikes.shape[-1] * scale
        self._sleep(batch)

        def rates():
            rgb = self.picture()[:height, :width].astype(np.float32) / np.float32(255 * gain)
            return torch.from_numpy(np.ascontiguousarray(np.broadcast_to(rgb.transpose(2, 0, 1),
                                                                         (batch, 3, height, width))))

        return {"image": self._buffer(("rates", batch, height, width, gain), rates)}


class _OldModelStandIn:
    """The old path's model (called as ``model(x, cfa, zero_reset, scale)``) answered by the stand-in;
    every other attribute (``config``, ...) is the real model's."""

    def __init__(self, real, stand_in: StandInDevice, gain: float):
        self._real, self._stand_in, self._gain = real, stand_in, gain

    def __call__(self, spikes, cfa, zero_reset=False, scale=SCALE):
        return self._stand_in.model(spikes, cfa, zero_reset, scale, self._gain)

    def __getattr__(self, name):
        return getattr(self._real, name)


def install_stand_in(seconds: float, picture: str, gain: float) -> str:
    """In this process: wrap ``pipeline.jobs.reconstruct_tasks.reconstructor`` so that every reconstructor it returns
    runs :class:`StandInDevice` instead of the network; -> which path the reconstructor has: "device-side"
    (it has ``device_images``) or "old". Idempotent."""
    import pipeline.jobs.reconstruct_tasks as reconstruct_module
    from cscsr.inference.reconstructor import NetworkReconstructor

    path = "device-side" if hasattr(NetworkReconstructor, "device_images") else "old"
    original = getattr(reconstruct_module.reconstructor, "measured_original", reconstruct_module.reconstructor)
    stand_in = StandInDevice(seconds, picture)

    def reconstructor(*args, **kwargs):
        method = original(*args, **kwargs)
        if isinstance(method, NetworkReconstructor) and getattr(method, "stand_in", None) is None:
            method.stand_in = stand_in
            if path == "device-side":
                method.device_images = stand_in.device_images
            else:
                method.model = _OldModelStandIn(method.model, stand_in, gain)
        return method

    reconstructor.measured_original = original
    reconstructor.stand_in = stand_in
    reconstruct_module.reconstructor = reconstructor
    return path


def stand_in_passes() -> list:
    """In a worker: the stand-in's passes so far, (start, stop, windows) on this process's perf_counter."""
    import pipeline.jobs.reconstruct_tasks as reconstruct_module

    return list(reconstruct_module.reconstructor.stand_in.passes)


def stand_in_plugin(seconds: float, picture: str, gain: float):
    """A WorkerPlugin installing the stand-in (:func:`install_stand_in`) in every worker, one that joins later too."""
    from distributed import WorkerPlugin

    class StandInPlugin(WorkerPlugin):
        name = "benchmark-stand-in"

        def setup(self, worker):
            worker.stand_in_path = install_stand_in(seconds, picture, gain)

    return StandInPlugin()
