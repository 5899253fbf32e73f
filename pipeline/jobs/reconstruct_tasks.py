"""A reconstruction's tasks, for the ``reconstruct`` job (and its dry run) and the lazy graphs alike.

:class:`TileBlocks` is a reconstruction read straight from a spike store, as frozen data: output frames cut into
blocks along time (the network's batches) and into tiles, on GPU workers the tiles of one shape joined into one
network pass; the tasks of any block are made on demand, as the lazy array's (:meth:`TileBlocks.graph`) or as the
job's (:meth:`TileBlocks.written`: read, reconstruct, write and commit in one task). Also here, what workers build
once per process (the method, the stores opened) and the automatic exposure.
"""

import dataclasses
import functools
import operator
import threading
from collections.abc import Iterable, Iterator
from typing import NamedTuple

import numpy as np

from pipeline.compute.hold import hold_point
from pipeline.stores.spike_store import open_spike_store, read_frames, store_identity
from pipeline.stores.storage import remove_partial_writes
from pipeline.stores.video_store import TileWriter, open_video_store
from stages.capture.bits import pack_rows, unpack_rows
from stages.errors import InputError
from stages.reconstruction.colour import auto_gain
from stages.reconstruction.methods import NETWORKS, Reconstructor, Window, classic, middle_centre, output_centres
from stages.reconstruction.tfp import tfp_rate
from stages.reconstruction.tiles import Tile

WINDOW_BLOCKS = 1024  # the most blocks along time for a method of one window a pass: then several windows a block


def reconstructor(method: str, weights: str | None, precision: str | None = "fp32", backend: str | None = "torch",
                  weights_sha256: str | None = None, *, fast_gpu: bool = False,
                  device: str | None = None) -> Reconstructor:
    """The method, built once per process and weights file (onto the worker's GPU if any, else ``device``) and
    reused by its tasks. Keyed by the weights' SHA-256 (the one the job was planned with; else hashed now), so a
    long-lived worker never runs a model cached from an older file at that path."""
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


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """What a task needs to build its reconstructor (once per worker process): a name and weights, or the user's
    own (``lazy.apply``)."""

    method: str
    weights: str | None = None
    precision: str | None = None
    backend: str | None = None
    weights_sha256: str | None = None
    fast_gpu: bool = False
    own: Reconstructor | None = None

    def built(self) -> Reconstructor:
        if self.own is not None:
            return self.own
        return reconstructor(self.method, self.weights, self.precision, self.backend, self.weights_sha256,
                             fast_gpu=self.fast_gpu)


