"""Windows, reconstructions and video as lazy xarray: the ``reconstruct`` job's stages as dask graphs.

    spikes (t, y, x) bool                      lazy.open_spikes, lazy.simulate  (pipeline.lazy.spikes)
      -> windows (t, dt, y, x) bool            one 41-frame window per output frame: dask's overlap along time
      -> hr (t, y, x, rgb) uint8               tfp, tfi, reconstruct, apply: a blockwise map per tile, halo included
      -> a video store                          to_video: written per (frames, tile) block, committed, resumable

The arithmetic is the job's own (one home for each piece): the output frames, ranges and regions of
``pipeline.jobs.reconstruct_plan.job_part``, the tiles and halos of ``stages.reconstruction.tiles.tile_grid``, the reconstructors of
``pipeline.jobs.reconstruct_tasks.reconstructor`` (built once per worker process), the frames grouped into the network's
batches as the job's tasks group them (``task_groups``), the gain by the job's rule, the store written by
``pipeline.stores.video_store`` with the attributes a job records (``reconstruct_plan.Plan``). So ``to_video`` of a lazy
reconstruction writes the bytes ``cscsr reconstruct`` writes with the same options, and ``cscsr reconstruct
--resume``, ``info``, ``export`` and ``evaluate`` read it as the job's.

Nothing is computed before ``to_video`` (or the user's ``.compute()``), but for the network's weights, which
are loaded once here to check them (as the job checks them before any output exists).
"""

import contextlib
import dataclasses
import functools
import uuid
from collections.abc import Callable

import dask
import dask.array as da
import numpy as np
import xarray as xr

from pipeline.compute.cluster import GPU, GPU_SHARE
from pipeline.lazy.spikes import check_spikes
from pipeline.stores.lease import claimed, held
from pipeline.stores.outputs import VIDEO_STORE, new_output
from pipeline.compute.progress import progress_bar
from pipeline.jobs.reconstruct_plan import Plan, ReconstructOptions, job_part
from pipeline.stores.storage import check_place, exists, remove_partial_writes
from pipeline.stores.video_store import TileWriter, committed_mask, create_video_store, open_video_store
from stages.capture.bits import pack_rows, unpack_rows
from stages.reconstruction.colour import auto_gain
from stages.errors import InputError, InputTypeError
from stages.reconstruction.methods import NETWORKS, WINDOW, Reconstructor, Window, output_centres
from stages.numbers import check_flag, check_number, check_text
from stages.reconstruction.tfp import tfp_rate
from stages.reconstruction.tiles import tile_grid

MARGIN = 32  # LR pixels kept around a region: the largest halo of a built-in method (the network's, HALO)
WINDOW_DIMS, VIDEO_DIMS = ("t", "dt", "y", "x"), ("t", "y", "x", "rgb")
BLOCKS_AT_ONCE = 256  # blocks of video to_video computes and writes per round: the graph in memory stays bounded


# ---- windows ----

