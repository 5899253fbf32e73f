"""Lazy reconstructions written and read back: :func:`to_video` writes ``hr`` (t, y, x, rgb) as the ``reconstruct``
job's video store (the same layout, record and commit per block: the job, ``info``, ``export`` and ``evaluate`` read
it, and each can resume the other's); :func:`open_video` gives a written store back as the ``hr`` that wrote it.
"""

import dataclasses
import sys
import uuid

import dask
import dask.array as da
import numpy as np
import xarray as xr
from dask.base import tokenize

from pipeline.compute.executor import computed
from pipeline.compute.progress import progress_bar
from pipeline.jobs.reconstruct_tasks import finish_video, run_blocks, write_block
from pipeline.lazy.spikes import (StoreReader, check_coordinates, check_here, check_times, distributed_client,
                                  place, run_of, stores_read)
from pipeline.lazy.video import VIDEO_DIMS, tile_blocks
from pipeline.lazy.windows import _output_part
from pipeline.stores.lease import claimed, held
from pipeline.stores.outputs import VIDEO_STORE, new_output
from pipeline.stores.storage import check_apart, exists, open_group
from pipeline.stores.video_store import (COMMITTED, VIDEO, create_video_store, lost_frames, resumed_mask,
                                         open_video_store, video_identity)
from stages.errors import InputError, InputTypeError
from stages.numbers import check_flag

BLOCKS_AT_ONCE = 256  # blocks to_video computes and writes a round (but a store's reconstruction on a cluster)


