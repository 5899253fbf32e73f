"""The HR video store: reconstructed frames, their spike-frame centres, and a commit record.

Layout (``PRODUCT.md``): ``video`` uint8 ``(T_out, s*H, s*W, 3)`` with dimension names
``j, hr_y, hr_x, c`` (stores before format_version 1 said ``t, y, x, c``: read alike), one chunk per (frame, tile), so each reconstruction task owns exactly one
chunk, zstd level 1 (half the encode time of level 3 for 7 % more bytes on HR frames); ``frames`` int64 ``(T_out,)``, the centre spike frame of each output frame;
``committed`` uint8 ``(T_out, tiles_y, tiles_x)``, one single-element chunk per task, set to 1
after that task's tile is written. ``committed`` is the record ``--resume`` trusts (an
absent chunk of ``video`` could be an empty tile or a lost one; a missing 1 can only mean
not done). Attributes say how the video was made and ``state`` says whether it is complete.
The metadata is consolidated once every array is declared (xarray opens the store, ``frames``
as the coordinate of ``video``); only the group's attributes change after, which keeps it valid.
"""

import asyncio
import hashlib
import json
import math
from collections.abc import Sequence

import numpy as np
import zarr
from zarr.codecs import ZstdCodec
from zarr.core.sync import sync

from cscsr.version import __version__
from pipeline.stores.storage import ChunkListing, consolidate, list_chunks, open_group, zarr_store
from stages.errors import InputError

VIDEO, FRAMES, COMMITTED = "video", "frames", "committed"
FORMAT_VERSION = 1
VIDEO_UNITS = "8-bit sRGB"


def create_video_store(url: str, *, centres: list[int], hr_size: tuple[int, int], tile_hr: tuple[int, int],
                       tiles: tuple[int, int], attrs: dict, fps: float | None = None,
                       graph: str | None = None) -> zarr.Group:
    """Write every array's metadata, ``frames`` and the attributes (state "writing"), and consolidate the
    metadata. ``fps``: output frames per second of recording time (the spike rate over ``every``); ``graph``: the
    token of the lazy graph whose blocks it holds (``committed``'s, which a resume compares)."""
    info = {"format_version": FORMAT_VERSION, "cscsr_version": __version__}
    if fps is not None:
        info["fps"] = fps
    group = zarr.open_group(zarr_store(url, read_only=False), mode="w",
                            attributes={**attrs, **info, "state": "writing"})
    n = len(centres)
    viewer = {k: attrs[k] for k in ("window", "every", "method") if k in attrs}
    group.create_array(VIDEO, shape=(n, *hr_size, 3), chunks=(1, *tile_hr, 3), dtype=np.uint8, fill_value=0,
                       compressors=ZstdCodec(level=1), dimension_names=("j", "hr_y", "hr_x", "c"),
                       attributes={"units": VIDEO_UNITS, "coordinates": FRAMES, **viewer, **info},
                       config={"write_empty_chunks": True})
    group.create_array(FRAMES, shape=(n,), chunks=(max(n, 1),), dtype=np.int64, fill_value=0, dimension_names=("j",),
                       attributes={"units": "spike frame index, the centre of each output frame's window"})
    group.create_array(COMMITTED, shape=(n, *tiles), chunks=(1, 1, 1), dtype=np.uint8, fill_value=0,
                       dimension_names=("j", "tile_y", "tile_x"),
                       attributes={"units": "1 = tile written", **({"graph": graph} if graph else {})})
    group[FRAMES][:] = np.asarray(centres, np.int64)
    consolidate(url)
    return zarr.open_group(zarr_store(url, read_only=False), mode="r+")  # knows the consolidated copy


def open_video_store(url: str, *, writable: bool = False) -> zarr.Group:
    try:
        group = zarr.open_group(zarr_store(url, read_only=not writable), mode="r+" if writable else "r")
    except FileNotFoundError:
        raise InputError(f"cannot read video store {url}: no Zarr group there") from None
    if VIDEO not in group or FRAMES not in group:
        raise InputError(f"{url} is not an HR video store: it needs '{VIDEO}' and '{FRAMES}'")
    check_video_store(url, group)
    return group


