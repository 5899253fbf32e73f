"""Windows as lazy xarray: the output frames of the ``reconstruct`` job, each the 41 (``length``) spike frames
around its centre, and the rule for selections of spikes and of windows.

A selection (``isel``/``sel``) is honoured exactly or refused in one line: a contiguous increasing run of frames
and of pixels is the part of the recording it holds, in the recording's numbers (the ``frame``, ``y`` and ``x``
coordinates); anything else (steps, repeats, reversed or shuffled frames, a cut through the colour pattern's phase,
a selection along ``dt``) is refused. The output frames, ranges and regions are the job's
(``pipeline.jobs.reconstruct_plan.job_part``).
"""

import dask.array as da
import numpy as np
import xarray as xr
from dask.base import tokenize
from dask.utils import key_split

from pipeline.jobs.reconstruct_plan import ReconstructOptions, job_part
from pipeline.jobs.reconstruct_tasks import WINDOW_BLOCKS, gain_task, store_gain
from pipeline.lazy.spikes import (check_coordinates, check_spikes, check_times, open_spikes, python_words, run_of,
                                  selection)
from stages.capture.bits import pack_rows
from stages.errors import InputError, InputTypeError
from stages.numbers import check_number
from stages.reconstruction.colour import auto_gain
from stages.reconstruction.methods import WINDOW, middle_centre
from stages.reconstruction.tfp import tfp_rate

MARGIN = 32  # LR pixels kept around a region: the largest halo of a built-in method (the network's, HALO)
WINDOW_DIMS = ("t", "dt", "y", "x")
AS_STORED = ("getitem", "rechunk-merge", "rechunk-split", "rechunk-p2p")  # graph layers that keep a store's values