def block_frames(n: int, batch: int, first: int) -> tuple[int, ...]:
    """Output frames per block along time: for ``batch`` windows a pass, the batches of the whole recording's output
    frames from index ``first`` on, so a part's and a resume's batches are a whole run's (a batch's numbers can depend
    on its size); for one window a pass, one a block up to :data:`WINDOW_BLOCKS` blocks, then several."""
    if n == 0:
        return (0,)
    if batch == 1:
        size = -(-n // WINDOW_BLOCKS)
        return (size,) * (n // size) + ((n % size,) if n % size else ())
    cut = [max(start, 0) for start in range(-(first % batch), n, batch)] + [n]
    return tuple(b - a for a, b in zip(cut, cut[1:]))


@dataclasses.dataclass(frozen=True)
class TileBlocks:
    """A reconstruction read straight from the spike store at ``url`` (the recording ``identity``): output frames
    centred on spike frames ``first_centre + j * every`` (j < ``sum(frames)``), ``frames`` of them a block along
    time, each cut into ``grid``'s tiles, the tiles of each of ``passes`` reconstructed in one network pass (one
    tile each but on GPU workers). ``gain``: a number, or the key of a task that gives it."""

    spec: MethodSpec
    url: str
    identity: str
    first_centre: int
    every: int
    half: int
    frames: tuple[int, ...]
    grid: tuple[tuple[Tile, ...], ...]
    passes: tuple[tuple[tuple[int, int], ...], ...]
    cfa: str
    reset: str
    scale: int
    most: int  # the most windows a network pass (GPU workers)
    gain: float | tuple
    gpu: bool = False  # its reconstructions ask for a share of a GPU worker (pipeline.compute.cluster.GPU_SHARE)
    # a part's first and last blocks: the whole run's windows before and after it in their network batch, run with
    # it and dropped, so that every batch is a whole run's (its numbers can depend on its size and neighbours)
    lead: int = 0
    tail: int = 0

    def __post_init__(self) -> None:
        from dask.base import tokenize

        # its tasks' key prefix: the method's name and a token of everything that makes them (made once, here)
        object.__setattr__(self, "name", f"{self.spec.method}-{tokenize(self)}")

    @functools.cached_property
    def starts(self) -> tuple[int, ...]:
        """The first output frame of each block along time, and the end."""
        return tuple(int(s) for s in np.cumsum((0, *self.frames)))

    @property
    def hr_tiles(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """HR rows of each tile row, HR columns of each tile column."""
        return (tuple((row[0].y1 - row[0].y0) * self.scale for row in self.grid),
                tuple((t.x1 - t.x0) * self.scale for t in self.grid[0]))

    @property
    def layout(self) -> dict:
        """The video store's tiles: ``tiles`` (rows, columns) and ``tile_hr`` (the first tile's HR size)."""
        rows, columns = self.hr_tiles
        return {"tiles": (len(rows), len(columns)), "tile_hr": (rows[0], columns[0])}

    def units(self, done: np.ndarray | None = None) -> Iterator[tuple[int, int]]:
        """(block along time, pass) of every unit still to run: any of its frames' tiles not committed (``done``,
        (frames, tile rows, tile columns)); generated as consumed."""
        finished = None if done is None else self._finished(done)
        for b in range(len(self.frames)):  # never empty (an empty part is refused before)
            for k in range(len(self.passes)):
                if finished is None or not finished[b, k]:
                    yield b, k

    def task_counts(self, done: np.ndarray) -> tuple[int, int]:
        """(tasks still to run, tasks in all): the job's tasks, a block along time and a pass of its tiles (one tile
        on CPU workers), as :meth:`units` gives them; ``done`` (frames, tile rows, tile columns) committed."""
        total = len(self.frames) * len(self.passes)
        return total - int(self._finished(done).sum()), total

    def _finished(self, done: np.ndarray) -> np.ndarray:
        """(blocks along time, passes) bool: every frame of every tile of the pass committed in ``done``."""
        whole = np.logical_and.reduceat(done, self.starts[:-1], axis=0)  # (blocks, rows, columns): all frames in
        return np.stack([np.logical_and.reduce([whole[:, ty, tx] for ty, tx in tiles]) for tiles in self.passes],
                        axis=1)

    def read(self, b: int, k: int, key=None):
        """The task that reads and reconstructs every tile of pass ``k`` of block ``b`` along time, as ``key``
        (None: inline, in a task that takes its output) -> per tile (n, h, w, 3) uint8 (:func:`read_tiles`)."""
        from dask._task_spec import Task, TaskRef

        lead = self.lead if b == 0 else 0
        tail = self.tail if b == len(self.frames) - 1 else 0
        run = range(self.starts[b] - lead, self.starts[b + 1] + tail)
        centres = tuple(self.first_centre + j * self.every for j in run)
        gain = TaskRef(self.gain) if isinstance(self.gain, tuple) else self.gain
        return Task(key, read_tiles, gain, self.spec, self.url, self.identity, centres, self.half,
                    tuple(self.grid[ty][tx] for ty, tx in self.passes[k]), self.cfa, self.reset, self.scale, self.most,
                    (lead, self.frames[b]))

    def graph(self, b: int, k: int) -> dict:
        """The tasks of pass ``k`` of block ``b`` along time, as the lazy array holds them: {key: task}, each tile's
        HR block (n, h, w, 3) uint8 under the key ``(name, b, ty, tx, 0)``; tiles of a joined pass are taken from
        its task, ``(pass-<name>, b, k)``."""
        from dask._task_spec import Task, TaskRef

        tiles = self.passes[k]
        if len(tiles) == 1:
            key = (self.name, b, *tiles[0], 0)
            return {key: Task(key, operator.getitem, self.read(b, k), 0)}
        joined = (f"pass-{self.name}", b, k)
        tasks = {joined: self.read(b, k, joined)}
        for i, (ty, tx) in enumerate(tiles):
            key = (self.name, b, ty, tx, 0)
            tasks[key] = Task(key, operator.getitem, TaskRef(joined), i)
        return tasks

    def corner(self, ty: int, tx: int) -> tuple[int, int]:
        """Tile (ty, tx)'s first HR row and column in the output."""
        rows, columns = self.hr_tiles
        return sum(rows[:ty]), sum(columns[:tx])

    @property
    def annotations(self) -> dict | None:
        """What the reconstruction tasks' layer asks of the scheduler: a share of a GPU worker, on GPU workers."""
        from pipeline.compute.cluster import GPU, GPU_SHARE

        return {"resources": {GPU: GPU_SHARE}} if self.gpu else None

    def written(self, b: int, k: int, url: str, run: str) -> tuple[tuple, object]:
        """(key, task) of the task that reads and reconstructs every tile of pass ``k`` of block ``b`` and writes them
        into the video store at ``url`` (:func:`write_blocks`), keyed ``(<name>-<run>, b, ty, tx, 0)``, or
        ``(pass-<name>-<run>, b, k)`` for a joined pass. One task, so an HR block never travels between workers."""
        from dask._task_spec import Task

        tiles, (rows, columns) = self.passes[k], self.hr_tiles
        key = (f"{self.name}-{run}", b, *tiles[0], 0) if len(tiles) == 1 else (f"pass-{self.name}-{run}", b, k)
        places = tuple(((ty, tx), self.corner(ty, tx), (self.frames[b], rows[ty], columns[tx], 3)) for ty, tx in tiles)
        return key, Task(key, write_blocks, self.read(b, k), url, run, self.starts[b], places)


def cut(spec: MethodSpec, url: str, identity: str, centres: list[int], first: int, every: int, window: int,
        grid: list[list[Tile]], batch: int, cfa: str, reset: str, scale: int, most: int, gain: float | tuple,
        gpu: bool, recording_frames: int) -> TileBlocks:
    """The blocks of the output frames centred on ``centres`` (index ``first`` of the whole recording's, of
    ``recording_frames`` spike frames) of the store at ``url``: :func:`block_frames` along time, ``grid``'s tiles, and
    on GPU workers (``gpu``) the tiles of one shape joined into passes of ``most`` windows; a part's first and last
    blocks run the whole run's batch they are in (``lead`` and ``tail``). The job and ``lazy.reconstruct`` cut them
    here."""
    from pipeline.jobs.reconstruct_plan import tile_blocks

    passes = tile_blocks(grid, max(1, most // batch) if gpu else 1)
    whole = len(output_centres(recording_frames, window, every))
    end = first + len(centres)
    lead, tail = (first % batch, min(-end % batch, whole - end)) if batch > 1 else (0, 0)
    return TileBlocks(spec, url, identity, centres[0], every, window // 2, block_frames(len(centres), batch, first),
                      tuple(map(tuple, grid)), tuple(passes), cfa, reset, scale, most, gain, gpu, lead, tail)


class Outcome(NamedTuple):
    """One finished tile of a block: block ``block`` along time (output frames ``start:stop``), tile (ty, tx), and
    why it failed, if it did."""

    block: int
    start: int
    stop: int
    ty: int
    tx: int
    error: str | None


def run_blocks(client, units: Iterable[tuple[int, int]], *, blocks: TileBlocks, out: str,
               run: str) -> Iterator[Outcome]:
    """Run ``units`` (block along time, pass) of ``blocks`` on ``client``, written into the video store at ``out``,
    each unit's task (:meth:`TileBlocks.written`) made as the executor's bounded window moves; yield the outcome of
    each of its tiles as it finishes. The job and ``lazy.to_video`` of a store's reconstruction on a client."""
    from dask.highlevelgraph import HighLevelGraph, MaterializedLayer

    from pipeline.compute.executor import failure, submitted

    def submit(unit):  # everything a task needs travels in it (scattered data dies with the workers holding it)
        key, task = blocks.written(*unit, out, run)  # one layer, annotated (a share of a GPU worker)
        graph = HighLevelGraph({key[0]: MaterializedLayer({key: task}, annotations=blocks.annotations)},
                               {key[0]: set()})
        return client.get(graph, [key], sync=False)[0]

    for (b, k), future in submitted(client, units, submit, idempotent=True):
        error = failure(future)  # the task raised, or the cluster failed it: report it, go on with the others
        for ty, tx in blocks.passes[k]:
            yield Outcome(b, blocks.starts[b], blocks.starts[b + 1], ty, tx, error)


def read_tiles(gain, spec: MethodSpec, url: str, identity: str, centres: tuple[int, ...], half: int,
               tiles: tuple[Tile, ...], cfa: str, reset: str, scale: int, most: int,
               keep: tuple[int, int] | None = None) -> tuple[np.ndarray, ...]:
    """Task: the windows centred on spike frames ``centres`` of each tile and its halo, read packed from the store,
    reconstructed (on a GPU, the windows of all ``tiles``, of one shape, in passes of ``most``) -> per tile
    (n, h, w, 3) uint8, the halo cropped; ``keep`` (first, count): those frames alone (the others ran to fill a
    whole run's batch)."""
    spikes = spike_array(url, identity)
    windows = [tile_windows(spikes, url, centres, half, tile, cfa, reset, float(gain), scale) for tile in tiles]
    images = spec.built().many_tiles(windows, most) if centres else [[] for _ in tiles]
    if keep is not None:
        images = [tile_images[keep[0] : keep[0] + keep[1]] for tile_images in images]
    return tuple(cropped(tile_images, tile.crop(scale)) for tile, tile_images in zip(tiles, images))


def cropped(images: list[np.ndarray], crop: tuple[slice, slice]) -> np.ndarray:
    """A tile's HR images, each (H, W, 3), cropped to ``crop`` (its halo off) -> (n, h, w, 3) uint8."""
    ys, xs = crop
    out = np.empty((len(images), ys.stop - ys.start, xs.stop - xs.start, 3), np.uint8)
    for n, image in enumerate(images):
        out[n] = image[ys, xs]
    return out


class JobIncomplete(RuntimeError):
    """Some tasks raised: which output frames are missing and why; the rest is committed."""

    def __init__(self, out: str, failed: dict[int, str], n_frames: int, again: str = "--resume"):
        frames = sorted(failed)
        shown = ", ".join(map(str, frames[:20])) + (", ..." if len(frames) > 20 else "")
        causes = {why.split("): ", 1)[-1] if why.startswith("tile (") else why for why in failed.values()}
        first = (f"each: {causes.pop()}" if len(causes) == 1 and len(frames) > 1  # one cause (a full disk): once
                 else f"frame {frames[0]}: {failed[frames[0]]}")
        rest = (f"the other frames are committed in {out}" if len(frames) < n_frames
                else f"what was written is kept in {out}")
        super().__init__(f"{len(frames)} of {n_frames} output frames failed (frames {shown}; {first}); {rest}: "
                         f"fix the cause and run again with {again}")
        self.failed = failed


def finish_video(url: str, failed: dict[int, str], n_frames: int, again: str = "--resume") -> None:
    """Complete the video store at ``url`` (a killed worker's temporary files removed, ``state`` the last write),
    unless output frames ``failed`` ({frame: why}): then :class:`JobIncomplete` names them for a resume (``again``)."""
    if failed:
        raise JobIncomplete(url, failed, n_frames, again)
    remove_partial_writes(url)
    open_video_store(url, writable=True).attrs["state"] = "complete"


def write_blocks(blocks: tuple[np.ndarray, ...], url: str, run: str, first: int, places: tuple) -> int:
    """Task: :func:`write_block` each of a pass's tile ``blocks`` at its place ((tile, corner, shape)) -> tiles
    written."""
    for block, place in zip(blocks, places):
        write_block(block, url, run, first, *place)
    return len(blocks)


def write_block(block: np.ndarray, url: str, run: str, first: int, tile: tuple[int, int], corner: tuple[int, int],
                shape: tuple[int, ...]) -> np.ndarray:
    """Task: check one HR block against its chunk (``shape``, uint8), write its frames (a chunk each, compressed
    and stored together), then commit them. -> (1, 1, 1, 1): how many frames."""
    hold_point()  # inert unless a fault test asks (pipeline.compute.hold): it holds a block's commit
    if not isinstance(block, np.ndarray) or block.shape != shape or block.dtype != np.uint8:
        got = f"{block.dtype} {block.shape}" if isinstance(block, np.ndarray) else type(block).__name__
        raise InputError(f"hr's block of output frames {first}..{first + shape[0] - 1}, tile {tile[0]},{tile[1]} "
                         f"computed {got} where its chunk is uint8 {shape}: a function between stages "
                         f"(map_blocks) must give each block its chunk's shape and dtype")
    writer(url, run).write_frames(first, tile, corner, list(block))
    return np.full((1, 1, 1, 1), len(block), np.int64)


@functools.lru_cache(maxsize=4)
def writer(url: str, run: str) -> TileWriter:
    """The output store opened once per worker process and run (a task's own work can be under a millisecond)."""
    return TileWriter(url)


@functools.lru_cache(maxsize=8)
def spike_array(url: str, identity: str):
    """The store's ``spikes`` array, opened once per process and recording ``identity`` (refused if another)."""
    store = open_spike_store(url)
    if store_identity(store) != identity:
        raise InputError(f"spike store {url} is not the recording this graph was built on (it was replaced): "
                         f"open it again")
    return store.spikes


def tile_windows(spikes, url: str, centres, half: int, tile: Tile, cfa: str, reset: str, gain: float,
                 scale: int) -> list[Window]:
    """The windows centred on spike frames ``centres`` of ``tile``'s read region (halo included), read packed from
    the store's ``spikes`` (refusing a lost chunk), their bits shifted where the region does not start on a byte."""
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


def gain_task(url: str, identity: str, n_frames: int, width: int, window: int,
              reset: str) -> tuple[tuple[str], tuple]:
    """(key, arguments of :func:`store_gain`) of the automatic exposure of the recording at ``url``: its middle window
    (``methods.middle_centre``), so every part of it, and every ``--every``, is exposed alike."""
    from dask.base import tokenize

    args = (url, identity, width, middle_centre(n_frames, window), window, reset)
    return (f"auto-gain-{tokenize(*args)}",), args


def store_gain(url: str, identity: str, width: int, centre: int, window: int, reset: str) -> np.ndarray:
    """Task: the automatic exposure of the window around spike frame ``centre``, whole frame (``width`` pixels),
    read from the store -> 0-d float64 (:func:`gain_task`)."""
    half = window // 2
    packed = read_frames(spike_array(url, identity), url, centre - half, centre + half + 1)
    return np.asarray(auto_gain(tfp_rate(packed, width, reset)), np.float64)
