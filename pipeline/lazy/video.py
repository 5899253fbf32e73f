"""Windows, reconstructions and video as lazy xarray: the ``reconstruct`` job's stages as dask graphs.

    spikes (t, y, x) bool                      lazy.open_spikes, lazy.simulate  (pipeline.lazy.spikes)
      -> windows (t, dt, y, x) bool            one 41-frame window per output frame: dask's overlap along time
      -> hr (t, y, x, rgb) uint8               tfp, tfi, reconstruct, apply: a block per (frames, tile), halo included
      -> a video store                          to_video (pipeline.lazy.written): per block, resumable

Every piece is the job's (the output frames and parts, the tiles and halos, the method prepared and cut into blocks,
the gain), so ``to_video`` of a lazy reconstruction writes the bytes ``cscsr reconstruct`` writes with the same
options. Nothing is computed before ``to_video`` or ``.compute()``, but for the network's weights, checked here.
"""

import contextlib
import dataclasses
import os
from collections.abc import Callable

import dask
import dask.array as da
import numpy as np
import xarray as xr
from dask.base import tokenize
from dask.highlevelgraph import HighLevelGraph, Layer, MaterializedLayer

from pipeline.compute.cluster import GPU, GPU_SHARE
from pipeline.jobs.reconstruct_plan import Plan, ReconstructOptions
from pipeline.jobs.reconstruct_tasks import MethodSpec, TileBlocks, block_frames, cropped, cut
from pipeline.lazy.spikes import distributed_client, python_words, url_text
from pipeline.lazy.windows import PackedReads, check_windows
from stages.capture.bits import pack_rows, unpack_rows
from stages.errors import InputError, InputTypeError
from stages.numbers import check_number, check_text
from stages.reconstruction.colour import check_gain
from stages.reconstruction.methods import NETWORKS, Reconstructor, Window
from stages.reconstruction.tiles import Tile, tile_grid

VIDEO_DIMS = ("t", "y", "x", "rgb")


@dataclasses.dataclass(frozen=True)
class FunctionReconstructor:
    """A user's own method as a ``Reconstructor``: ``func(window) -> image``, ``window`` (N, h, w) bool (a tile and
    its halo), ``image`` (scale*h, scale*w, 3) uint8."""

    func: Callable
    scale: int
    halo: int
    name: str
    batch: int = 1
    weights: None = None
    weights_sha256: None = None

    def __call__(self, window: Window) -> np.ndarray:
        bits = unpack_rows(window.packed, window.width).view(bool)
        image = self.func(bits)
        expected = (self.scale * bits.shape[1], self.scale * bits.shape[2], 3)
        if not isinstance(image, np.ndarray) or image.shape != expected or image.dtype != np.uint8:
            got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise InputError(f"{self.name}(window) must give a uint8 image of shape {expected} for a window "
                             f"{bits.shape} at scale {self.scale}, got {got}")
        return image

    def many(self, windows: list[Window]) -> list[np.ndarray]:
        return [self(window) for window in windows]

    def many_tiles(self, tiles: list[list[Window]], most: int | None = None) -> list[list[np.ndarray]]:
        return [self.many(windows) for windows in tiles]

    def check(self, window: int, scale: int, cfa: str) -> None:
        return None


def tfp(win: xr.DataArray, *, gain: float | None = None, scale: int | None = None, tile: int | None = None) -> xr.DataArray:
    """TFP of every window (``reconstruct(win, method="tfp")``)."""
    return reconstruct(win, method="tfp", gain=gain, scale=scale, tile=tile)


def tfi(win: xr.DataArray, *, gain: float | None = None, scale: int | None = None, tile: int | None = None) -> xr.DataArray:
    """TFI of every window (``reconstruct(win, method="tfi")``)."""
    return reconstruct(win, method="tfi", gain=gain, scale=scale, tile=tile)


