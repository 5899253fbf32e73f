"""Spike recordings as lazy xarray: a spike store opened as a dask-backed ``DataArray`` of spikes.

The convention every lazy stage (:mod:`pipeline.lazy`) takes and gives for spikes: a ``DataArray`` named
``spikes``, dims ``(t, y, x)``, bool (True = fired), dask-backed; coordinates ``t`` (seconds: frame ``i`` at
``i / fps``), ``frame`` along ``t`` (the spike frame's index in its recording), ``y`` and ``x`` (LR pixel
indices); ``attrs`` the store's attributes (``cfa``, ``fps``, ``reset``, ``gain`` ...), which the stages read.
Stored spikes are bit-packed (8 pixels a byte along x): unpacking is a per-chunk stage of the graph, so a chunk
is read and unpacked only when something downstream computes it.

The rule every lazy stage keeps for xarray selections (``isel``, ``sel``, slicing): honoured exactly, in the
recording's numbers (the coordinates carried through), or refused in one line before anything is written.
:func:`selection` reads which part of its recording a ``DataArray`` of spikes holds from its coordinates, and
:func:`run_of` refuses steps, repeats and reversed or shuffled runs; errors of the jobs' checks are said in
Python words (``start=``, not ``--start``: :func:`python_words`).
"""

import contextlib
import os
import re
from typing import NamedTuple

import dask.array as da
import dask.local
import dask.threaded
import numpy as np
import xarray as xr

from pipeline.compute.cluster import check_in_memory
from pipeline.jobs.reconstruct_tasks import spike_array
from pipeline.stores.storage import recorded
from pipeline.stores.spike_store import SPIKES, open_spike_store, read_frames, store_identity
from stages.capture.bits import packed_width, unpacked_bits
from stages.errors import InputError, InputTypeError

DIMS = ("t", "y", "x")
IN_THIS_PROCESS = (dask.threaded.get, dask.local.get_sync)  # Dask's schedulers that run tasks in this process


def url_text(url, what: str = "url") -> str:
    """``url`` (a string or a ``pathlib.Path``, as the jobs take it) as text, or one line: not a path, or empty."""
    if isinstance(url, os.PathLike):
        url = os.fspath(url)
    if not isinstance(url, str):
        raise InputTypeError(f"{what} must be a path or URL (a string or pathlib.Path), got {url!r}")
    if not url.strip():
        raise InputError(f"{what} is empty: give a path or URL (an empty one is not the current folder)")
    return url


def place(url, what: str = "url") -> str:
    """:func:`url_text` of a store or file a graph's tasks read or write, a local path made absolute
    (``storage.recorded``): a worker started in another folder (``dask worker`` on a cluster) finds it there."""
    return recorded(url_text(url, what))


def check_here(urls, *collections) -> None:
    """Refuse, in one line, a ``memory://`` store among ``urls`` where the scheduler that would compute
    ``collections`` (the active one if none) runs its tasks in other processes, which cannot see it (the jobs'
    ``check_in_memory``)."""
    from dask.base import get_scheduler

    scheduler = get_scheduler(collections=list(collections) or None)
    if scheduler in IN_THIS_PROCESS or scheduler is None:
        return
    check_in_memory(urls, client=distributed_client(*collections),
                    instead=", or compute with Dask's threads (dask.config.set(scheduler='threads'))")


def distributed_client(*collections):
    """The ``distributed`` client that would compute ``collections`` (the active one if none), or None: no client,
    or Dask's own scheduler chosen (``dask.config.set(scheduler=...)``)."""
    from dask.base import get_scheduler

    client = getattr(get_scheduler(collections=list(collections) or None), "__self__", None)
    try:
        from distributed import Client
    except ImportError:
        return None
    return client if isinstance(client, Client) else None


@contextlib.contextmanager
def python_words(**renamed: str):
    """One-line errors of the jobs' checks in Python words: ``--start 300`` -> ``start=300``, ``--window must``
    -> ``window must`` (``renamed``: an option the function names otherwise, ``window="length"``)."""
    try:
        yield
    except InputError as error:
        def word(match: re.Match) -> str:
            name = match.group(1).replace("-", "_")
            name = renamed.get(name, name)
            value = match.group(2)
            return f"{name}={value}" if value else name

        text = re.sub(r"(?<![\w-])--([a-z][a-z-]*)(?: ((?:[-\d'\"(\[]|\w+:)\S*))?", word, str(error))
        raise type(error)(text) from None