def check_video_store(url: str, group: zarr.Group) -> None:
    """Refuse a video store of a ``format_version`` this release does not read, or whose metadata contradicts itself:
    an array whose own ``zarr.json`` and the consolidated copy in the group's disagree, arrays that disagree on the
    number of output frames (``video``, ``frames`` and ``committed``, as the group reads them: the consolidated copy
    where there is one), or more output frames than the spike frames it records (``start``, ``stop``, ``every``) can
    give, or attributes that no reconstruction records (:func:`_nonsense_attribute`, :func:`_region_outside`); and,
    as not an RGB video store, a ``video`` that is not (frames, height, width, 3) uint8. Metadata only, no chunk
    read, so a shape edited to claim 10⁹ frames is one line at once. A store being written has every array
    declared already: it passes."""
    check_format_version(dict(group.attrs), f"video store {url}", FORMAT_VERSION)
    arrays = {name: group[name] for name in (VIDEO, FRAMES, COMMITTED) if name in group}
    if not all(isinstance(array, zarr.Array) and array.ndim >= 1 for array in arrays.values()):
        raise InputError(f"video store {url}: its '{VIDEO}', '{FRAMES}' and '{COMMITTED}' must be arrays")
    video = arrays[VIDEO]
    if video.ndim != 4 or video.shape[3] != 3 or video.dtype != np.uint8:
        raise InputError(f"{url} is not an RGB video store: its '{VIDEO}' is {video.dtype} {video.shape}, not (frames, "
                         f"height, width, 3) uint8: give a store made by cscsr reconstruct")
    if problem := (_copies_disagree(group, list(arrays)) or _frames_disagree(arrays) or _more_than_recorded(group)
                   or _nonsense_attribute(dict(group.attrs)) or _region_outside(dict(group.attrs), video.shape)):
        raise InputError(f"video store {url}: metadata inconsistent: {problem}: the store was altered or damaged; make "
                         f"it again with cscsr reconstruct --overwrite")


def _copies_disagree(group: zarr.Group, names: list[str]) -> str | None:
    """Which array's shape differs between its own ``zarr.json`` and the consolidated copy, or None."""
    consolidated = consolidated_shapes(group)
    for name in names:
        own = _metadata(group, f"{name}/zarr.json").get("shape")
        if name in consolidated and isinstance(own, list) and tuple(own) != consolidated[name]:
            return (f"'{name}' is {tuple(own)} in {name}/zarr.json but {consolidated[name]} in the consolidated copy "
                    f"in zarr.json")
    return None


def _frames_disagree(arrays: dict[str, zarr.Array]) -> str | None:
    """Whether the arrays disagree on the number of output frames (their first dimension), in words, or None."""
    counts = {name: array.shape[0] for name, array in arrays.items()}
    if len(set(counts.values())) <= 1:
        return None
    disagree = ", ".join(f"'{name}' {count}" for name, count in counts.items())
    return f"its arrays disagree on the number of output frames ({disagree})"


