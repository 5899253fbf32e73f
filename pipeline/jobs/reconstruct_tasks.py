"""What a reconstruction's workers run: the method built once per process (a network loaded once per weights file),
the stores opened once per run, the task that reconstructs a block of tiles, the automatic exposure. The job
(``pipeline.jobs.reconstruct``), its dry run (``pipeline.jobs.dry_run``) and the lazy graphs (``pipeline.lazy``) send them.
"""

import functools
import threading

from pipeline.compute.hold import hold_point
from pipeline.jobs.reconstruct_plan import (
    Plan,
)
from pipeline.stores.spike_store import open_spike_store, read_frames
from pipeline.stores.video_store import TileWriter
from stages.capture.bits import pack_rows, unpack_rows
from stages.errors import InputError
from stages.reconstruction.colour import auto_gain
from stages.reconstruction.methods import NETWORKS, Reconstructor, Window, classic
from stages.reconstruction.tfp import tfp_rate
from stages.reconstruction.tiles import Tile


def reconstructor(method: str, weights: str | None, precision: str | None = "fp32", backend: str | None = "torch",
                  weights_sha256: str | None = None, *, fast_gpu: bool = False,
                  device: str | None = None) -> Reconstructor:
    """The method, built once per process and file contents (the cache lives in each worker) and reused
    by its tasks: for the network, loaded from its weights once, onto the worker's GPU if any (or onto
    ``device``: the job's own process checks the weights on the CPU). Keyed by the weights' SHA-256 (a
    job's tasks pass the one the job was planned with; else the file is hashed now), so a long-lived
    worker or watcher never runs a model cached from an older file at that path."""
    if method not in NETWORKS:
        with _building:
            return _built(method, None, None, None, None)
    from cscsr.weights.weights_io import weights_file
    from cscsr.weights.weights_io import weights_sha256 as sha256_of

    with _building:  # the worker's tasks in flight start together: one loads, the others wait for its network
        return _built(method, weights, precision, backend, weights_sha256 or sha256_of(weights_file(weights)),
                      fast_gpu, device)


_building = threading.Lock()


@functools.lru_cache(maxsize=4)
def _built(method: str, weights: str | None, precision: str | None, backend: str | None,
           weights_sha256: str | None, fast_gpu: bool = False, device: str | None = None) -> Reconstructor:
    if method in NETWORKS:
        from cscsr.inference.reconstructor import load_reconstructor

        loaded = load_reconstructor(weights, device, self_ensemble=method == "cscsr-ensemble",
                                    precision=precision or "fp32", backend=backend or "torch", fast_gpu=fast_gpu)
        if loaded.weights_sha256 != weights_sha256:
            raise InputError(f"weights file {loaded.weights} changed since the job started (sha256 "
                             f"{weights_sha256[:12]}… -> {loaded.weights_sha256[:12]}…): run the job again")
        return loaded
    return classic(method)


@functools.lru_cache(maxsize=4)
def _opened(spikes: str, out: str, run: str):
    """The input array and output writer, opened once per worker process and run (opening
    costs several metadata reads; a task's own work can be under a millisecond)."""
    return open_spike_store(spikes).spikes, TileWriter(out)


def _reconstruct_tiles(plan: Plan, frames: tuple[tuple[int, int], ...],
                       tiles: tuple[tuple[int, int, Tile], ...]) -> int:
    """Task: for each tile (ty, tx, tile) and each (output frame, centre), read the window + halo;
    reconstruct each tile's windows as one batch (on a GPU, the windows of all tiles of one shape
    together); crop, write and commit each frame's tile."""
    hold_point()  # inert unless a fault test asks (pipeline.compute.hold)
    half = plan.window // 2
    spikes, writer = _opened(plan.spikes, plan.out, plan.run)
    method = reconstructor(plan.method, plan.weights, plan.precision, plan.backend, plan.weights_sha256,
                           fast_gpu=bool(plan.fast_gpu))
    windows = [tile_windows(spikes, plan.spikes, [c for _, c in frames], half, tile, plan.cfa, plan.reset, plan.gain,
                            plan.scale) for _, _, tile in tiles]
    first = frames[0][0]  # a task's output frames are consecutive
    top, _, left, _ = plan.region or (0, None, 0, None)  # the output's corner in the recording (LR)
    for (ty, tx, tile), images in zip(tiles, method.many_tiles(windows, plan.gpu_batch)):
        ys, xs = tile.crop(plan.scale)
        writer.write_frames(first, (ty, tx), ((tile.y0 - top) * plan.scale, (tile.x0 - left) * plan.scale),
                            [image[ys, xs] for image in images])  # compressed and stored together
    return len(frames) * len(tiles)


def tile_windows(spikes, url: str, centres, half: int, tile: Tile, cfa: str, reset: str, gain: float,
                 scale: int) -> list[Window]:
    """The windows centred on spike frames ``centres`` of ``tile``'s read region (halo included), read packed
    straight from the store's ``spikes`` array (refusing a lost chunk): the store's own bytes where the region starts
    on a byte (tiles of a whole recording do), else its bits shifted to start the row (a selection of pixels from
    an even column that is not a multiple of 8)."""
    width = tile.rx1 - tile.rx0
    shift = tile.rx0 % 8
    region = (slice(tile.ry0, tile.ry1), slice(tile.rx0 // 8, -(-tile.rx1 // 8)))
    windows = []
    for centre in centres:
        packed = read_frames(spikes, url, centre - half, centre + half + 1, region)
        if shift:
            packed = pack_rows(unpack_rows(packed, shift + width)[..., shift:])
        windows.append(Window(packed, width, cfa, reset, gain, scale))
    return windows


def _auto_gain(spikes: str, centre: int, window: int, reset: str) -> float:
    """Task: the automatic exposure of the window around ``centre``, whole frame."""
    store = open_spike_store(spikes)
    half = window // 2
    return auto_gain(tfp_rate(store.read(centre - half, centre + half + 1), store.meta.width, reset))