def open_spikes(url) -> xr.DataArray:
    """The spike store at ``url`` as lazy spikes ``(t, y, x)`` bool, one dask chunk per stored chunk (whole frames),
    nothing read but metadata. Refuses, in one line, what every job refuses: no store, an incomplete one (its
    writer did not finish), a damaged or contradictory one. A chunk lost from the store is refused when a
    computation reads it, naming its frames (never read as zeros)."""
    url = place(url)
    check_here([url])
    store = open_spike_store(url)
    frames, height, width = store.shape
    packed = da.from_array(_PackedFrames(url, store_identity(store), (frames, height, packed_width(width))),
                           chunks=store.spikes.chunks, asarray=False, fancy=False, meta=np.empty((0, 0, 0), np.uint8),
                           name=f"packed-spikes-{store_identity(store)}")
    bits = packed.map_blocks(unpacked_bits, width, chunks=(packed.chunks[0], (height,), (width,)), dtype=bool,
                             name=f"spikes-{store_identity(store)}")
    # where it was read from and what it is: what an output made from it records (source, source_identity)
    return as_spikes(bits, {**store.attrs, "store": recorded(url), "identity": store_identity(store)})


def as_spikes(bits: da.Array, attrs: dict, first_frame: int = 0) -> xr.DataArray:
    """``bits`` (t, y, x) bool as the spikes convention's ``DataArray`` (coordinates from ``attrs['fps']``), frames
    numbered from ``first_frame``."""
    frame = np.arange(first_frame, first_frame + bits.shape[0], dtype=np.int64)
    return xr.DataArray(bits, dims=DIMS, name=SPIKES, attrs=dict(attrs),
                        coords={"t": ("t", frame / float(attrs["fps"]), {"units": "s"}), "frame": ("t", frame),
                                "y": np.arange(bits.shape[1]), "x": np.arange(bits.shape[2])})


class Selection(NamedTuple):
    """Which part of its recording a ``DataArray`` of spikes holds: spike frames ``[f0, f1)`` and LR pixels ``box``
    (y0, y1, x0, x1) of a recording of ``shape`` (frames, height, width), all in the recording's numbers (the
    ``frame``, ``y`` and ``x`` coordinates)."""

    f0: int
    f1: int
    box: tuple[int, int, int, int]
    shape: tuple[int, int, int]

    @property
    def whole(self) -> bool:
        return (self.f0, self.f1, self.box) == (0, self.shape[0], (0, self.shape[1], 0, self.shape[2]))


def run_of(values, dim: str, what: str) -> tuple[int, int]:
    """``[first, last + 1)`` of coordinate ``values`` if they are a contiguous increasing run (a step of 1), else
    one line naming the selection that is not, and how to select instead."""
    values = np.asarray(values)
    if values.size == 0:
        raise InputError(f"{what} select no {dim}: select at least one")
    if not np.issubdtype(values.dtype, np.integer):
        raise InputError(f"{what} have {dim} numbers {values[:3].tolist()}... that are not whole: keep the "
                         f"coordinates lazy.open_spikes gives")
    steps = np.diff(values)
    if steps.size and not (steps == 1).all():
        bad = int(np.argmax(steps != 1))
        kind = ("repeats" if steps[bad] == 0 else "runs backwards" if steps[bad] < 0
                else f"skips (a step of {steps[bad]})")
        raise InputError(f"{what} are a selection whose {dim} {kind} at {dim} {int(values[bad])}, "
                         f"{int(values[bad + 1])}: only a contiguous increasing run is honoured "
                         f"(isel({'t' if dim == 'frame' else dim}=slice(a, b)))")
    return int(values[0]), int(values[-1]) + 1


def check_times(array: xr.DataArray, per_second: float, what: str, given_by: str) -> None:
    """One line where ``array``'s ``t`` coordinate (where it has one) is not its ``frame`` coordinate over
    ``per_second`` (to a quarter of a frame): one of them was changed (``assign_coords``), so which frames the data
    hold is unknown, and reading the recording at the ``frame`` numbers would give other frames than the data."""
    if "t" not in array.coords:
        return
    t, frame = (np.asarray(array.coords[name].values, np.float64) for name in ("t", "frame"))
    off = ~(np.abs(t - frame / per_second) <= 0.25 / per_second)  # NaN is off too
    if off.any():
        bad = int(np.argmax(off))
        raise InputError(f"the t and frame coordinates of {what} disagree (t {t[bad]:.9g} s at frame {frame[bad]:g}, "
                         f"{per_second:g} frames a second): one was changed (assign_coords?), so the frames the data "
                         f"hold are unknown: keep the coordinates {given_by} gives")