def _more_than_recorded(group: zarr.Group) -> str | None:
    """Whether ``video`` has more output frames than the spike frames ``start`` to ``stop`` that the store records,
    one every ``every``, can give, in words, or None (a store from before ``start`` and ``stop``: nothing to
    compare)."""
    attrs, frames = group.attrs, group[VIDEO].shape[0]
    start, stop, every = (attrs.get(name) for name in ("start", "stop", "every"))
    if not all(isinstance(value, int) and not isinstance(value, bool) for value in (start, stop, every)) \
            or every <= 0 or stop < start:
        return None
    most = -(-(stop - start) // every)
    if frames <= most:
        return None
    return (f"'{VIDEO}' has {frames} output frames, but the store records spike frames {start} to {stop} (stop "
            f"excluded), one output frame every {every}: at most {most}")


WHOLE_ATTRIBUTES = {"every": 1, "window": 1, "scale": 1, "tile_lr": 1, "start": 0, "stop": 0}  # name: least value
POSITIVE_ATTRIBUTES = ("fps", "gain")  # finite numbers above 0


def _whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _nonsense_attribute(attrs: dict) -> str | None:
    """The first attribute that no reconstruction records (a count below its least, a rate or gain that is not a
    finite positive number, a range that ends before it starts), in words, or None; absent ones (stores from
    before them) pass."""
    for name, least in WHOLE_ATTRIBUTES.items():
        if (value := attrs.get(name)) is not None and not (_whole(value) and value >= least):
            return f"{name} {value!r} is not a whole number >= {least}"
    for name in POSITIVE_ATTRIBUTES:
        value = attrs.get(name)
        if value is not None and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                      and math.isfinite(value) and value > 0):
            return f"{name} {value!r} is not a finite number > 0"
    start, stop = attrs.get("start"), attrs.get("stop")
    if start is not None and stop is not None and stop < start:
        return f"stop {stop} is before start {start}"
    return None


def _region_outside(attrs: dict, video_shape: tuple) -> str | None:
    """Whether the LR ``region`` [y0, y1, x0, x1] is not a region of the recording's frame (``source_shape``,
    where recorded), or ``scale`` times it is not the size of ``video``'s frames, in words, or None."""
    region, scale, source = attrs.get("region"), attrs.get("scale"), attrs.get("source_shape")
    if region is None:
        return None
    if not (isinstance(region, list) and len(region) == 4 and all(map(_whole, region))):
        return f"region {region!r} is not [y0, y1, x0, x1] in LR pixels"
    y0, y1, x0, x1 = region
    frame = source[1:] if isinstance(source, list) and len(source) == 3 and all(map(_whole, source)) else None
    if not (0 <= y0 < y1 and 0 <= x0 < x1) or (frame and (y1 > frame[0] or x1 > frame[1])):
        where = f"the recording's {frame[0]}x{frame[1]} frame" if frame else "a frame"
        return f"region {y0}:{y1},{x0}:{x1} is not inside {where}"
    if _whole(scale) and tuple(video_shape[1:3]) != ((y1 - y0) * scale, (x1 - x0) * scale):
        return (f"region {y0}:{y1},{x0}:{x1} at x{scale} is {(y1 - y0) * scale}x{(x1 - x0) * scale} HR, but '{VIDEO}' "
                f"frames are {video_shape[1]}x{video_shape[2]}")
    return None


def check_format_version(attrs: dict, what: str, known: int) -> None:
    """Refuse a ``format_version`` this release does not read (a newer one, or not a version at all) in one
    line naming ``what``; a store without one (written before versions were recorded) is read as version 1."""
    version = attrs.get("format_version")
    if version is None:
        return
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError(f"{what}: metadata inconsistent: format_version {version!r} is not a format version "
                         f"(1..{known})")
    if version > known:
        writer = attrs.get("cscsr_version")
        why = (f"metadata inconsistent: it records cscsr {writer}, which writes {known}" if writer == __version__
               else f"read it with the release that wrote it (cscsr {writer}) or a newer one" if writer
               else "read it with the release that wrote it")
        raise InputError(f"{what}: format_version {version} is not one this cscsr ({__version__}) reads "
                         f"(1..{known}): {why}")


def consolidated_shapes(group: zarr.Group) -> dict[str, tuple]:
    """The shape of each array as the consolidated copy in the group's ``zarr.json`` records it (one small metadata
    read; the group is opened from the arrays' own metadata, :func:`pipeline.stores.storage.open_group`); empty where there
    is no copy or it cannot be read (xarray's concern, not ours)."""
    entries = _metadata(group, "zarr.json").get("consolidated_metadata")
    entries = entries.get("metadata") if isinstance(entries, dict) else None
    if not isinstance(entries, dict):
        return {}
    return {name: tuple(entry["shape"]) for name, entry in entries.items()
            if isinstance(entry, dict) and entry.get("node_type") == "array" and isinstance(entry.get("shape"), list)}