def reconstruct(win: xr.DataArray, *, method: str = "cscsr", weights: str | os.PathLike | None = None,
                tile: int | None = None, precision: str = "fp32", backend: str = "torch", gain: float | None = None,
                scale: int | None = None) -> xr.DataArray:
    """Every window reconstructed by ``method`` (tfp, tfi, cscsr, cscsr-ensemble) as the job does it: (t, y, x, rgb)
    uint8 at ``scale`` (default the recording's, else 4), a block per (the job's task of frames, tile). ``weights``:
    default ``full`` where a ``distributed`` client has GPU workers (its tasks then run there), else ``lite``.
    ``gain``: default the recording's, else the job's automatic exposure. Lazy."""
    win = check_windows(win)
    check_text("method", method)
    weights = url_text(weights, "weights") if isinstance(weights, os.PathLike) else weights
    options = ReconstructOptions(method=method, every=win.attrs["every"], window=win.attrs["window"], gain=gain,
                                 scale=scale, tile=tile, weights=weights, precision=precision, backend=backend)
    with python_words():
        options.check()
    from pipeline.jobs.reconstruct import method_spec, prepared

    y0, y1, x0, x1 = win.attrs["region"]
    options, where, scale, built = prepared(options, distributed_client(win.data), win.attrs["cfa"],
                                            win.attrs.get("scale"), (y1 - y0, x1 - x0), {})
    return _reconstructed(win, method_spec(options, built, where), built, scale, options.tile, gain,
                          options.gpu_batch, where.gpus)


def apply(win: xr.DataArray, func: Callable, *, scale: int, halo: int = 0, tile: int | None = None,
          gain: float | None = None) -> xr.DataArray:
    """The user's own reconstructor over every window, run over tiles with its halo exactly as the built-in methods
    are: ``func(window)`` gets one window of a tile and ``halo`` LR pixels around it ((N, h, w) bool; fewer at the
    frame's edges) and gives its (scale*h, scale*w, 3) uint8 image, whose halo is cropped off. Lazy."""
    win = check_windows(win)
    if not callable(func):
        raise InputTypeError(f"func must be a function of a window, got {func!r}")
    check_number("scale", scale, at_least=1, integer=True)
    check_number("halo", halo, at_least=0, integer=True)
    if halo % 2 and (cfa := win.attrs["cfa"]) != "mono":
        raise InputError(f"halo={halo} is odd: the {cfa} colour pattern repeats every 2 pixels, so an odd halo would "
                         f"give func windows of differing colour phase; give an even halo")
    if tile is not None:
        with python_words():
            ReconstructOptions(tile=tile).check()
    name = getattr(func, "__name__", type(func).__name__)
    own = FunctionReconstructor(func, scale, halo, name)
    y0, y1, x0, x1 = win.attrs["region"]
    return _reconstructed(win, MethodSpec(name, own=own), own, scale, tile or max(y1 - y0, x1 - x0, 8) // 8 * 8 + 8,
                          gain, 1, False)


