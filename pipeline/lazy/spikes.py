"""Spike recordings as lazy xarray: a spike store opened as a dask-backed ``DataArray`` of spikes.

The convention every lazy stage (:mod:`pipeline.lazy`) takes and gives for spikes: a ``DataArray`` named
``spikes``, dims ``(t, y, x)``, bool (True = fired), dask-backed; coordinates ``t`` (seconds: frame ``i`` at
``i / fps``), ``frame`` along ``t`` (the spike frame's index in its recording), ``y`` and ``x`` (LR pixel
indices); ``attrs`` the store's attributes (``cfa``, ``fps``, ``reset``, ``gain`` ...), which the stages read.
Stored spikes are bit-packed (8 pixels a byte along x): unpacking is a per-chunk stage of the graph, so a chunk
is read and unpacked only when something downstream computes it.
"""

import functools

import dask.array as da
import numpy as np
import xarray as xr

from pipeline.stores.storage import recorded
from pipeline.stores.spike_store import SPIKES, open_spike_store, read_frames, store_identity
from stages.capture.bits import packed_width, unpack_rows
from stages.errors import InputError, InputTypeError

DIMS = ("t", "y", "x")


def open_spikes(url: str) -> xr.DataArray:
    """The spike store at ``url`` as lazy spikes ``(t, y, x)`` bool, one dask chunk per stored chunk (whole frames),
    nothing read but metadata. Refuses, in one line, what every job refuses: no store, an incomplete one (its
    writer did not finish), a damaged or contradictory one. A chunk lost from the store is refused when a
    computation reads it, naming its frames (never read as zeros)."""
    if not isinstance(url, str):
        raise InputTypeError(f"url must be a spike store's path or URL as a string, got {url!r}")
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
    if missing or "frame" not in spikes.coords:
        raise InputError(f"{what} lacks the recording's {', '.join(missing) or 'frame coordinate'}: keep the "
                         f"attrs and coordinates lazy.open_spikes gives (xarray drops attrs in arithmetic unless "
                         f"keep_attrs)")
    return spikes


class _PackedFrames:
    """A spike store's packed frames as dask reads them, a block at a time (``da.from_array``): every block through
    :func:`pipeline.stores.spike_store.read_frames`, which refuses a lost or damaged chunk. Pickled as its URL (workers open
    the store once per process)."""

    ndim, dtype = 3, np.dtype(np.uint8)

    def __init__(self, url: str, identity: str, shape: tuple[int, int, int]):
        self.url, self.identity, self.shape = url, identity, shape

    def __getitem__(self, key: tuple[slice, slice, slice]) -> np.ndarray:
        frames, *rest = key
        spikes = _spike_array(self.url, self.identity)
        return read_frames(spikes, self.url, frames.start or 0, self.shape[0] if frames.stop is None else frames.stop,
                           tuple(rest))


@functools.lru_cache(maxsize=8)
def _spike_array(url: str, identity: str):
    """The store's ``spikes`` array, opened once per process and recording (``identity``: another recording at the
    same path is opened afresh, and refused if it is not the one the graph was built on)."""
    store = open_spike_store(url)
    if store_identity(store) != identity:
        raise InputError(f"spike store {url} is not the recording this graph was built on (it was replaced): "
                         f"open it again")
    return store.spikes


def unpacked_bits(packed: np.ndarray, width: int) -> np.ndarray:
    """(n, h, ceil(w/8)) packed -> (n, h, w) bool."""
    return unpack_rows(packed, width).view(bool)
