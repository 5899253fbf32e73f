"""Scene frames as lazy xarray (``cscsr.lazy``, issue #56): :func:`open_frames`, what ``cscsr simulate`` reads.

A video file, a folder of pictures, a Zarr video (``cscsr reconstruct``'s output) or one picture, as the HR scene
frames ``(t, y, x, rgb)`` that :func:`pipeline.lazy.simulate.simulate` takes, each frame as the job's reader gives
it (uint8; uint16 for a 16-bit grey picture; grey frames with ``rgb`` of size 1, RGBA with 4), read a block at a
time when something computes it, through the reader of the ``simulate`` job (``pipeline.stores.frame_sources``). So
``to_spikes(simulate(frames), url, truth=frames)`` writes the recording and ground truth that ``cscsr simulate``
writes of a source with one frame per spike frame (``--interp linear``: spike frame ``t`` is frame ``t``). A
picture becomes the job's scene under ``--motion``: repeated, or rendered along the job's camera path (the job
also writes that path's flow between truth frames; ``to_spikes`` writes none).
"""

import functools
import math
from dataclasses import dataclass

import dask.array as da
import numpy as np
import xarray as xr
from dask.base import tokenize

from pipeline.jobs.simulate import MAX_FRAMES, MAX_FRAMES_WHY, MOTIONS
from pipeline.lazy.spikes import check_here, python_words, url_text
from pipeline.stores.frame_sources import FrameSource, open_frame_source
from pipeline.stores.storage import recorded, resolve
from stages.errors import InputError
from stages.numbers import check_number, check_text
from stages.simulation.camera_path import CameraPath, render
from stages.simulation.intensities import to_unit_rgb

FRAME_DIMS = ("t", "y", "x", "rgb")
BLOCK_BYTES = 64 * 2**20  # frames a block unless chunk_frames= says otherwise: about this many bytes, at least one


def open_frames(url, *, chunk_frames: int | None = None, frames: int | None = None, motion: str | None = None,
                seed: int = 0, speed: float = 0.5, deform: float = 0.0) -> xr.DataArray:
    """The frames at ``url`` (a video, a folder of pictures, a Zarr video, a picture) as lazy scene frames
    ``(t, y, x, rgb)``, ``chunk_frames`` frames a block (default: about :data:`BLOCK_BYTES`); attributes ``source``
    (the place, as a store records it) and ``motion``. The first frame is read now (its dtype and colours are every
    frame's); a frame of another size, dtype or colours is refused, in one line naming it, when its block is read.

    A picture is a scene of ``frames`` frames under ``motion``, as ``cscsr simulate PICTURE --motion`` makes it:
    ``"static"``, the picture in every frame as stored; ``"random"``, the camera path of ``seed``, ``speed`` and
    ``deform`` (``stages.simulation.camera_path.CameraPath.random``: the job's own, of its ``--seed``), each frame
    rendered as float32 intensities in [0, 1]; the attributes ``seed`` and ``frames`` say which path, and
    ``simulate`` must be given that seed (the job's one ``--seed`` draws both). ``frames`` and ``motion`` are for a
    picture alone."""
    url = url_text(url)
    with python_words():
        for name, value in (("chunk_frames", chunk_frames), ("frames", frames)):
            if value is not None:
                check_number(name, value, at_least=1, at_most=MAX_FRAMES, integer=True, why=MAX_FRAMES_WHY)
        check_text("motion", motion, optional=True)
        check_number("seed", seed, at_least=0, integer=True)
        check_number("speed", speed, at_least=0)
        check_number("deform", deform, at_least=0)
        check_here([url])  # a memory:// source is this process's alone
        source = open_frame_source(url)
        first = _as_4d(source.read(0), source, 0, None)
        if source.kind == "image" or frames is not None or motion is not None:
            if source.kind != "image":
                raise InputError(f"frames= and motion= are for a picture; {url} is a {source.kind} with motion of "
                                 f"its own")
            if frames is None or motion not in MOTIONS:
                raise InputError(f"{url} is one picture: give frames= and motion= ({' or '.join(MOTIONS)}), the "
                                 f"scene's length and how the camera moves, got frames={frames}, motion={motion!r}")
            path = CameraPath.random(frames, source.height, source.width, seed=seed, speed=speed, deform=deform) \
                if motion == "random" else None
            scene = _CameraFrames(source, frames, first.dtype.str, first.shape[-1], path, _modified(url))
        else:
            scene = _SourceFrames(source, first.dtype.str, first.shape[-1], _modified(url))
    frame_bytes = scene.dtype.itemsize * math.prod(scene.shape[1:])
    chunk = min(chunk_frames or max(1, BLOCK_BYTES // frame_bytes), scene.shape[0])
    data = da.from_array(scene, chunks=(chunk, -1, -1, -1), asarray=False, fancy=False,
                         meta=np.empty((0, 0, 0, 0), scene.dtype), name=f"frames-{tokenize(scene)}")
    attrs = {"source": recorded(url), "motion": motion or "video"}
    if motion == "random":  # the path's: lazy.simulate records the job's options only for the job's scene
        attrs.update(seed=seed, frames=frames)
    return xr.DataArray(data, dims=FRAME_DIMS, attrs=attrs)


def _modified(url: str):
    """What tells this version of the source from a later one at the same place (in the graph's token): a file's
    key, a folder's (pictures, a Zarr video) every file's name, size and time (a file rewritten inside a folder
    leaves the folder's own as it was)."""
    fs, path = resolve(url)
    if fs.isdir(path):
        return tuple(sorted((entry["name"], entry.get("size"), str(entry.get("mtime") or entry.get("LastModified")
                                                                    or entry.get("ETag")))
                            for entry in fs.find(path, detail=True).values()))
    return fs.ukey(path)


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
class _CameraFrames:
    """A picture as ``n_frames`` scene frames under a camera ``path`` (None: static), as dask reads them, a block
    at a time; the picture decoded once a block. Pickled as its fields."""

    source: FrameSource
    n_frames: int
    dtype_str: str  # the picture's (static), float32 (rendered)
    colours: int
    path: CameraPath | None
    version: object  # :func:`_modified`: only in the token

    ndim = 4

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.dtype_str if self.path is None else np.float32)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return self.n_frames, self.source.height, self.source.width, self.colours if self.path is None else 3

    def __getitem__(self, key) -> np.ndarray:
        frames, *rest = key
        start, stop, _ = frames.indices(self.n_frames)
        picture = _picture(self.source, self.version, (self.dtype_str, self.colours))
        if self.path is None:
            block = np.broadcast_to(picture, (stop - start, *picture.shape[1:]))
        else:
            image = to_unit_rgb(picture[0])
            block = np.stack([render(image, self.path, t) for t in range(start, stop)])
        return np.ascontiguousarray(block[(slice(None), *rest)])


@functools.lru_cache(maxsize=2)
def _picture(source: FrameSource, version, like: tuple[str, int]) -> np.ndarray:
    """The picture of a scene, (1, H, W, colours), decoded once a process (every block of its frames reads it)."""
    picture = _as_4d(source.read(0), source, 0, like)
    picture.flags.writeable = False  # shared between blocks
    return picture


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