def windows(spikes: xr.DataArray, length: int = WINDOW, every: int = WINDOW, start=None, stop=None, region=None,
            *, margin: int = MARGIN) -> xr.DataArray:
    """The windows of the output frames ``cscsr reconstruct --window LENGTH --every EVERY --start --stop --region``
    makes of ``spikes``: (t, dt, y, x) bool, output frame ``t`` (coordinate: its centre's time; ``frame``: its
    centre spike frame) seeing spike frames ``centre + dt``, dt in -LENGTH//2..LENGTH//2. The time overlap of
    neighbouring windows is dask's (``map_overlap`` along t: each chunk of the recording reads LENGTH//2 frames of
    its neighbours), not a copy of the recording. With a region, its LR pixels and ``margin`` more on every side
    where the frame has them (the context a method's halo reads); ``attrs['region']`` says which are the region's.
    Lazy: nothing is read."""
    spikes = check_spikes(spikes)
    for name, value in (("length", length), ("every", every), ("margin", margin)):
        check_number(name, value, integer=True)
    check_number("margin", margin, at_least=0)
    frames, height, width = spikes.shape
    options = ReconstructOptions(window=length, every=every, start=start, stop=stop, region=region)
    options.check()
    if length > frames:
        raise InputError(f"--window {length} is longer than the recording ({frames} frames)")
    attrs = spikes.attrs
    part = job_part(options, frames, float(attrs["fps"]), height, width, attrs["cfa"])
    y0, y1, x0, x1 = part.region
    around = (max(y0 - margin, 0), min(y1 + margin, height), max(x0 - margin, 0) // 8 * 8, min(x1 + margin, width))
    half = length // 2
    first, last = part.centres[0] - half, part.centres[-1] + half + 1  # the spike frames the windows read
    read = spikes.data[first:last, around[0]:around[1], around[2]:around[3]]
    read = read.rechunk({0: da.overlap.ensure_minimum_chunksize(half + 1, read.chunks[0])}) if half else read
    starts = np.cumsum((0, *read.chunks[0]))  # each chunk's first frame, relative to ``first``
    centres = np.asarray(part.centres) - first
    counts = tuple(int(n) for n in np.diff(np.searchsorted(centres, starts)))  # windows centred in each chunk
    data = da.map_overlap(_windows_of, read, depth={0: half, 1: 0, 2: 0}, boundary="none", trim=False,
                          new_axis=1, chunks=(counts, (length,), read.chunks[1], read.chunks[2]), dtype=bool,
                          meta=np.empty((0, 0, 0, 0), bool), starts=tuple(int(s) for s in starts),
                          centre0=int(centres[0]), centre1=int(centres[-1]), every=every, half=half, align_arrays=False)
    times = spikes.coords["t"].values
    frame0 = int(spikes.coords["frame"].values[0])
    out = xr.DataArray(
        data, dims=WINDOW_DIMS, name="windows",
        coords={"t": ("t", times[part.centres], {"units": "s", "meaning": "time of the window's centre"}),
                "frame": ("t", np.asarray(part.centres, np.int64) + frame0),
                "dt": ("dt", np.arange(-half, half + 1), {"units": "spike frames from the centre"}),
                "y": np.arange(around[0], around[1]), "x": np.arange(around[2], around[3])},
        attrs={**attrs, "window": length, "every": every, "start": part.start, "stop": part.stop,
               "region": list(part.region), "first": part.first, "frames": frames, "height": height, "width": width})
    if attrs.get("gain") is None:  # the job's automatic exposure: the whole frame's middle window, made when needed
        out.coords["auto_gain"] = ((), _whole_recording_gain(spikes.data, length, every, attrs["reset"]))
    return out


def _windows_of(block: np.ndarray, *, starts: tuple[int, ...], centre0: int, centre1: int, every: int, half: int,
                block_info=None) -> np.ndarray:
    """(n + overlap, h, w) frames of one chunk and ``half`` of each neighbour's (none beyond the recording) ->
    (windows, 2*half + 1, h, w): the windows centred in the chunk (at ``centre0 + j * every``, up to ``centre1``)."""
    k = block_info[0]["chunk-location"][0]
    core, end = starts[k], starts[k + 1]
    origin = max(core - half, 0)  # the block's first frame ('none' boundary: no overlap before the first chunk)
    j0 = max(0, -(-(core - centre0) // every))
    centres = range(centre0 + j0 * every, min(end, centre1 + 1), every)
    out = np.empty((len(centres), 2 * half + 1, *block.shape[1:]), bool)
    for n, centre in enumerate(centres):
        out[n] = block[centre - half - origin : centre + half + 1 - origin]
    return out


def _whole_recording_gain(bits: da.Array, length: int, every: int, reset: str) -> da.Array:
    """0-d lazy: the automatic exposure of the whole recording's middle window, whole frame (the job's rule, so
    every part of a recording is exposed alike)."""
    whole = output_centres(bits.shape[0], length, every)
    centre, half = whole[len(whole) // 2], length // 2
    window = bits[centre - half : centre + half + 1].rechunk(-1)
    return window.map_blocks(_gain_of, bits.shape[2], reset, drop_axis=(0, 1, 2), dtype=np.float64,
                             meta=np.empty((), np.float64))


def _gain_of(window: np.ndarray, width: int, reset: str) -> np.ndarray:
    return np.float64(auto_gain(tfp_rate(pack_rows(window), width, reset)))


def check_windows(win, what: str = "windows") -> xr.DataArray:
    if not isinstance(win, xr.DataArray):
        raise InputTypeError(f"{what} must be an xarray.DataArray of windows (lazy.windows), got {type(win).__name__}")
    if win.dims != WINDOW_DIMS or win.dtype != bool or not isinstance(win.data, da.Array):
        raise InputError(f"{what} must be lazy windows (t, dt, y, x) bool as lazy.windows gives, got {win.dims} "
                         f"{win.dtype}")
    if missing := [k for k in ("window", "every", "region", "frames", "fps", "cfa", "reset") if k not in win.attrs]:
        raise InputError(f"{what} lack the attributes lazy.windows gives ({', '.join(missing)}): keep its attrs")
    return win


# ---- reconstructions ----

@dataclasses.dataclass(frozen=True)
class FunctionReconstructor:
    """A user's own method as a :class:`stages.reconstruction.methods.Reconstructor`: ``func(window) -> image``, ``window`` (N, h, w)
    bool (a tile and its halo), ``image`` (scale*h, scale*w, 3) uint8."""

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


@dataclasses.dataclass(frozen=True)
class _Method:
    """What a task needs to build its reconstructor (once per worker process): a name and weights, or the user's."""

    method: str
    weights: str | None = None
    precision: str | None = None
    backend: str | None = None
    weights_sha256: str | None = None
    fast_gpu: bool = False
    own: FunctionReconstructor | None = None

    def built(self) -> Reconstructor:
        if self.own is not None:
            return self.own
        from pipeline.jobs.reconstruct_tasks import reconstructor

        return reconstructor(self.method, self.weights, self.precision, self.backend, self.weights_sha256,
                             fast_gpu=self.fast_gpu)


def tfp(win: xr.DataArray, *, gain: float | None = None, scale: int | None = None, tile: int | None = None) -> xr.DataArray:
    """TFP of every window (``reconstruct(win, method="tfp")``)."""
    return reconstruct(win, method="tfp", gain=gain, scale=scale, tile=tile)


def tfi(win: xr.DataArray, *, gain: float | None = None, scale: int | None = None, tile: int | None = None) -> xr.DataArray:
    """TFI of every window (``reconstruct(win, method="tfi")``)."""
    return reconstruct(win, method="tfi", gain=gain, scale=scale, tile=tile)


def reconstruct(win: xr.DataArray, *, method: str = "cscsr", weights: str | None = None, tile: int | None = None,
                precision: str = "fp32", backend: str = "torch", gain: float | None = None,
                scale: int | None = None) -> xr.DataArray:
    """Every window reconstructed by ``method`` (tfp, tfi, cscsr, cscsr-ensemble) as the job does it: (t, y, x, rgb)
    uint8 at ``scale`` (default the recording's, else 4), one block per (the job's task of frames, tile), each tile
    read with the method's halo. ``weights`` (the network's): default ``full`` where a ``distributed`` client has
    GPU workers (the tasks then carry the ``GPU`` resource the jobs' network tasks ask for, and run there), else
    ``lite``. ``gain``: default the recording's, else the job's automatic exposure. Lazy."""
    win = check_windows(win)
    check_text("method", method)
    options = ReconstructOptions(method=method, every=win.attrs["every"], window=win.attrs["window"], gain=gain,
                                 scale=scale, tile=tile, weights=weights, precision=precision, backend=backend)
    options.check()
    from pipeline.jobs.reconstruct import network_options, placed, placement, reconstructor, sized

    where = placement(options, _active_client())
    options = placed(options, where, {})
    precision_, backend_ = network_options(options)
    built = reconstructor(options.method, options.weights, precision_, backend_, device="cpu")  # checks the weights
    scale = options.scale if options.scale is not None else int(win.attrs.get("scale", 4))
    built.check(options.window, scale, win.attrs["cfa"])
    y0, y1, x0, x1 = win.attrs["region"]
    options = sized(options, where, built, (y1 - y0, x1 - x0), {})
    spec = _Method(options.method, built.weights, precision_, backend_, built.weights_sha256,
                   bool(options.fast_gpu and where.gpus) if options.method in NETWORKS else False)
    gpu = where.gpus and options.method in NETWORKS
    return _reconstructed(win, spec, built, scale, options.tile, gain, options.gpu_batch, gpu,
                          fast_gpu=spec.fast_gpu if options.method in NETWORKS else None)


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
    if tile is not None:
        ReconstructOptions(tile=tile).check()
    name = getattr(func, "__name__", type(func).__name__)
    own = FunctionReconstructor(func, scale, halo, name)
    y0, y1, x0, x1 = win.attrs["region"]
    return _reconstructed(win, _Method(name, own=own), own, scale, tile or max(y1 - y0, x1 - x0, 8) // 8 * 8 + 8,
                          gain, 1, False, fast_gpu=None)


def _reconstructed(win: xr.DataArray, spec: _Method, built: Reconstructor, scale: int, tile: int, gain, most: int,
                   gpu: bool, *, fast_gpu: bool | None) -> xr.DataArray:
    """The graph of :func:`reconstruct` and :func:`apply`: the windows' frames grouped as the job's tasks group them
    (the network's ``batch``), a blockwise map per tile of the job's grid reading its halo, tiles put together."""
    attrs = win.attrs
    height, width, cfa = attrs["height"], attrs["width"], attrs["cfa"]
    region = tuple(attrs["region"])
    oy, ox = int(win.coords["y"][0]), int(win.coords["x"][0])
    grid = tile_grid(height, width, tile, built.halo, region)
    if any(t.ry0 < oy or t.rx0 < ox or t.ry1 > oy + win.shape[2] or t.rx1 > ox + win.shape[3] for row in grid for t in row):
        raise InputError(f"{spec.method} reads {built.halo} LR pixels around each tile, more than the windows keep "
                         f"around their region: make them with lazy.windows(..., margin={built.halo})")
    gain = _gain(win, gain)
    data = win.data.rechunk({1: -1, 2: -1, 3: -1})
    data = data.rechunk({0: _task_frames(data.chunks[0], built.batch, attrs["first"])})
    annotation = dask.annotate(resources={GPU: GPU_SHARE}) if gpu else contextlib.nullcontext()
    rows = []
    with annotation:
        for row in grid:
            rows.append([])
            for t in row:
                read = data[:, :, t.ry0 - oy : t.ry1 - oy, t.rx0 - ox : t.rx1 - ox]
                ys, xs = t.crop(scale)
                rows[-1].append(read.map_blocks(
                    _reconstruct_block, spec, gain, t.rx1 - t.rx0, cfa, attrs["reset"], scale, (ys, xs), most,
                    chunks=(read.chunks[0], ((t.y1 - t.y0) * scale,), ((t.x1 - t.x0) * scale,), (3,)),
                    dtype=np.uint8, meta=np.empty((0, 0, 0, 0), np.uint8)))
    hr = da.concatenate([da.concatenate(row, axis=2) for row in rows], axis=1)  # tiles side by side, rows down
    plan = Plan(attrs.get("store") or "", "", spec.method, built.weights, attrs["window"], attrs["every"], np.nan, scale,
                cfa, attrs["reset"], tile, "", spec.precision, most, spec.backend, fast_gpu,
                source_identity=attrs.get("identity"), source_shape=(attrs["frames"], height, width),
                weights_sha256=built.weights_sha256, start=attrs["start"], stop=attrs["stop"], region=region)
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
        return float(gain)
    if win.attrs.get("gain") is not None:
        return float(win.attrs["gain"])
    return win.coords["auto_gain"].data


def _task_frames(chunks: tuple[int, ...], batch: int, first: int) -> tuple[int, ...]:
    """Chunks of output frames for a method that reconstructs ``batch`` windows together: the job's task groups
    (``reconstruct_plan.task_groups``: batches of the whole recording's output frames, from index ``first`` on), so
    that each batch holds the windows it holds in the job (a network's numbers can depend on the batch); any
    chunking (empty chunks dropped) where windows are reconstructed one at a time."""
    total = sum(chunks)
    if batch == 1:
        return tuple(n for n in chunks if n) or (0,)
    cut = [max(start, 0) for start in range(-(first % batch), total, batch)] + [total]
    return tuple(b - a for a, b in zip(cut, cut[1:]))


def _reconstruct_block(block: np.ndarray, spec: _Method, gain, width: int, cfa: str, reset: str, scale: int,
                       crop: tuple[slice, slice], most: int) -> np.ndarray:
    """Task: (n, N, h, w) bool windows of one tile with its halo -> (n, tile_h*s, tile_w*s, 3) uint8, the halo cropped."""
    method = spec.built()
    windows = [Window(pack_rows(window), width, cfa, reset, float(gain), scale) for window in block]
    images = method.many_tiles([windows], most)[0] if windows else []
    ys, xs = crop
    out = np.empty((len(images), ys.stop - ys.start, xs.stop - xs.start, 3), np.uint8)
    for n, image in enumerate(images):
        out[n] = image[ys, xs]
    return out


def _active_client():
    """The ``distributed`` client dask would compute on now, or None (dask's default scheduler)."""
    try:
        from distributed import default_client

        return default_client()
    except (ImportError, ValueError):
        return None


# ---- the video store ----

def to_video(hr: xr.DataArray, url: str, *, overwrite: bool = False, resume: bool = False,
             progress: bool = False) -> dict:
    """Write ``hr`` (t, y, x, rgb) uint8 as a video store at ``url`` (the job's format: ``video`` one chunk per
    (frame, tile) of ``hr``'s chunks, ``frames``, ``committed``, the attributes, ``state``), computed on the active
    ``distributed`` client if there is one, else on dask's default scheduler, ``BLOCKS_AT_ONCE`` blocks a round. Each
    block is written, then committed; ``resume=True`` continues a store a failed or killed call left, computing
    only the blocks not committed (the same bytes as one uninterrupted call). -> {frames, tasks_run, tasks_skipped}.
    """
    hr = _check_video(hr)
    if not isinstance(url, str):
        raise InputTypeError(f"url must be a path or URL as a string, got {url!r}")
    check_flag("overwrite", overwrite)
    check_flag("resume", resume)
    if resume and overwrite:
        raise InputError("--resume and --overwrite contradict each other: choose one")
    if resume and not exists(url):
        raise InputError(f"cannot resume: {url} does not exist")
    check_place(url)
    data = _tiled(hr.data)
    n, height, width, _ = data.shape
    tile_hr = (data.chunks[1][0], data.chunks[2][0])
    tiles = (len(data.chunks[1]), len(data.chunks[2]))
    centres = [int(c) for c in hr.coords["frame"].values]
    gain = hr.coords["gain"].data if "gain" in hr.coords else None
    attrs = {**hr.attrs, "gain": None if gain is None else float(dask.compute(gain)[0])}
    fps = attrs.get("fps")
    with claimed(url), new_output(url, overwrite=overwrite, kind=VIDEO_STORE, flag="--resume or --overwrite",
                                  resume=resume, keep_partial=True):
        if resume:
            done = _resumable(url, attrs, n, tiles)
        else:
            create_video_store(url, centres=centres, hr_size=(height, width), tile_hr=tile_hr, tiles=tiles,
                               attrs={k: v for k, v in attrs.items() if k != "fps"}, fps=fps)
            done = np.zeros((n, *tiles), bool)
        starts = np.cumsum((0, *data.chunks[0]))
        blocks = [(b, ty, tx) for b in range(len(data.chunks[0])) for ty in range(tiles[0]) for tx in range(tiles[1])
                  if data.chunks[0][b] and not done[starts[b]:starts[b + 1], ty, tx].all()]
        # one task per block of ``hr``: write its frames' chunks of its tile, then commit them
        written = data.map_blocks(_write_block, url, uuid.uuid4().hex, tuple(int(s) for s in starts), tile_hr,
                                  chunks=tuple((1,) * len(c) for c in data.chunks), dtype=np.int64,
                                  meta=np.empty((0, 0, 0, 0), np.int64))
        with held(url), progress_bar(f"to_video {url}", len(blocks), unit="blocks", enabled=progress) as advance:
            for at in range(0, len(blocks), BLOCKS_AT_ONCE):
                chosen = blocks[at : at + BLOCKS_AT_ONCE]
                dask.compute(*(written.blocks[b, ty, tx, 0] for b, ty, tx in chosen),
                             optimize_graph=not _annotated(data))
                advance(len(chosen))
        remove_partial_writes(url)
        open_video_store(url, writable=True).attrs["state"] = "complete"
    return {"frames": n, "tasks_run": len(blocks), "tasks_skipped": int(done.sum())}


def _check_video(hr) -> xr.DataArray:
    if not isinstance(hr, xr.DataArray):
        raise InputTypeError(f"hr must be an xarray.DataArray (t, y, x, rgb) uint8, got {type(hr).__name__}")
    if hr.dims != VIDEO_DIMS or hr.dtype != np.uint8 or hr.shape[3] != 3:
        raise InputError(f"hr must be (t, y, x, rgb) uint8 with 3 colours, got {hr.dims} {hr.dtype} {hr.shape}")
    if not isinstance(hr.data, da.Array):
        raise InputError("hr must be dask-backed (a lazy reconstruction, or .chunk() a DataArray in memory)")
    if "frame" not in hr.coords or hr.shape[0] == 0:
        raise InputError("hr needs its output frames' centre spike frames (coordinate frame, as lazy.reconstruct "
                         "gives) and at least one frame")
    return hr


def _tiled(data: da.Array) -> da.Array:
    """``data`` with tiles of one size (but the last row and column): as they are if so, else rechunked."""
    def regular(chunks: tuple[int, ...]) -> bool:
        return all(c == chunks[0] for c in chunks[:-1]) and chunks[-1] <= chunks[0]

    if regular(data.chunks[1]) and regular(data.chunks[2]) and len(data.chunks[3]) == 1:
        return data
    return data.rechunk({1: data.chunks[1][0], 2: data.chunks[2][0], 3: -1})


def _annotated(data: da.Array) -> bool:
    """Whether a layer of the graph asks for resources (GPU workers): then computed unoptimised, since fusing
    blockwise layers drops their annotations."""
    return any(getattr(layer, "annotations", None) for layer in data.__dask_graph__().layers.values())


def _resumable(url: str, attrs: dict, n: int, tiles: tuple[int, int]) -> np.ndarray:
    """The commit mask of the store to resume, refused unless it was made with the same attributes and layout."""
    group = open_video_store(url, writable=True)
    changed = [k for k, v in attrs.items() if k != "fps" and group.attrs.get(k) != v]
    if changed or group["committed"].shape != (n, *tiles):
        what = ", ".join(f"{k} {group.attrs.get(k)!r} -> {attrs[k]!r}" for k in changed) or "layout"
        raise InputError(f"cannot resume {url}: it was made with other parameters ({what})")
    return committed_mask(group)


@functools.lru_cache(maxsize=4)
def _writer(url: str, run: str) -> TileWriter:
    """The output store opened once per worker process and call (``run``)."""
    return TileWriter(url)


def _write_block(block: np.ndarray, url: str, run: str, starts: tuple[int, ...], tile_hr: tuple[int, int],
                 block_id: tuple[int, int, int, int]) -> np.ndarray:
    """Task: write the frames of one block (its tile of output frames ``starts[b]``, ...; a chunk each), then commit
    them. -> (1, 1, 1, 1): how many frames."""
    b, ty, tx, _ = block_id
    _writer(url, run).write_frames(starts[b], (ty, tx), (ty * tile_hr[0], tx * tile_hr[1]), list(block))
    return np.full((1, 1, 1, 1), len(block), np.int64)