def _reconstructed(win: xr.DataArray, spec: MethodSpec, built: Reconstructor, scale: int, tile: int, gain, most: int,
                   gpu: bool) -> xr.DataArray:
    """The graph of :func:`reconstruct` and :func:`apply`: the job's blocks read from the store where the windows
    are a store's as read, else a blockwise map per tile of the job's grid over the windows, tiles put together."""
    attrs = win.attrs
    height, width, cfa = attrs["height"], attrs["width"], attrs["cfa"]
    region = tuple(attrs["region"])
    oy, ox = int(win.coords["y"][0]), int(win.coords["x"][0])
    by0, by1, bx0, bx1 = attrs.get("bounds") or (0, height, 0, width)  # the selected pixels: the frame's edges
    grid = [[Tile(t.y0 + by0, t.y1 + by0, t.x0 + bx0, t.x1 + bx0, t.ry0 + by0, t.ry1 + by0, t.rx0 + bx0, t.rx1 + bx0)
             for t in row]
            for row in tile_grid(by1 - by0, bx1 - bx0, tile, built.halo,
                                 (region[0] - by0, region[1] - by0, region[2] - bx0, region[3] - bx0))]
    if any(t.ry0 < oy or t.rx0 < ox or t.ry1 > oy + win.shape[2] or t.rx1 > ox + win.shape[3] for row in grid for t in row):
        kept = attrs.get("kept")
        sliced = (kept is not None and [oy, oy + win.shape[2], ox, ox + win.shape[3]] != list(kept))
        raise InputError(f"{spec.method} reads {built.halo} LR pixels around each tile, more than the windows keep "
                         f"around their region" + (f": they were sliced (y {oy}:{oy + win.shape[2]}, x {ox}:"
                                                   f"{ox + win.shape[3]} of the y {kept[0]}:{kept[1]}, x {kept[2]}:"
                                                   f"{kept[3]} lazy.windows kept): select pixels on the spikes "
                                                   f"instead" if sliced else
                                                   f": make them with lazy.windows(..., margin={built.halo})"))
    gain = _gain(win, gain)
    reads = attrs.get("reads")
    if isinstance(reads, PackedReads) and reads.holds(win.data, int(win.coords["frame"][0])):  # read from the store
        blocks = cut(spec, reads.url, reads.identity, [int(c) for c in win.coords["frame"].values], attrs["first"],
                     attrs["every"], attrs["window"], grid, built.batch, cfa, attrs["reset"], scale, most,
                     gain.__dask_keys__()[0] if isinstance(gain, da.Array) else gain, gpu, attrs["frames"])
        hr = _blocks_array(blocks, gain)
    else:  # the windows as they are (a function between stages): each block's tile of them
        frames = _task_frames(win.data.chunks[0], built.batch, attrs["first"])
        data = win.data.rechunk({1: -1, 2: -1, 3: -1}).rechunk({0: frames})
        arguments = (spec, gain, cfa, attrs["reset"], scale)
        with dask.annotate(resources={GPU: GPU_SHARE}) if gpu else contextlib.nullcontext():
            rows = [[_windows_tile(data, oy, ox, t, (*arguments, t.crop(scale), most),
                                   ((t.y1 - t.y0) * scale, (t.x1 - t.x0) * scale)) for t in row] for row in grid]
        hr = da.concatenate([da.concatenate(row, axis=2) for row in rows], axis=1)  # tiles side by side, rows down
    plan = Plan(attrs.get("store") or "", "", spec.method, built.weights, attrs["window"], attrs["every"], np.nan, scale,
                cfa, attrs["reset"], tile, "", spec.precision, most, spec.backend,
                spec.fast_gpu if spec.method in NETWORKS else None,
                source_identity=attrs.get("identity"), source_shape=(attrs["frames"], height, width),
                weights_sha256=built.weights_sha256, start=attrs["start"], stop=attrs["stop"], region=region,
                edges=None if (by0, by1, bx0, bx1) == (0, height, 0, width) else (by0, by1, bx0, bx1))
    # what a job's output records, and its frame rate: output frames per second of recording
    recorded = {**plan.attrs(), "source": attrs.get("store"), "fps": float(attrs["fps"]) / attrs["every"]}
    del recorded["gain"]  # a coordinate: lazy where it is the automatic exposure
    return xr.DataArray(hr, dims=VIDEO_DIMS, name="video", attrs=recorded,
                        coords={"t": win.coords["t"], "frame": win.coords["frame"], "gain": ((), gain),
                                "y": np.arange(region[0] * scale, region[1] * scale),
                                "x": np.arange(region[2] * scale, region[3] * scale)})


def _gain(win: xr.DataArray, gain: float | None):
    """The gain every tile uses: ``gain``, else the recording's, else its automatic exposure (0-d lazy)."""
    if gain is not None:
        check_gain("gain", gain)
        return float(gain)
    if win.attrs.get("gain") is not None:
        return float(win.attrs["gain"])
    if "auto_gain" not in win.coords:
        raise InputError("the windows are of a part of spikes that are not a store's as it holds them (computed, or "
                         "not read from a store), and their recording's automatic gain needs all of it: give gain=")
    return win.coords["auto_gain"].data


def _task_frames(chunks: tuple[int, ...], batch: int, first: int) -> tuple[int, ...]:
    """Chunks of output frames: the job's blocks for a method of ``batch`` windows a pass (a network's numbers can
    depend on its batch), else ``chunks`` (empty ones dropped)."""
    if batch == 1:
        return tuple(n for n in chunks if n) or (0,)
    return block_frames(sum(chunks), batch, first)


def _windows_tile(data: da.Array, oy: int, ox: int, t: Tile, arguments: tuple, hr_tile: tuple[int, int]) -> da.Array:
    """Tile ``t`` of every window (``data``, kept from LR pixel (oy, ox)) reconstructed, a block per chunk of frames."""
    read = data[:, :, t.ry0 - oy : t.ry1 - oy, t.rx0 - ox : t.rx1 - ox]
    return read.map_blocks(_reconstruct_block, *arguments, name=f"{arguments[0].method}-{tokenize(read.name, *arguments)}",
                           chunks=(read.chunks[0], *((n,) for n in hr_tile), (3,)), dtype=np.uint8,
                           meta=np.empty((0, 0, 0, 0), np.uint8))


def tile_blocks(data: da.Array) -> TileBlocks | None:
    """The blocks ``data`` holds where it is :func:`reconstruct`'s array read from a store as it was made (nothing
    since: ``to_video`` on a cluster then runs them as the job does), else None."""
    layer = data.__dask_graph__().layers.get(data.name)
    if not isinstance(layer, BlocksLayer):
        return None
    blocks = layer.blocks
    return blocks if data.chunks == (blocks.frames, *blocks.hr_tiles, (3,)) else None


