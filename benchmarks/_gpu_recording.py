"""The recording ``gpu_pipeline.py`` reconstructs, and its geometry.

A simulated RGGB spike recording of a still picture (``pipeline.jobs.simulate``), cached in
``/tmp/cscsr_bench`` by its parameters (:func:`cached_recording`; ``gpu_prove.py`` calls it too,
to simulate the pipeline steps' recording before the lease's clock runs), and the figures every part
of the GPU benchmark shares: the network's window (one output frame per window), the scale, and the
output frames of a terabyte of capture.
"""

import shutil
import sys
import time
from pathlib import Path

import numpy as np

CACHE = Path("/tmp/cscsr_bench")
RECORDING_VERSION = 1  # part of the cache key: bump when the recording's recipe changes
WINDOW = 41  # the network's window; output frames every WINDOW spike frames (the default --every)
SCALE = 4
CAPTURE_SPIKE_FRAMES = 8_000_000  # a terabyte of the 1000x1000 camera's capture
OUTPUT_FRAMES_PER_TB = round(CAPTURE_SPIKE_FRAMES / WINDOW)  # 195,122


def scene(side_hr: int, seed: int = 0) -> np.ndarray:
    """(side_hr, side_hr, 3) uint8: smooth colour gradients plus fine texture (something for the flow net to see)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:side_hr, 0:side_hr].astype(np.float32) * (1000 / side_hr * 4)  # features scale with the side
    channels = [0.5 + 0.25 * np.sin(x / 37 + k) * np.cos(y / 53 - k) + 0.15 * np.sin((x + (0.6 + k / 5) * y) / 23)
                for k in range(3)]
    texture = rng.random((side_hr // 4 + 1, side_hr // 4 + 1), dtype=np.float32)
    texture = np.kron(texture, np.ones((4, 4), np.float32))[:side_hr, :side_hr] - 0.5  # 4-pixel blocks
    image = np.stack([c + 0.1 * texture for c in channels], axis=-1)
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)


def simulate_recording(work: Path, side: int, frames: int) -> str:
    """Simulate ``frames`` spike frames of side x side LR RGGB (a still picture) into ``work/spikes.zarr``."""
    import cv2

    from pipeline.jobs.simulate import SimulateOptions, simulate

    picture = work / "scene.png"
    cv2.imwrite(str(picture), scene(side * SCALE)[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1])  # RGB -> BGR
    store = work / "spikes.zarr"
    simulate(str(picture), str(store), SimulateOptions(scale=SCALE, cfa="rggb", frames=frames, motion="static",
                                                       truth_every=frames, overwrite=True), progress=False)
    return str(store)


def cached_recording(side: int, frames: int) -> tuple[str, float]:
    """The recording of ``frames`` spike frames at ``side``, simulated once and kept in :data:`CACHE` under
    a name made of its parameters; -> (its URL, seconds spent simulating now: 0 when it was cached)."""
    folder = CACHE / f"recording-v{RECORDING_VERSION}-side{side}-frames{frames}"
    store = folder / "spikes.zarr"
    if (folder / "done").exists():
        return str(store), 0.0
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    print(f"simulating {frames} spike frames of {side}x{side} RGGB into {folder} ...", file=sys.stderr, flush=True)
    start = time.perf_counter()
    simulate_recording(folder, side, frames)
    seconds = time.perf_counter() - start
    (folder / "done").write_text(f"{seconds:.1f} s\n")
    print(f"simulated in {seconds:.1f} s", file=sys.stderr, flush=True)
    return str(store), seconds
