"""Frames to simulate from: a video file, a folder of images, a Zarr video, or one image.

Each source knows its frame count and size from its header and reads frame ``i`` on
demand, so Dask workers read only the frames their task needs. Frames come back as the
file holds them (uint8/uint16, grey or RGB[A]); :func:`stages.simulation.intensities.to_unit_rgb` turns
them into intensities.
"""

import os
from dataclasses import dataclass

import numpy as np

from pipeline.stores.images import IMAGE_SUFFIXES, decode_image
from pipeline.stores.storage import is_local, recorded, resolve
from stages.errors import InputError, describe

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".gif")


def _suffix(path: str) -> str:
    return os.path.splitext(path)[1].lower()


def _read_image_bytes(fs, path: str) -> np.ndarray:
    with fs.open(path, "rb") as handle:
        return decode_image(handle.read(), path)


@dataclass(frozen=True)
class FrameSource:
    """What a source is and how big; ``read(i)`` returns frame ``i``."""

    url: str
    kind: str  # "image", "folder", "video" or "zarr"
    n_frames: int
    height: int
    width: int
    files: tuple = ()

    def __post_init__(self):  # read by tasks in workers, whose working folder is not the client's
        object.__setattr__(self, "url", recorded(self.url))

    def read(self, index: int) -> np.ndarray:
        if not 0 <= index < self.n_frames:
            raise IndexError(f"frame {index} outside 0..{self.n_frames - 1}")
        fs, path = resolve(self.url)
        if self.kind == "image":
            return _read_image_bytes(fs, path)
        if self.kind == "folder":
            return _read_image_bytes(fs, self.files[index])
        if self.kind == "zarr":
            from pipeline.stores.video_store import video_array

            return video_array(self.url)[index]
        return _video_frame(self.url, index)

    def read_run(self, start: int, stop: int) -> list[np.ndarray]:
        """Frames ``start`` to ``stop - 1``: a video's decoded by one reader in order (a reader per frame decodes
        from the start each time), the others one by one."""
        if self.kind != "video":
            return [self.read(index) for index in range(start, stop)]
        if not 0 <= start <= stop <= self.n_frames:
            raise IndexError(f"frames {start}..{stop - 1} outside 0..{self.n_frames - 1}")
        import imageio.v2 as iio2

        with iio2.get_reader(_local_copy(self.url), format="FFMPEG") as reader:
            return [reader.get_data(index) for index in range(start, stop)]


def _local_copy(url: str) -> str:
    """A local path for a video (ffmpeg reads files): the path itself, or a cached download."""
    if is_local(url):
        return resolve(url)[1]
    import fsspec

    from pipeline.stores.storage import storage_options

    options = storage_options(url)  # S3's bounded timeouts, as everywhere else
    chained = {fsspec.core.split_protocol(url)[0]: options} if options else {}
    return fsspec.open_local(f"simplecache::{url}", **chained)


def _video_frame(url: str, index: int) -> np.ndarray:
    import imageio.v2 as iio2

    with iio2.get_reader(_local_copy(url), format="FFMPEG") as reader:
        return reader.get_data(index)


def _video_header(url: str) -> tuple[int, int, int]:
    import imageio.v2 as iio2

    try:
        with iio2.get_reader(_local_copy(url), format="FFMPEG") as reader:
            n = reader.count_frames()
            height, width = reader.get_data(0).shape[:2]
    except Exception as error:
        raise InputError(f"cannot read video {url}: {describe(error)[:200]}") from None
    return n, height, width


def open_frame_source(url: str) -> FrameSource:
    """Inspect ``url`` and describe it; an error if it is missing, empty or of unknown type."""
    fs, path = resolve(url)
    if not fs.exists(path):
        raise InputError(f"cannot read {url}: no such file or folder")
    if fs.isdir(path):
        if fs.exists(f"{path.rstrip('/')}/zarr.json"):
            from pipeline.stores.video_store import video_array

            video = video_array(url)
            if video.ndim != 4 or video.shape[-1] != 3:
                raise InputError(f"{url}: 'video' has shape {video.shape}, expected (T, H, W, 3)")
            return FrameSource(url, "zarr", video.shape[0], video.shape[1], video.shape[2])
        files = tuple(sorted(f for f in fs.ls(path, detail=False) if _suffix(f) in IMAGE_SUFFIXES))
        if not files:
            raise InputError(f"folder {url} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        first = _read_image_bytes(fs, files[0])
        return FrameSource(url, "folder", len(files), first.shape[0], first.shape[1], files)
    suffix = _suffix(path)
    if suffix in IMAGE_SUFFIXES:
        image = _read_image_bytes(fs, path)
        return FrameSource(url, "image", 1, image.shape[0], image.shape[1])
    if suffix in VIDEO_SUFFIXES:
        return FrameSource(url, "video", *_video_header(url))
    raise InputError(f"unknown source type {suffix or '(no extension)'} for {url}: expected an image, a video, a folder of images or a Zarr video")