def windows(spikes: xr.DataArray, length: int = WINDOW, every: int = WINDOW, start=None, stop=None, region=None,
            *, margin: int = MARGIN) -> xr.DataArray:
    """The windows of the output frames ``cscsr reconstruct --window LENGTH --every EVERY --start --stop --region``
    makes of ``spikes``: (t, dt, y, x) bool, output frame ``t`` (coordinate: its centre's time; ``frame``: its centre
    spike frame) seeing spike frames ``centre + dt``. The time overlap of neighbouring windows is dask's
    (``map_overlap`` along t), not a copy of the recording. With a region, its LR pixels and ``margin`` more on every
    side where the frame has them (the context a method's halo reads). Lazy: nothing is read.

    ``spikes`` may be a selection of a recording (``isel``/``sel``): a contiguous increasing run of frames and of
    pixels, in the recording's numbers: the windows of the recording's output frames whose whole window it holds, the
    selected pixels the frame's edges, the automatic gain the whole recording's. Refused in one line: steps, repeats,
    reversed or shuffled frames or pixels, and (a Bayer CFA) pixels that start or end on an odd row or column."""
    spikes = check_spikes(spikes)
    for name, value in (("length", length), ("every", every), ("margin", margin)):
        check_number(name, value, integer=True)
    check_number("margin", margin, at_least=0)
    chosen = selection(spikes)
    frames, height, width = chosen.shape
    attrs = spikes.attrs
    cfa = attrs["cfa"]
    by0, by1, bx0, bx1 = chosen.box
    if cfa != "mono" and (odd := [f"{n}={v}" for n, v in (("y", by0), ("x", bx0)) if v % 2]
                          + [f"{n} end {v}" for n, v in (("y", by1), ("x", bx1)) if v % 2]):
        raise InputError(f"spikes are a selection at {', '.join(odd)}: the {cfa} colour pattern repeats every 2 "
                         f"pixels, so a selection starts and ends on even rows and columns (its colour phase)")
    options = ReconstructOptions(window=length, every=every, start=start, stop=stop, region=region)
    with python_words(window="length"):
        options.check()
        if length > chosen.f1 - chosen.f0:
            selected = "" if chosen.f1 - chosen.f0 == frames else f"selected frames {chosen.f0}..{chosen.f1 - 1} of "
            raise InputError(f"--window {length} is longer than the {selected}recording ({chosen.f1 - chosen.f0} "
                             f"frames)")
        part = job_part(options, frames, float(attrs["fps"]), height, width, cfa)
    half = length // 2
    if (chosen.f0, chosen.f1) != (0, frames):  # a run of frames: the centres whose whole window it holds
        lo, hi = max(part.start, chosen.f0 + half), min(part.stop, chosen.f1 - half)
        centres = [c for c in part.centres if lo <= c < hi]
        if not centres:
            raise InputError(f"spikes hold frames {chosen.f0}..{chosen.f1 - 1}, where no output frame's window of "
                             f"{length} frames fits whole (centres every {every} from {half}, within start= and "
                             f"stop=): select more frames")
        part = part._replace(start=lo, stop=hi, first=part.first + part.centres.index(centres[0]), centres=centres)
    if region is None and chosen.box != (0, height, 0, width):
        part = part._replace(region=chosen.box)
    y0, y1, x0, x1 = part.region
    if not (by0 <= y0 and y1 <= by1 and bx0 <= x0 and x1 <= bx1):
        raise InputError(f"region={y0}:{y1},{x0}:{x1} is outside the selected pixels (y {by0}:{by1}, x {bx0}:{bx1})")
    around = (max(y0 - margin, by0), min(y1 + margin, by1), max(max(x0 - margin, 0) // 8 * 8, bx0),
              min(x1 + margin, bx1))
    store = _store_spikes(spikes)
    if store is not None and not _as_stored(spikes.data, store.data):  # computed from the store's: not its record
        store, attrs = None, {k: v for k, v in attrs.items() if k not in ("store", "identity")}
    # a store's spikes as it holds them (a selection, rechunked or not) are its bits at their coordinates, read from
    # it: a selection whose coordinates were moved gives the frames and pixels they name, as the output records
    bits = spikes.data if store is None else _as_read(store.data, chosen)
    first, last = part.centres[0] - half, part.centres[-1] + half + 1  # the spike frames the windows read
    read = bits[first - chosen.f0:last - chosen.f0, around[0] - by0:around[1] - by0, around[2] - bx0:around[3] - bx0]
    # blocks of ``every`` frames from the first window's start: a window's centre each (a slice computes only its
    # windows), several where there are more than WINDOW_BLOCKS windows (the graph stays bounded), at least half a
    # window long (dask's overlap reads ``half`` frames of each neighbour)
    read = read.rechunk({0: max(every * -(-len(part.centres) // WINDOW_BLOCKS), half + 1)})
    read = read.rechunk({0: da.overlap.ensure_minimum_chunksize(half + 1, read.chunks[0])}) if half else read
    starts = np.cumsum((0, *read.chunks[0]))  # each chunk's first frame, relative to ``first``
    centres = np.asarray(part.centres) - first
    counts = tuple(int(n) for n in np.diff(np.searchsorted(centres, starts)))  # windows centred in each chunk
    data = da.map_overlap(_windows_of, read, depth={0: half, 1: 0, 2: 0}, boundary="none", trim=False,
                          new_axis=1, chunks=(counts, (length,), read.chunks[1], read.chunks[2]), dtype=bool,
                          meta=np.empty((0, 0, 0, 0), bool), starts=tuple(int(s) for s in starts),
                          centre0=int(centres[0]), centre1=int(centres[-1]), every=every, half=half, align_arrays=False,
                          name=f"windows-{tokenize(read.name, starts, centres[0], centres[-1], every, half)}")
    if store is not None:  # nothing between store and here: the blocks read their tiles from it
        attrs = {**attrs, "reads": PackedReads(store.attrs["store"], store.attrs["identity"], data.name, data.chunks,
                                               part.centres[0], every)}
    fps = float(attrs["fps"])
    out = xr.DataArray(
        data, dims=WINDOW_DIMS, name="windows",
        coords={"t": ("t", np.asarray(part.centres) / fps, {"units": "s", "meaning": "time of the window's centre"}),
                "frame": ("t", np.asarray(part.centres, np.int64)),
                "dt": ("dt", np.arange(-half, half + 1), {"units": "spike frames from the centre"}),
                "y": np.arange(around[0], around[1]), "x": np.arange(around[2], around[3])},
        attrs={**attrs, "window": length, "every": every, "start": part.start, "stop": part.stop,
               "region": list(part.region), "first": part.first, "frames": frames, "height": height, "width": width,
               "bounds": list(chosen.box), "kept": list(around)})
    if attrs.get("gain") is None:  # the job's automatic exposure: the whole frame's middle window, made when needed
        if store is not None:  # the job's own task, reading it from the store
            out.coords["auto_gain"] = ((), _store_gain(store, length))
        elif chosen.whole:
            out.coords["auto_gain"] = ((), _whole_recording_gain(spikes.data, length, attrs["reset"]))
    return out


class PackedReads:
    """Windows made by :func:`windows` of a store's spikes (or one selection of them) with nothing in between: their
    reconstruction reads each block's tile and halo as packed bytes straight from the store, as the job's tasks do.
    Known by the windows' graph name (anything in between makes a new one); one selection along ``t`` of the windows
    is still theirs (:meth:`holds`)."""

    def __init__(self, url: str, identity: str, name: str, chunks: tuple, first_centre: int, every: int):
        self.url, self.identity, self.name, self.chunks = url, identity, name, chunks
        self.first_centre, self.every = first_centre, every

    def holds(self, data: da.Array, first_centre: int) -> bool:
        """Whether ``data`` are these windows, or one run of them along t from the window centred on
        ``first_centre`` (the name Dask gives that selection of them)."""
        if data.name == self.name:  # all of them, but only at their own centres (not a frame relabelled)
            return first_centre == self.first_centre and data.shape == self.shape
        start = (first_centre - self.first_centre) // self.every
        if start < 0 or start + data.shape[0] > sum(self.chunks[0]) or data.shape[1:] != self.shape[1:]:
            return False
        ours = da.Array({}, self.name, self.chunks, meta=np.empty((0, 0, 0, 0), bool))  # the name and shape alone
        return ours[start : start + data.shape[0]].name == data.name

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(sum(c) for c in self.chunks)

    def __repr__(self) -> str:
        return f"PackedReads(read straight from {self.url})"


def _store_spikes(spikes: xr.DataArray) -> xr.DataArray | None:
    """The whole recording ``spikes`` were read from, opened again from its store; None where they were not read from
    a store. One line where the store holds another recording now."""
    url, identity = spikes.attrs.get("store"), spikes.attrs.get("identity")
    if not isinstance(url, str) or not isinstance(identity, str):
        return None
    whole = open_spikes(url)
    if whole.attrs.get("identity") != identity:
        raise InputError(f"spike store {url} is not the recording these spikes were read from (it was replaced): "
                         f"open it again")
    return whole


def _as_stored(bits: da.Array, stored: da.Array) -> bool:
    """Whether ``bits`` hold the store's ``stored`` spikes as it holds them: selected or rechunked, nothing else
    (xarray keeps the attributes that name the store through arithmetic and the user's ``map_blocks``)."""
    below = stored.__dask_graph__().layers
    return all(key_split(name) in AS_STORED for name in bits.__dask_graph__().layers if name not in below)


def _as_read(bits: da.Array, chosen) -> da.Array:
    """``bits`` of the whole recording cut as ``chosen`` (one selection): what a selection of the spikes as read
    gives, name included."""
    y0, y1, x0, x1 = chosen.box
    return bits if chosen.whole else bits[chosen.f0 : chosen.f1, y0:y1, x0:x1]


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


def _store_gain(store: xr.DataArray, length: int) -> da.Array:
    """0-d lazy: the automatic exposure of the whole recording ``store``, by the job's own task and key."""
    from dask._task_spec import Task

    frames, _, width = store.shape
    key, args = gain_task(store.attrs["store"], store.attrs["identity"], frames, width, length,
                          store.attrs["reset"])
    return da.Array({key: Task(key, store_gain, *args)}, key[0], chunks=(), dtype=np.float64,
                    meta=np.empty((), np.float64))


def _whole_recording_gain(bits: da.Array, length: int, reset: str) -> da.Array:
    """0-d lazy: the automatic exposure of the whole recording's middle window, whole frame (the job's rule, so
    every part of a recording is exposed alike)."""
    centre, half = middle_centre(bits.shape[0], length), length // 2
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
    attrs = win.attrs
    half = attrs["window"] // 2
    check_coordinates(win, ("frame", "dt", "y", "x"), what, "lazy.windows")
    if not np.array_equal(win.coords["dt"].values, np.arange(-half, half + 1)):
        dt = win.coords["dt"].values
        raise InputError(f"{what} are a selection along dt ({len(dt)} of the {attrs['window']} frames of each window, "
                         f"from dt={dt[0] if len(dt) else None}): a window is all its frames in order; make shorter "
                         f"ones with lazy.windows(spikes, length=...)")
    if not np.issubdtype(win.coords["frame"].dtype, np.integer):
        raise InputError(f"{what} have frame numbers {win.coords['frame'].values[:3].tolist()}... that are not whole "
                         f"(pad? reindex?): keep the frame coordinate lazy.windows gives")
    check_times(win, float(attrs["fps"]), what, "lazy.windows")
    y0, y1, x0, x1 = attrs["region"]
    ys, xs = (run_of(win.coords[d].values, d, what) for d in ("y", "x"))
    if (kept := attrs.get("kept")) and (ys[0] < kept[0] or ys[1] > kept[1] or xs[0] < kept[2] or xs[1] > kept[3]):
        raise InputError(f"{what} hold pixels y {ys[0]}:{ys[1]}, x {xs[0]}:{xs[1]}, outside the y {kept[0]}:{kept[1]}, "
                         f"x {kept[2]}:{kept[3]} lazy.windows kept: their y or x coordinate was changed "
                         f"(assign_coords?): keep the coordinates lazy.windows gives")
    if ys[0] > y0 or ys[1] < y1 or xs[0] > x0 or xs[1] < x1:
        raise InputError(f"{what} are a selection of pixels (y {ys[0]}:{ys[1]}, x {xs[0]}:{xs[1]}) inside their "
                         f"region ({y0}:{y1},{x0}:{x1}): select pixels on the spikes, before lazy.windows, or give "
                         f"lazy.windows(region=...)")
    return win.assign_attrs(_output_part(win.coords["frame"].values, attrs, what))


def _output_part(frames, attrs: dict, what: str) -> dict:
    """``start``, ``stop`` and ``first`` of output frames centred on spike ``frames`` (``attrs``' part, or a
    selection of it): refused in one line unless consecutive output frames of the recording's grid, increasing."""
    frames = np.asarray(frames)
    every, half = int(attrs["every"]), int(attrs["window"]) // 2
    if frames.size == 0:
        raise InputError(f"{what} hold no output frame: select at least one")
    steps = np.diff(frames)
    if steps.size and not (steps == every).all():
        bad = int(np.argmax(steps != every))
        kind = ("repeat" if steps[bad] == 0 else "run backwards" if steps[bad] < 0 else "skip output frames")
        raise InputError(f"{what} are a selection of output frames that {kind} (centres {int(frames[bad])}, "
                         f"{int(frames[bad + 1])}; consecutive ones are {every} spike frames apart): only a "
                         f"contiguous increasing run is honoured (isel(t=slice(a, b)))")
    if (int(frames[0]) - half) % every:
        raise InputError(f"{what} have centre {int(frames[0])}, not one of the recording's output frames ({half}, "
                         f"{half + every}, ...): keep the frame coordinate lazy.windows gives")
    start, stop = attrs.get("start"), attrs.get("stop")
    first = (int(frames[0]) - half) // every
    if isinstance(start, int) and isinstance(stop, int):  # the centres of [start, stop): all of them, or a selection
        k0 = -(-(max(start, half) - half) // every)
        k1 = -(-(min(stop, int(attrs["frames"]) - half) - half) // every)
        if (k1 - k0, half + k0 * every) == (len(frames), int(frames[0])):
            return {"start": start, "stop": stop, "first": first}
    return {"start": int(frames[0]), "stop": int(frames[-1]) + 1, "first": first}
