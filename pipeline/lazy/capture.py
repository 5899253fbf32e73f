"""A raw capture as lazy spikes (``cscsr.lazy``, issue #56): :func:`open_capture`.

A ``.dat``, a ``.npy`` or a raw capture of a named layout (``layout="sps100"``), whatever ``cscsr ingest`` reads
by frame range, as the spikes convention's ``DataArray`` (:mod:`pipeline.lazy.spikes`): the spikes, coordinates
and attributes that ``lazy.open_spikes`` gives for the store ``cscsr ingest`` writes from it with the same options,
less what only a written store has (``state``, ``spike_count``, ``identity``). So a capture is explored or
reconstructed without converting it first, and ``to_spikes(open_capture(...), url)`` writes the spikes, chunks and
attributes of that ingest.

Every check is ingest's own, before any graph exists, in Python words (``height=``, not ``--height``): its options
(:meth:`pipeline.jobs.ingest.IngestOptions.check`), the capture's reader (``pipeline.stores.captures.open_capture``:
sizes, layout, a ``.dat`` that does not divide into frames, a ``.npy`` header, an sps100 capture's first whole
frame) and the store's metadata (:func:`pipeline.jobs.ingest.capture_meta`); an sps100 capture's frame cut short
at its end is checked then too (its packets and the last whole frame's: one range read of two frames at most), and
said in one warning line, as ingest says it. Nothing else is read then: each dask block reads its frames by one
byte range with ingest's reader (``RawCapture.read``, ``ArrayCapture.read``), which checks an sps100 capture's tags
when the block is computed, naming the byte offset (``stages.capture.sps100.CaptureDamaged``).
"""

import json
import logging
import weakref

import dask.array as da
import numpy as np
import xarray as xr
from dask.base import tokenize

from pipeline.jobs.ingest import (CaptureFrames, IngestOptions, capture_change, capture_meta, capture_record,
                                  opened_capture, opened_frames, unread_parts)
from pipeline.lazy.spikes import as_spikes, check_here, place, python_words
from pipeline.stores.captures import RANGED_KINDS
from pipeline.stores.spike_store import chunk_frames_for
from stages.capture.bits import packed_width, unpacked_bits
from stages.errors import InputError
from stages.numbers import check_number

log = logging.getLogger("cscsr.lazy")


def open_capture(path, *, height: int | None = None, width: int | None = None, layout: str | None = None,
                 flip: bool = False, head_columns: int = 0, cfa: str = "mono", fps: float = 20000.0,
                 reset: str = "subtract", chunk_frames: int | None = None) -> xr.DataArray:
    """The raw capture at ``path`` as lazy spikes ``(t, y, x)`` bool: what ``cscsr ingest`` with the same options
    stores, read a block at a time when something computes it (``chunk_frames`` frames a block; default: the
    chunks of the store ingest writes). The options are ``cscsr ingest``'s and mean what they mean there:
    ``height``/``width`` of a ``.dat`` (an array's or an sps100 capture's own, if given, must agree),
    ``layout`` (``dat``, ``sps100``; default by extension), ``flip`` (frames stored upside down),
    ``head_columns`` (a ``.dat``'s header columns, dropped), ``cfa`` (the sensor's pattern), ``fps``, ``reset``.
    Everything is refused, in one line, before any graph exists; damage inside the frames (an sps100 tag out of
    sequence) when the block holding it is computed, naming its byte offset."""
    path = place(path, "path")
    options = IngestOptions(height, width, cfa, fps, flip, head_columns, None, reset, layout=layout)
    with python_words():
        options.check()
        if chunk_frames is not None:
            check_number("--chunk-frames", chunk_frames, at_least=1, integer=True)
        check_here([path])  # a memory:// capture is this process's alone
        capture = opened_capture(path, options)
        if not capture.ranged:
            raise InputError(f"{path}: a .npz is read as one stream, and lazy spikes are read by frame range "
                             f"({', '.join(RANGED_KINDS)}): save the array as .npy (or ingest it with cscsr ingest)")
        sensor_cfa, meta = capture_meta(path, options, capture)
        record = capture_record(path, options, capture, sensor_cfa)  # its fingerprint: two range reads
        n_frames = capture.n_frames
        if capture.unread_bytes:  # a frame cut short: its packets checked now, with the last whole frame's
            capture.read(n_frames - 1, n_frames)
    for line in unread_parts(path, capture, n_frames):
        log.warning("%s", line)
    frames = CaptureFrames(path, options.height, options.width, flip, head_columns, layout, n_frames,
                           capture.height, packed_width(capture.width), json.dumps(record))
    chunk = min(chunk_frames or chunk_frames_for(meta, n_frames), n_frames)
    token = tokenize(frames, capture.fs.size(capture.path), capture.fs.ukey(capture.path))
    packed = da.from_array(frames, chunks=(chunk, -1, -1), asarray=False, fancy=False,
                           meta=np.empty((0, 0, 0), np.uint8), name=f"packed-capture-{token}")
    bits = packed.map_blocks(unpacked_bits, capture.width, chunks=(packed.chunks[0], (capture.height,),
                                                                   (capture.width,)),
                             dtype=bool, name=f"spikes-{token}")
    _READS[bits.name] = frames
    return as_spikes(bits, {**meta.attrs(), "frames": n_frames})


def capture_frames(data: da.Array) -> "CaptureFrames | None":
    """The capture ``data`` are all the frames of, as :func:`open_capture` made them (a selection, a function or a
    rechunk since makes a new array): then ``to_spikes`` runs ``cscsr ingest``'s own tasks, each reading its frames
    packed by one byte range and writing them as they are. Else None."""
    return _READS.get(data.name)


def check_unchanged(frames: CaptureFrames) -> None:
    """Refuse, in one line, a capture whose bytes are not those :func:`open_capture` fingerprinted (its size, a
    SHA-256 of its ends: two range reads): another recording written under the same name since."""
    if why := capture_change(json.loads(frames.record)["capture"], opened_frames(frames).fingerprint()):
        raise InputError(f"{frames.url} changed since lazy.open_capture opened it ({why}): open it again")


_READS: "weakref.WeakValueDictionary[str, CaptureFrames]" = weakref.WeakValueDictionary()  # kept while a graph
# holds the capture's reader