def to_video(hr: xr.DataArray, url, *, overwrite: bool = False, resume: bool = False,
             progress: bool = False) -> dict:
    """Write ``hr`` (t, y, x, rgb) uint8 as a video store at ``url``, in the job's format (one chunk per (frame,
    tile) of ``hr``'s chunks, ``committed``, the attributes, ``state``), on the active ``distributed`` client if
    there is one, else on dask's default scheduler. On a client, a reconstruction read from a store as
    ``lazy.reconstruct`` made it runs as the ``reconstruct`` job runs (``reconstruct_tasks.run_blocks``); anything
    else runs ``BLOCKS_AT_ONCE`` blocks a round (``executor.computed``). Each block is checked against its chunk
    (shape, uint8), written, then committed. On a client a block that fails does not stop the others, and the call
    fails naming the output frames lost (``JobIncomplete``); on dask's own scheduler the first error stops it.
    ``resume=True`` continues what a failed or killed call left, computing only the blocks not committed (the bytes
    of one uninterrupted call), and refuses a store written by another graph (``committed``'s ``graph``: the token of
    ``hr``'s graph). -> {frames, tasks_run, tasks_skipped}, in the job's tasks (a frame's tile; the network's batch
    of frames). ``progress=True``: a bar on a terminal, a line every ``BLOCKS_AT_ONCE`` blocks where stderr is piped.

    ``hr`` may be a selection (``isel``/``sel``) of a reconstruction: a contiguous increasing run of output frames
    (recorded as its ``start``/``stop``) and of whole LR pixels (recorded as its ``region``). Anything else is
    refused in one line before anything is written.
    """
    hr = _check_video(hr)
    url = place(url)
    check_flag("overwrite", overwrite)
    check_flag("resume", resume)
    check_flag("progress", progress)
    if resume and overwrite:
        raise InputError("resume=True and overwrite=True contradict each other: choose one")
    if resume and not exists(url):
        raise InputError(f"cannot resume: {url} does not exist")
    check_apart(url, hr.attrs.get("source"), *stores_read(hr.data))
    check_here([url, hr.attrs.get("source")], hr.data)
    if resume:
        _open_to_resume(url)
    attrs = {**hr.attrs, **_selected_part(hr)}
    data = _tiled(hr.data)
    n, height, width, _ = data.shape
    tile_hr = (data.chunks[1][0], data.chunks[2][0])
    tiles = (len(data.chunks[1]), len(data.chunks[2]))
    centres = [int(c) for c in hr.coords["frame"].values]
    gain = hr.coords["gain"].data if "gain" in hr.coords else None
    from_store = tile_blocks(data)
    if from_store is not None and gain is None:
        raise InputError("hr lacks its gain coordinate, the exposure its blocks are reconstructed with: keep the "
                         "coordinates lazy.reconstruct gives")
    client = distributed_client(hr.data)
    attrs["gain"] = None if gain is None else float(dask.compute(gain, optimize_graph=False)[0])  # its key: the job's
    computed_gain = {gain.__dask_keys__()[0]: attrs["gain"]} if isinstance(gain, da.Array) else {}  # not made again
    fps = attrs.get("fps")
    graph = graph_token(hr.data)
    with claimed(url), new_output(url, overwrite=overwrite, kind=VIDEO_STORE, flag="resume=True or overwrite=True",
                                  resume=resume, keep_partial=True):
        if resume:
            done = _resumable(url, attrs, n, tiles, graph)
        else:
            create_video_store(url, centres=centres, hr_size=(height, width), tile_hr=tile_hr, tiles=tiles,
                               attrs={k: v for k, v in attrs.items() if k != "fps"}, fps=fps, graph=graph)
            done = np.zeros((n, *tiles), bool)
        starts = np.cumsum((0, *data.chunks[0]))
        blocks = [(b, ty, tx) for b in range(len(data.chunks[0])) for ty in range(tiles[0]) for tx in range(tiles[1])
                  if data.chunks[0][b] and not done[starts[b]:starts[b + 1], ty, tx].all()]
        run = uuid.uuid4().hex
        # counted in the job's tasks (TileBlocks.task_counts): a block along time and a pass of its tiles, for a
        # store's reconstruction (a share of the pass a tile), else a block
        if from_store is not None:
            to_run, total = from_store.task_counts(done)
            share = {tile: 1 / len(tiles) for tiles in from_store.passes for tile in tiles}
        else:
            to_run, total = len(blocks), sum(1 for c in data.chunks[0] if c) * tiles[0] * tiles[1]
            share = {}
        unit_of = {block: share.get(block[1:], 1) for block in blocks}
        piped = progress and not sys.stderr.isatty()  # no bar to draw: a line every BLOCKS_AT_ONCE blocks
        failed, finished, finished_units = {}, 0, 0
        with held(url), progress_bar(f"to_video {url}", total, done=total - to_run, unit="tasks",
                                     enabled=progress) as advance:
            def outcome(block: tuple[int, int, int], error: str | None = None) -> None:
                nonlocal finished, finished_units
                b, ty, tx = block
                if error is not None:
                    failed.update({i: f"tile ({ty}, {tx}): {error}" for i in range(starts[b], starts[b + 1])})
                elif block in unit_of:  # a GPU pass also rewrites the tiles it shares with one not committed
                    advance(unit_of[block])
                    finished_units += unit_of[block]  # as the bar: written ones
                finished += 1
                if piped and (finished % BLOCKS_AT_ONCE == 0 or finished == len(blocks)):
                    print(f"to_video {url}: {round(total - to_run + finished_units)} of {total} tasks",
                          file=sys.stderr, flush=True)

            if from_store is not None and client is not None:  # as the job runs it: the executor's window, each
                # pass's one task made as it moves, the exposure computed (a cluster's restart forgets a held one)
                from_store = dataclasses.replace(from_store, gain=attrs["gain"])
                for done_tile in run_blocks(client, from_store.units(done), blocks=from_store, out=url, run=run):
                    outcome((done_tile.block, done_tile.ty, done_tile.tx), done_tile.error)
            else:  # BLOCKS_AT_ONCE blocks a round, a round's graph culled at once (its blocks share what they read)
                written = _written(data, url, run)
                keys = {(written.name, *block, 0): block for block in blocks}
                graph = dict(written.__dask_graph__().cull(set(keys)))
                computed(graph | {key: value for key, value in computed_gain.items() if key in graph}, keys, outcome,
                         client, BLOCKS_AT_ONCE, failed=outcome)
        finish_video(url, failed, n, again="to_video(..., resume=True)")
    return {"frames": n, "tasks_run": to_run, "tasks_skipped": total - to_run}


def graph_token(data: da.Array) -> str:
    """What identifies ``data``'s graph: its name (Dask's token of every layer's function and arguments) and chunks."""
    return tokenize(data.name, data.chunks)