class BlocksLayer(Layer):
    """The tasks of every block of ``blocks`` (``TileBlocks.graph``) as one graph layer, annotated as the job's, each
    task made (once) when something asks for it: a long recording's graph costs nothing until it is computed, and then
    only what a computation needs (:meth:`cull`) is made."""

    has_legacy_tasks = False  # every task a ``dask._task_spec.Task`` (the base class would make them all to find out)

    def __init__(self, blocks: TileBlocks):
        super().__init__(annotations=blocks.annotations)
        self.blocks = blocks
        self._pass_of = {tile: k for k, tiles in enumerate(blocks.passes) for tile in tiles}  # (ty, tx) -> pass
        self._made: dict = {}

    def _unit(self, key) -> tuple[int, int] | None:
        """(block along time, pass) whose tasks hold ``key``, or None for a key not of this layer."""
        blocks = self.blocks
        if not isinstance(key, tuple) or not key or not isinstance(key[0], str):
            return None
        if key[0] == blocks.name and len(key) == 5 and (key[2], key[3]) in self._pass_of:
            b, k = key[1], self._pass_of[key[2], key[3]]
        elif key[0] == f"pass-{blocks.name}" and len(key) == 3 and 0 <= key[2] < len(blocks.passes):
            b, k = key[1], key[2]
            if len(blocks.passes[k]) == 1:
                return None
        else:
            return None
        return (b, k) if isinstance(b, int) and 0 <= b < len(blocks.frames) and blocks.frames[b] else None

    def _tasks(self, b: int, k: int) -> dict:
        tasks = self.blocks.graph(b, k)
        self._made.update(tasks)
        return tasks

    def __getitem__(self, key):
        if key in self._made:
            return self._made[key]
        unit = self._unit(key)
        if unit is None:
            raise KeyError(key)
        return self._tasks(*unit)[key]

    def __contains__(self, key) -> bool:
        return self._unit(key) is not None

    def __iter__(self):
        blocks = self.blocks
        for b, k in blocks.units():
            tiles = blocks.passes[k]
            if len(tiles) > 1:
                yield f"pass-{blocks.name}", b, k
            for ty, tx in tiles:
                yield blocks.name, b, ty, tx, 0

    def __len__(self) -> int:
        per_block = sum(len(tiles) + (len(tiles) > 1) for tiles in self.blocks.passes)
        return per_block * sum(1 for n in self.blocks.frames if n)

    def is_materialized(self) -> bool:
        return False

    def get_output_keys(self):
        return set(self)

    def cull(self, keys, all_hlg_keys):
        """Only the tasks ``keys`` need, made now: -> (their layer, {key: its dependencies})."""
        out = {}
        for unit in {self._unit(key) for key in keys} - {None}:
            tasks = self._tasks(*unit)
            wanted = {key for key in tasks if key in keys}
            wanted |= {dep for key in wanted for dep in tasks[key].dependencies if dep in tasks}  # the pass they share
            out.update({key: tasks[key] for key in wanted})
        return MaterializedLayer(out, annotations=self.annotations), {k: set(v.dependencies) for k, v in out.items()}


def _blocks_array(blocks: TileBlocks, gain) -> da.Array:
    """``blocks`` as a dask array (t, y, x, rgb) uint8 (:class:`BlocksLayer`), on the exposure's graph if lazy."""
    layers, dependencies = {blocks.name: BlocksLayer(blocks)}, {blocks.name: set()}
    if isinstance(gain, da.Array):
        below = gain.__dask_graph__()
        layers.update(below.layers)
        dependencies.update(below.dependencies)
        dependencies[blocks.name] = {gain.name}
    return da.Array(HighLevelGraph(layers, dependencies), blocks.name, (blocks.frames, *blocks.hr_tiles, (3,)),
                    meta=np.empty((0, 0, 0, 0), np.uint8))


def _reconstruct_block(block: np.ndarray, spec: MethodSpec, gain, cfa: str, reset: str, scale: int,
                       crop: tuple[slice, slice], most: int) -> np.ndarray:
    """Task: (n, N, h, w) bool windows of one tile with its halo -> (n, tile_h*s, tile_w*s, 3) uint8, the halo cropped."""
    width = block.shape[3]
    windows = [Window(pack_rows(window), width, cfa, reset, float(gain), scale) for window in block]
    return cropped(spec.built().many_tiles([windows], most)[0] if windows else [], crop)