def _metadata(group: zarr.Group, key: str) -> dict:
    """The JSON document ``key`` (relative to the group: ``zarr.json``, ``video/zarr.json``) as stored, whatever the
    group was opened from; empty where it is missing or not a JSON object."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.sync import sync

    prefix = f"{group.store_path.path}/" if group.store_path.path else ""
    try:
        raw = sync(group.store.get(prefix + key, prototype=default_buffer_prototype()))
        document = json.loads(raw.to_bytes()) if raw is not None else {}
    except (TypeError, ValueError, AttributeError, OSError):
        return {}
    return document if isinstance(document, dict) else {}


def video_array(url: str) -> zarr.Array:
    """The ``video`` array of the Zarr group at ``url``, read-only: a video store, or any group holding
    frames as ``video`` (T, H, W, 3) uint8, as the simulator takes them for a source."""
    group = open_group(url)
    if VIDEO not in group:
        raise InputError(f"{url} is a Zarr group without a '{VIDEO}' array (j, hr_y, hr_x, c: frames of 8-bit RGB)")
    return group[VIDEO]


def video_identity(group: zarr.Group) -> str:
    """What names a finished video store and no other that could differ from it: a SHA-256 of what its writer
    recorded (the group's and ``committed``'s attributes: method, weights, source and its identity, the part, the
    graph) and the ``video`` array's shape and chunks. No chunk is read. Two stores recording the same are the same
    reconstruction of the same recording, and so the same bytes (outputs do not depend on workers or chunking)."""
    described = json.dumps({"attrs": dict(group.attrs), "committed": dict(group[COMMITTED].attrs)
                            if COMMITTED in group else None, "shape": group[VIDEO].shape,
                            "chunks": group[VIDEO].chunks}, sort_keys=True, default=str)
    return hashlib.sha256(described.encode()).hexdigest()


def is_video_store(group: zarr.Group) -> bool:
    return VIDEO in group and FRAMES in group


def describe_video_store(url: str, group: zarr.Group) -> str:
    """One line saying what a video store holds, for a command that was given one where it wanted
    a spike store: ``URL is a video store (N frames of WxH RGB, method M, state S)``."""
    attrs = group.attrs
    n, height, width = group[VIDEO].shape[:3]
    return (f"{url} is a video store ({n} frames of {height}x{width} RGB, method {attrs.get('method')}, "
            f"state {attrs.get('state')})")


def committed_mask(group: zarr.Group) -> np.ndarray:
    """(T_out, tiles_y, tiles_x) bool: which tasks have committed their tile."""
    return group[COMMITTED][:].astype(bool)


def resumed_mask(group: zarr.Group, url: str, expected: dict, found: dict, shape: tuple[int, int, int]) -> np.ndarray:
    """The commit mask of the video store ``group`` at ``url`` to resume, refused in one line unless what it records
    (``found``, as the caller reads it) is ``expected`` and its ``committed`` is of ``shape`` (output frames, tile
    rows, tile columns): the ``reconstruct`` job's and ``lazy.to_video``'s check. Its ``source`` may be spelled
    otherwise (moved, a copy, a link, ``file://``) where the store records the recording's identity, the same."""
    identity = expected.get("source_identity")
    moved = identity is not None and group.attrs.get("source_identity") == identity  # the same recording, elsewhere
    changed = [k for k in expected if found.get(k) != expected[k] and not (k == "source" and moved)]
    if changed or group[COMMITTED].shape != shape:
        what = ", ".join(f"{k} {found.get(k)!r} -> {expected[k]!r}" for k in changed) or "layout"
        raise InputError(f"cannot resume {url}: it was made with other parameters ({what})")
    return committed_mask(group)


SHOWN = 4  # ranges of lost frames named in full


def lost_chunks(group: zarr.Group, video: ChunkListing) -> list[range]:
    """The runs of chunks of ``video`` (chunk numbers, :class:`pipeline.stores.storage.ChunkListing`) that were written and
    are not in the store now: lost data (read back, they would be black). Every tile is written as a chunk, empty
    or not, and recorded in ``committed`` after it, so a missing chunk is lost when its tile is recorded committed,
    or anywhere in a complete store. Bounded by what is stored: the listings of both arrays, and a read of
    ``committed`` only where a tile recorded there has no chunk."""
    if group.attrs.get("state") == "complete":
        return list(video.missing_runs())
    if COMMITTED not in group:
        return []
    committed = group[COMMITTED]
    recorded, present = list_chunks(committed), set(video.stored)
    tail = (0,) * (len(video.grid) - 3)  # a tile's chunk spans the colour channels
    unwritten = {number: coords for coords in map(recorded.coordinates, recorded.stored)
                 if (number := video.number((*coords, *tail))) is not None and number not in present}
    if not unwritten:
        return []
    elements = np.array([[i * size for i, size in zip(coords, committed.chunks)] for coords in unwritten.values()])
    done = committed.get_coordinate_selection(tuple(elements.T))
    return [range(number, number + 1) for number, tile_done in zip(unwritten, done) if tile_done]


def lost_frames(group: zarr.Group) -> str | None:
    """``N of M chunks of video (output frames a..b (spike frames c..d), ...)`` for the lost chunks of a video
    store (:func:`lost_chunks`), or None if none is lost. Only the centres of the frames named are read."""
    video = list_chunks(group[VIDEO])
    lost = lost_chunks(group, video)
    if not lost:
        return None
    per_frame = math.prod(video.grid[1:])
    runs = []  # output frames with a lost chunk, consecutive ones as one [first, last]
    for chunks in lost:
        first, last = chunks.start // per_frame, (chunks.stop - 1) // per_frame
        if runs and first <= runs[-1][1] + 1:
            runs[-1][1] = max(runs[-1][1], last)
        else:
            runs.append([first, last])
    centres = group[FRAMES]
    named = [f"{a} (spike frame {centres[a]})" if a == b else f"{a}..{b} (spike frames {centres[a]}..{centres[b]})"
             for a, b in runs[:SHOWN]]
    shown = ", ".join(named) + (f", and {len(runs) - SHOWN} more" if len(runs) > SHOWN else "")
    several = len(runs) > 1 or runs[0][0] < runs[0][1]
    return (f"{sum(map(len, lost))} of {video.total} chunks of video (output frame{'s' if several else ''} "
            f"{shown})")


class TileWriter:
    """The output store opened once (per worker process and run) for many tile writes."""

    def __init__(self, url: str):
        group = zarr.open_group(zarr_store(url, read_only=False), mode="r+")
        # write_empty_chunks is a runtime setting, not stored: without it every write first
        # scans its whole chunk for emptiness (~30 % of a tile write).
        self.video = group[VIDEO].with_config({"write_empty_chunks": True})
        self.committed = group[COMMITTED]

    def write(self, index: int, tile_index: tuple[int, int], origin: tuple[int, int], image: np.ndarray) -> None:
        """Write one HR tile of output frame ``index`` (its own chunk), then record it committed."""
        self.write_frames(index, tile_index, origin, [image])

    def write_frames(self, first: int, tile_index: tuple[int, int], origin: tuple[int, int],
                     images: Sequence[np.ndarray]) -> None:
        """Write one HR tile of output frames ``first``, ``first + 1``, ... (``images``, (h, w, 3) each, a chunk
        each) together through Zarr's asynchronous API, so that it compresses and stores them at once on its
        threads (no copy into one array); then record them committed."""
        y, x = origin
        n = len(images)
        video = self.video.async_array

        async def every_frame() -> None:
            await asyncio.gather(*(video.setitem((first + k, slice(y, y + image.shape[0]), slice(x, x + image.shape[1])),
                                                 image) for k, image in enumerate(images)))

        sync(every_frame())
        self.committed[first : first + n, tile_index[0], tile_index[1]] = 1