def selection(spikes: xr.DataArray, what: str = "spikes") -> Selection:
    """The part of its recording ``spikes`` (the convention) holds, from its coordinates; one line if they are not
    a contiguous increasing run along each dim, lie outside the recording its attributes describe, or disagree
    (``t`` against ``frame``)."""
    f0, f1 = run_of(spikes.coords["frame"].values, "frame", what)
    check_times(spikes, float(spikes.attrs["fps"]), what, "lazy.open_spikes")
    y0, y1 = run_of(spikes.coords["y"].values, "y", what)
    x0, x1 = run_of(spikes.coords["x"].values, "x", what)
    attrs = spikes.attrs
    shape = tuple(int(attrs[k]) if isinstance(attrs.get(k), (int, np.integer)) else end
                  for k, end in (("frames", f1), ("height", y1), ("width", x1)))
    if f0 < 0 or y0 < 0 or x0 < 0 or f1 > shape[0] or y1 > shape[1] or x1 > shape[2]:
        raise InputError(f"{what} hold frames {f0}..{f1 - 1}, y {y0}..{y1 - 1}, x {x0}..{x1 - 1}, outside their "
                         f"recording of {shape[0]} frames of {shape[1]}x{shape[2]} (its attrs frames, height, width)")
    return Selection(f0, f1, (y0, y1, x0, x1), shape)


def check_spikes(spikes, what: str = "spikes") -> xr.DataArray:
    """``spikes`` if it follows the convention (a dask-backed bool ``DataArray`` with dims (t, y, x), a ``frame``
    coordinate and the recording's ``cfa``, ``fps`` and ``reset``), else one line naming what is wrong."""
    if not isinstance(spikes, xr.DataArray):
        raise InputTypeError(f"{what} must be an xarray.DataArray of spikes (lazy.open_spikes), got "
                             f"{type(spikes).__name__}")
    if spikes.dims != DIMS:
        raise InputError(f"{what} must have dims {DIMS} (as lazy.open_spikes gives), got {spikes.dims}")
    if spikes.dtype != bool:
        raise InputError(f"{what} must be bool spikes (True = fired), got {spikes.dtype}")
    if not isinstance(spikes.data, da.Array):
        raise InputError(f"{what} must be dask-backed (lazy.open_spikes, or .chunk() a DataArray in memory)")
    missing = [name for name in ("cfa", "fps", "reset") if name not in spikes.attrs]
    if missing:
        raise InputError(f"{what} lacks the recording's {', '.join(missing)}: keep the attrs lazy.open_spikes gives "
                         f"(xarray drops attrs in arithmetic unless keep_attrs)")
    check_coordinates(spikes, ("frame", "y", "x"), what, "lazy.open_spikes")  # the recording's numbers
    return spikes


def check_coordinates(array: xr.DataArray, names: tuple[str, ...], what: str, given_by: str) -> None:
    """One line where ``array`` lacks any of the coordinates ``names``, which say which part of the recording it
    holds (``drop_vars`` would leave the stages to guess it)."""
    if lost := [name for name in names if name not in array.coords]:
        missing = (f"the {lost[0]} coordinate is missing (it says" if len(lost) == 1 else
                   f"the {', '.join(lost[:-1])} and {lost[-1]} coordinates are missing (they say")
        raise InputError(f"{what}: {missing} which part of the recording is held): keep the coordinates {given_by} "
                         f"gives")


class StoreReader:
    """What ``da.from_array`` reads a store's array through (:class:`_PackedFrames`, ``written._StoredVideo``): it
    knows the store's ``url``, so that an output is never written over a store its graph reads (:func:`stores_read`)."""

    url: str


def stores_read(data: da.Array) -> list[str]:
    """The stores ``data``'s graph reads through a :class:`StoreReader` (``da.from_array`` holds it in a layer of
    its own, ``original-<name>``), whatever attributes the lazy arrays kept."""
    return [held.url for name, layer in data.__dask_graph__().layers.items() if name.startswith("original-")
            for held in layer.values() if isinstance(held, StoreReader)]


class _PackedFrames(StoreReader):
    """A spike store's packed frames as dask reads them, a block at a time (``da.from_array``): every block through
    :func:`pipeline.stores.spike_store.read_frames`, which refuses a lost or damaged chunk. Pickled as its URL (workers open
    the store once per process)."""

    ndim, dtype = 3, np.dtype(np.uint8)

    def __init__(self, url: str, identity: str, shape: tuple[int, int, int]):
        self.url, self.identity, self.shape = url, identity, shape

    def __getitem__(self, key: tuple[slice, slice, slice]) -> np.ndarray:
        frames, *rest = key
        spikes = spike_array(self.url, self.identity)
        return read_frames(spikes, self.url, frames.start or 0, self.shape[0] if frames.stop is None else frames.stop,
                           tuple(rest))