def _open_to_resume(url: str) -> None:
    """Refuse, in one line, resuming what is not a video store (a file, a folder, a spike store)."""
    try:
        open_video_store(url)
    except InputError as error:
        raise InputError(f"cannot resume {url}: {error}") from None
    except (OSError, ValueError, TypeError) as error:
        raise InputError(f"cannot resume {url}: it is not a video store ({type(error).__name__}): give the store a "
                         f"to_video call left, or another url") from None


def _selected_part(hr: xr.DataArray) -> dict:
    """The ``start``/``stop`` and ``region`` a selection of a reconstruction holds (none where it is all of it); one
    line for a selection that cannot be written as one, or whose coordinates were changed."""
    attrs, changed = hr.attrs, {}
    if isinstance(attrs.get("fps"), (int, float)) and isinstance(attrs.get("every"), int):
        check_times(hr, attrs["fps"] * attrs["every"], "hr", "lazy.reconstruct")  # t: the centre's time
    if all(isinstance(attrs.get(k), int) for k in ("every", "window")) and attrs.get("source_shape"):
        part = _output_part(hr.coords["frame"].values, {**attrs, "frames": attrs["source_shape"][0]}, "hr")
        changed.update({k: part[k] for k in ("start", "stop")})
    else:
        frames = np.asarray(hr.coords["frame"].values)
        if frames.size > 1 and not (np.diff(frames) > 0).all():
            raise InputError("hr's output frames repeat or run backwards (coordinate frame): only increasing "
                             "frames are written")
    scale, region = attrs.get("scale"), attrs.get("region")
    if isinstance(scale, int) and region is not None:
        check_coordinates(hr, ("y", "x"), "hr", "lazy.reconstruct")
        box = []
        for dim, (lo, hi) in zip(("y", "x"), (region[:2], region[2:])):
            a, b = run_of(hr.coords[dim].values, dim, "hr")
            if a < lo * scale or b > hi * scale:
                raise InputError(f"hr holds HR {dim} {a}:{b}, outside the {lo * scale}:{hi * scale} it was made of "
                                 f"(region {lo}:{hi} at scale {scale}): its {dim} coordinate was changed "
                                 f"(assign_coords?): keep the coordinates lazy.reconstruct gives")
            if a % scale or b % scale:
                raise InputError(f"hr is a selection of HR {dim} {a}:{b}, which cuts through LR pixels (scale={scale}):"
                                 f" select whole ones ({dim} a multiple of {scale} at both ends)")
            box += [a // scale, b // scale]
        cfa = attrs.get("cfa")
        if cfa not in (None, "mono") and (odd := [f"{dim} {v}" for dim, v in zip(("y0", "y1", "x0", "x1"), box)
                                                  if v % 2]):
            raise InputError(f"hr is a selection of LR {', '.join(odd)}, odd: the {cfa} colour pattern repeats every 2 "
                             f"pixels and a region of it starts and ends on even ones (HR multiples of {2 * scale})")
        changed["region"] = box
    return {k: v for k, v in changed.items() if attrs.get(k) != v}


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


def _resumable(url: str, attrs: dict, n: int, tiles: tuple[int, int], graph: str) -> np.ndarray:
    """The commit mask of the store to resume, refused unless it was made with the same attributes and layout, by
    the same graph (where it records one: a job's does not)."""
    group = open_video_store(url, writable=True)
    done = resumed_mask(group, url, {k: v for k, v in attrs.items() if k != "fps"}, dict(group.attrs), (n, *tiles))
    if group[COMMITTED].attrs.get("graph", graph) != graph:
        raise InputError(f"cannot resume {url}: hr is not the graph that wrote it (a function, a selection or an "
                         f"input changed; or a function holds something Dask cannot hash): write it again with "
                         f"overwrite=True")
    return done


def _written(data: da.Array, url: str, run: str) -> da.Array:
    """A task per block of ``data`` (t, y, x, rgb) uint8 that writes it into the video store at ``url``
    (``reconstruct_tasks.write_block``) -> (blocks along t, tile rows, tile columns, 1) int64, the frames each wrote."""
    from dask._task_spec import Task, TaskRef
    from dask.highlevelgraph import HighLevelGraph

    name, starts = f"write-{run}", np.cumsum((0, *data.chunks[0]))
    tile_hr = (data.chunks[1][0], data.chunks[2][0])
    layer = {}
    for b, frames in enumerate(data.chunks[0]):
        for ty, rows in enumerate(data.chunks[1]):
            for tx, columns in enumerate(data.chunks[2]):
                key = (name, b, ty, tx, 0)
                layer[key] = Task(key, write_block, TaskRef((data.name, b, ty, tx, 0)), url, run, int(starts[b]),
                                  (ty, tx), (ty * tile_hr[0], tx * tile_hr[1]), (frames, rows, columns, 3))
    return da.Array(HighLevelGraph.from_collections(name, layer, dependencies=[data]), name,
                    tuple((1,) * len(c) for c in data.chunks), meta=np.empty((0, 0, 0, 0), np.int64))


STORED = "video-"  # the name of the array open_video reads; "original-" + it: its layer holding the _StoredVideo
STORE_ONLY = ("gain", "format_version", "cscsr_version", "state")  # attributes of a store, not of the hr it holds


def open_video(url) -> xr.DataArray:
    """The video store at ``url`` as the lazy ``hr`` that wrote it: (t, y, x, rgb) uint8, a dask chunk per stored
    chunk, nothing read but metadata; coordinates ``t`` (seconds), ``frame`` (the centre spike frame), ``y``/``x``
    (the recording's HR pixels; from 0 in a store from before ``region``) and ``gain``; ``attrs`` as ``hr.attrs``.
    Refuses, in one line, what is not a video store, a damaged one, and one whose writer did not finish."""
    url = place(url)
    check_here([url])
    group = open_video_store(url)
    attrs = dict(group.attrs)
    if attrs.get("state") != "complete":
        raise InputError(f"video store {url} is incomplete (state {attrs.get('state')!r}): its writer did not finish; "
                         f"finish it with to_video(..., resume=True) or cscsr reconstruct --resume")
    if lost := lost_frames(group):  # a listing, no chunk read: a lost chunk would read as black
        raise InputError(f"video store {url} has lost data: {lost}: make it again")
    video, frames = group["video"], np.asarray(group["frames"][:], np.int64)
    n, height, width, _ = video.shape
    identity = video_identity(group)
    data = da.from_array(_StoredVideo(url, identity, video.shape), chunks=video.chunks, asarray=False, fancy=False,
                         meta=np.empty((0, 0, 0, 0), np.uint8), name=f"{STORED}{tokenize(url, identity)}")
    scale, region, every, fps = (attrs.get(k) for k in ("scale", "region", "every", "fps"))
    y0, x0 = (region[0] * scale, region[2] * scale) if region and isinstance(scale, int) else (0, 0)
    coords = {"frame": ("t", frames), "y": np.arange(y0, y0 + height), "x": np.arange(x0, x0 + width)}
    if isinstance(fps, (int, float)) and isinstance(every, int):
        spike_fps = fps * every  # the recording's rate (the store records output frames per second)
        spike_fps = float(round(spike_fps)) if abs(spike_fps - round(spike_fps)) < 1e-9 * spike_fps else spike_fps
        coords["t"] = ("t", frames / spike_fps, {"units": "s", "meaning": "time of the window's centre"})
    if attrs.get("gain") is not None:
        coords["gain"] = ((), float(attrs["gain"]))
    return xr.DataArray(data, dims=VIDEO_DIMS, name="video", coords=coords,
                        attrs={k: v for k, v in attrs.items() if k not in STORE_ONLY})


class _StoredVideo(StoreReader):
    """A video store's ``video`` as dask reads it, a block at a time (``da.from_array``), each read refused if the
    store at ``url`` is no longer the one opened (``video_identity``: gone, or replaced by another reconstruction;
    its metadata read again: a few milliseconds a block)."""

    ndim, dtype = 4, np.dtype(np.uint8)

    def __init__(self, url: str, identity: str, shape: tuple[int, ...]):
        self.url, self.identity, self.shape = url, identity, shape

    def __getitem__(self, key: tuple[slice, ...]) -> np.ndarray:
        try:
            group = open_group(self.url, "video store")
            same = video_identity(group) == self.identity
        except (InputError, KeyError):
            same = False
        if not same:
            raise InputError(f"video store {self.url} is not the one this graph was opened on (it was replaced, "
                             f"written again or removed since): open it again")
        return group[VIDEO][key]
