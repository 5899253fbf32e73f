"""Scene frames as lazy xarray (``cscsr.lazy``, issue #56): :func:`open_frames`, what ``cscsr simulate`` reads.

A video file, a folder of pictures, a Zarr video (``cscsr reconstruct``'s output) or one picture, as the HR scene
frames ``(t, y, x, rgb)`` that :func:`pipeline.lazy.simulate.simulate` takes, each frame as the file holds it (uint8
or uint16; grey frames with ``rgb`` of size 1, RGBA with 4), read a block at a time when something computes it,
through the reader of the ``simulate`` job (``pipeline.stores.frame_sources``). So
``to_spikes(simulate(frames), url, truth=frames)`` writes the recording and ground truth that ``cscsr simulate``
writes of a source with one frame per spike frame (``--interp linear``: spike frame ``t`` is frame ``t``).
"""

from dataclasses import dataclass

import dask.array as da
import numpy as np
import xarray as xr
from dask.base import tokenize

from pipeline.lazy.spikes import check_here, python_words, url_text
from pipeline.stores.frame_sources import FrameSource, open_frame_source
from pipeline.stores.storage import recorded, resolve
from stages.errors import InputError
from stages.numbers import check_number

FRAME_DIMS = ("t", "y", "x", "rgb")
FRAMES_A_BLOCK = 8  # frames read by one task unless chunk_frames= says otherwise


def open_frames(url, *, chunk_frames: int | None = None) -> xr.DataArray:
    """The frames at ``url`` (a video, a folder of pictures, a Zarr video, a picture) as lazy scene frames
    ``(t, y, x, rgb)``, ``chunk_frames`` frames a block (default :data:`FRAMES_A_BLOCK`); attribute ``source``: the
    place, as a store records it. The first frame is read now (its dtype and colours are every frame's); a frame
    of another size, dtype or colours is refused, in one line naming it, when its block is computed."""
    url = url_text(url)
    with python_words():
        if chunk_frames is not None:
            check_number("chunk_frames", chunk_frames, at_least=1, integer=True)
        check_here([url])  # a memory:// source is this process's alone
        source = open_frame_source(url)
        first = _as_4d(source.read(0), source, 0, None)
    frames = _SourceFrames(source, first.dtype.str, first.shape[-1], _modified(url))
    data = da.from_array(frames, chunks=(min(chunk_frames or FRAMES_A_BLOCK, source.n_frames), -1, -1, -1),
                         asarray=False, fancy=False, meta=np.empty((0, 0, 0, 0), first.dtype),
                         name=f"frames-{tokenize(frames)}")
    return xr.DataArray(data, dims=FRAME_DIMS, attrs={"source": recorded(url)})


def _modified(url: str):
    """What tells this version of the source from a later one at the same place (in the graph's token)."""
    fs, path = resolve(url)
    try:
        return fs.ukey(path)
    except (OSError, NotImplementedError):  # a folder: its listing's names and sizes
        return tuple(sorted((entry["name"], entry.get("size")) for entry in fs.ls(path, detail=True)))


def _as_4d(frame: np.ndarray, source: FrameSource, index: int, like: tuple[str, int] | None) -> np.ndarray:
    """Frame ``index`` as (1, H, W, colours); refused unless it is the size of the source and, given ``like``
    (dtype, colours), of that dtype and those colours."""
    frame = np.asarray(frame)
    frame = frame[:, :, None] if frame.ndim == 2 else frame
    if frame.ndim != 3 or frame.shape[:2] != (source.height, source.width) or frame.shape[2] not in (1, 3, 4):
        raise InputError(f"{source.url}: frame {index} has shape {frame.shape}, not ({source.height}, "
                         f"{source.width}) grey, RGB or RGBA as frame 0")
    if not np.issubdtype(frame.dtype, np.unsignedinteger):
        raise InputError(f"{source.url}: frame {index} holds {frame.dtype}, not unsigned integers")
    if like is not None and (frame.dtype.str, frame.shape[2]) != like:
        raise InputError(f"{source.url}: frame {index} is {frame.dtype} with {frame.shape[2]} colours, frame 0 "
                         f"{np.dtype(like[0])} with {like[1]}: convert the frames alike")
    return frame[None]


@dataclass(frozen=True)
class _SourceFrames:
    """A source's frames as dask reads them (``da.from_array``), a block of frames at a time. Pickled as its
    fields."""

    source: FrameSource
    dtype_str: str
    colours: int
    version: object  # :func:`_modified`: only in the token

    ndim = 4

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.dtype_str)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return self.source.n_frames, self.source.height, self.source.width, self.colours

    def __getitem__(self, key) -> np.ndarray:
        frames, *rest = key
        start, stop, _ = frames.indices(self.source.n_frames)
        like = (self.dtype_str, self.colours)
        block = np.concatenate([_as_4d(frame, self.source, i, like)
                                for i, frame in enumerate(self.source.read_run(start, stop), start)])
        return block[(slice(None), *rest)]
