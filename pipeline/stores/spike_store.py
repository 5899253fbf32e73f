"""The spike store: a Zarr v3 group holding bit-packed spike frames and their metadata.

Layout (see ``PRODUCT.md``): ``spikes`` uint8 ``(T, H, ceil(W/8))``, chunked by whole frames
along time, compressed with zstd level 1 (measured: within 1-8 % of the entropy bound at
firing rates >= 0.1 and the fastest codec tried; ``benchmarks/size_at_rest.py``).

Every chunk is written, empty or not. Writing follows xarray's habit: the group, the array metadata and every attribute are
written first with ``state = "writing"``; regions are filled next (each a whole number of
chunks, so parallel writers never share a chunk); ``state`` becomes ``"complete"`` last.
Readers refuse a store that is not complete, so an interrupted ingest never passes for
a finished one, and one whose ``format_version`` they do not know or whose metadata contradicts
itself (the length of ``spikes`` against its ``frames`` attribute, ``spike_count``, the consolidated
copy or the ingest tasks: :meth:`SpikeStore._contradiction`), so an edited store never passes either.

Every store gets an ``identity`` when it is finished: a SHA-256 of what it records and of the bits
of its first and last frames (:func:`recording_identity`), so the same capture ingested again (or the
same simulation run again) gives the same bytes and identity, a copy keeps it, and another recording
at the same path has another. An output records the identity and shape of the store it was made from,
and ``--resume`` refuses a store that is not that one (:func:`store_identity`).

An ingested store also holds ``committed``: int64, one element (and chunk) per ingest task (a run of
whole chunks of ``spikes``), the spikes counted in that task's frames, written once they are stored;
-1 = not committed. Its attributes record the capture (size and a checksum of its ends) and the ingest
options, which ``ingest --resume`` compares (``pipeline.jobs.ingest``).
"""

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from cscsr.version import __version__
from pipeline.stores.storage import consolidate, open_group, remove_partial_writes, zarr_store
from pipeline.stores.video_store import check_format_version, consolidated_shapes, describe_video_store, is_video_store
from stages.capture.bits import packed_width
from stages.capture.dat import check_head_side
from stages.errors import InputError, describe
from stages.numbers import as_float, check_number
from stages.reconstruction.cfa import check_cfa
from stages.reconstruction.colour import MAX_GAIN
from stages.capture.resets import check_reset

FORMAT_VERSION = 1
SPIKES = "spikes"
COMMITTED = "committed"  # an ingested store's record of its tasks (the module docstring)
CODEC_LEVEL = 1
TARGET_CHUNK_BYTES = 4 * 2**20
# What a viewer shows beside the spikes (``spikes``'s own attributes; xarray shows them as the variable's).
SPIKES_UNITS = "bit-packed spikes, 1 = fired"
SPIKES_PACKING = "8 pixels per byte along x, least significant bit first: pixel x is bit x % 8 of byte x // 8"
# Encode chunks on every core, a few in flight each: 1.3x faster writes than Zarr's
# defaults on 2 cores (benchmarks/ingest_throughput.py); zstd releases the GIL.
WRITE_CONFIG = {"threading.max_workers": os.cpu_count() or 1, "async.concurrency": 2 * (os.cpu_count() or 1)}


MIN_FPS = 1.0  # spike frames a second: a rate below it is a frame period given for the rate (5e-05 s at 20 kHz)


def check_fps(name: str, fps) -> None:
    """Refuse a spike-frame rate that is no rate (not a number > 0) or that is a frame period given for one."""
    check_number(name, fps, above=0)
    if fps < MIN_FPS:
        raise InputError(f"{name} must be >= {MIN_FPS:g} spike frame a second, got {fps:g}: it is a rate, not a "
                         f"frame period (20 kHz is {name} 20000)")


@dataclass(frozen=True)
class SpikeMeta:
    """What a spike store says about its recording (the group's attributes)."""

    height: int
    width: int
    cfa: str = "mono"
    fps: float = 20000.0
    source: str = ""
    flipped: bool = False
    head_columns: int = 0
    head_at: str = "end"  # where the .dat header columns were; stores without it had them at the start
    reset: str = "subtract"
    gain: float | None = None
    threshold: float | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "cfa", check_cfa(self.cfa, self.height, self.width))
        check_fps("fps", self.fps)
        object.__setattr__(self, "fps", as_float(self.fps))  # an int fps records the bytes a float one does
        for name in ("gain", "threshold"):  # optional: simulated stores record them
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), **_ATTRIBUTE_RANGES[name])
        check_head_side(self.head_at)
        check_reset(self.reset)

    def attrs(self) -> dict:
        attrs = {k: v for k, v in asdict(self).items() if k != "extra" and v is not None}
        attrs.update(self.extra, format_version=FORMAT_VERSION, cscsr_version=__version__)
        return attrs

    @classmethod
    def from_attrs(cls, attrs: dict) -> "SpikeMeta":
        missing = [k for k in ("height", "width", "cfa") if k not in attrs]
        if missing:
            raise InputError(f"spike store attributes lack {', '.join(missing)}")
        check_attribute_types(attrs)
        if attrs.get("head_columns") and "head_at" not in attrs:  # written when header columns led each row
            attrs = {**attrs, "head_at": "start"}
        known = {f for f in cls.__dataclass_fields__ if f != "extra"}
        extra = {k: v for k, v in attrs.items()
                 if k not in known | {"format_version", "cscsr_version", "state", "spike_count", "identity", "frames"}}
        return cls(**{k: attrs[k] for k in known if k in attrs}, extra=extra)


# What each attribute must be: a store written by hand or damaged is refused by name, never misread
# (a string "no" for flipped would otherwise read as true and export frames upside down).
_ATTRIBUTE_TYPES = {"height": int, "width": int, "head_columns": int, "spike_count": int, "frames": int, "scale": int,
                    "fps": float, "gain": float, "threshold": float, "flipped": bool, "cfa": str, "reset": str,
                    "head_at": str, "identity": str}


# The range of each number a store records: finite, and one that its readers can use (a negative
# gain or a scale of 0 would otherwise fail inside every task, an infinite fps print as invalid JSON).
_ATTRIBUTE_RANGES = {"fps": {"above": 0, "at_least": MIN_FPS}, "gain": {"above": 0, "at_most": MAX_GAIN},
                     "threshold": {"above": 0}, "spike_count": {"at_least": 0}, "frames": {"at_least": 0}, "scale": {"at_least": 1},
                     "truth_every": {"at_least": 1, "integer": True}, "brightness": {"above": 0}}


def check_attribute_types(attrs: dict) -> None:
    for name, kind in _ATTRIBUTE_TYPES.items():
        if name not in attrs or attrs[name] is None:
            continue
        value = attrs[name]
        ok = (isinstance(value, bool) if kind is bool else
              isinstance(value, int) and not isinstance(value, bool) if kind is int else
              isinstance(value, (int, float)) and not isinstance(value, bool) if kind is float else isinstance(value, str))
        if not ok:
            label = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}[kind]
            raise InputError(f"attribute {name} must be {label}, got {value!r}")
    for name in ("height", "width"):
        if attrs[name] <= 0:
            raise InputError(f"attribute {name} must be positive, got {attrs[name]}")
    for name, bounds in _ATTRIBUTE_RANGES.items():
        if attrs.get(name) is not None:
            check_number(f"attribute {name}", attrs[name], **bounds)


def chunk_frames_for(meta: SpikeMeta, n_frames: int) -> int:
    """Frames per chunk: about 4 MiB of packed frames, at most the whole recording."""
    frame_bytes = meta.height * packed_width(meta.width)
    return max(1, min(n_frames, TARGET_CHUNK_BYTES // frame_bytes))


class SpikeStore:
    """A spike store opened for reading: metadata plus block reads of packed frames."""

    def __init__(self, url: str, group: zarr.Group):
        self.url = url
        self.group = group
        self.attrs = dict(group.attrs)
        check_format_version(self.attrs, f"spike store {url}", FORMAT_VERSION)
        try:
            self.meta = SpikeMeta.from_attrs(self.attrs)
        except InputError as error:
            raise InputError(f"spike store {url}: {error}") from None
        if SPIKES not in group:
            raise InputError(f"{url} is not a spike store: it has no '{SPIKES}' array")
        self.spikes: zarr.Array = group[SPIKES]
        if not isinstance(self.spikes, zarr.Array):
            raise InputError(f"{url} is not a spike store: its '{SPIKES}' is a group, not an array")
        expected = (self.meta.height, packed_width(self.meta.width))
        if self.spikes.dtype != np.uint8 or self.spikes.ndim != 3 or self.spikes.shape[1:] != expected:
            raise InputError(
                f"{url}: '{SPIKES}' is {self.spikes.dtype} {self.spikes.shape}, expected uint8 (T, {expected[0]}, {expected[1]})"
            )
        if problem := self._contradiction():
            raise InputError(f"spike store {url}: metadata inconsistent: {problem}: the store was altered or damaged; "
                             f"make it again from its source")

    def _contradiction(self) -> str | None:
        """What the store's own records say against the frame count of ``spikes`` (its shape), or None. Metadata
        only, no chunk read: the ``frames`` attribute (written with the array's metadata), ``spike_count`` (at most
        every pixel of every frame), the consolidated copy of the arrays' metadata in the root ``zarr.json``, and an
        ingested store's task record (``committed``: one element per ``task_frames`` frames). Each is compared where
        it is recorded: an unfinished store has neither a count nor a consolidated copy yet, and a store from before
        them is read as before."""
        n, height, width = self.shape
        if (recorded := self.attrs.get("frames")) is not None and recorded != n:
            return f"'{SPIKES}' has {n} frames, but the store records {recorded} (attribute frames)"
        count = self.attrs.get("spike_count")
        if isinstance(count, int) and not isinstance(count, bool) and count > n * height * width:
            return (f"spike_count {count} is more than its {n} frames of {height}x{width} pixels can hold "
                    f"({n * height * width})")
        for name, shape in consolidated_shapes(self.group).items():
            if name in self.group and isinstance(own := self.group[name], zarr.Array) and tuple(own.shape) != shape:
                return (f"'{name}' is {tuple(own.shape)} in {name}/zarr.json but {shape} in the consolidated copy in "
                        f"zarr.json")
        if COMMITTED in self.group and isinstance(committed := self.group[COMMITTED], zarr.Array):
            task_frames = committed.attrs.get("task_frames")
            if (isinstance(task_frames, int) and not isinstance(task_frames, bool) and task_frames > 0
                    and committed.ndim == 1 and committed.shape[0] != -(-n // task_frames)):
                return (f"'{SPIKES}' has {n} frames, but '{COMMITTED}' records {committed.shape[0]} ingest tasks of "
                        f"{task_frames} frames ({-(-n // task_frames)} for {n} frames)")
        return None

    @property
    def n_frames(self) -> int:
        return self.spikes.shape[0]

    @property
    def complete(self) -> bool:
        return self.attrs.get("state") == "complete"

    @property
    def spike_count(self) -> int | None:
        return self.attrs.get("spike_count")

    def read(self, start: int, stop: int) -> np.ndarray:
        """Packed frames ``[start, stop)``; an error naming the frames if a chunk is missing or damaged."""
        return read_frames(self.spikes, self.url, start, stop)

    @property
    def shape(self) -> tuple[int, int, int]:
        """(frames, height, width) of the recording, in pixels."""
        return self.n_frames, self.meta.height, self.meta.width


IDENTITY_FRAMES = 64  # frames read at each end of a recording for its identity: milliseconds of work
NOT_IDENTITY = ("state", "identity", "source", "cscsr_version", "format_version",  # where and by what, not what
                "frames")  # the shape's, hashed as such: identities stay those of stores from before it


def recording_identity(attrs: dict, spikes: zarr.Array) -> str:
    """A finished recording's identity: the SHA-256 of every attribute its writer recorded but those that
    say where and by what it was written (:data:`NOT_IDENTITY`): its settings, spike count, ...; its shape;
    and the bits of its first and last :data:`IDENTITY_FRAMES` frames. Independent of chunking, of the
    workers that wrote it and of the release of cscsr."""
    described = json.dumps({"attrs": {k: v for k, v in attrs.items() if k not in NOT_IDENTITY},
                            "shape": list(spikes.shape)}, sort_keys=True, default=str)
    digest = hashlib.sha256(described.encode())
    n_frames = spikes.shape[0]
    for start, stop in ((0, min(IDENTITY_FRAMES, n_frames)), (max(0, n_frames - IDENTITY_FRAMES), n_frames)):
        digest.update(np.ascontiguousarray(spikes[start:stop]).tobytes())
    return digest.hexdigest()


def store_identity(store: SpikeStore) -> str:
    """What names this recording and no other: the ``identity`` written when the store was finished
    (:func:`recording_identity`).

    Stores from before identities have none; theirs is ``metadata-`` and a SHA-256 of what their
    writer recorded once it finished: every attribute but ``state`` (the source, its spike count,
    the sensor's settings, ...) and the array's shape and chunking. No chunk is read: a chunk lost
    and put back, or a damaged one, does not change it (the tasks that read such a chunk say so).
    Another recording differs there unless it has the same source, settings and spike count.
    """
    if store.attrs.get("identity"):
        return store.attrs["identity"]
    attrs = {k: v for k, v in store.attrs.items() if k != "state"}
    described = json.dumps({"attrs": attrs, "shape": store.spikes.shape, "chunks": store.spikes.chunks},
                           sort_keys=True, default=str)
    return "metadata-" + hashlib.sha256(described.encode()).hexdigest()


def read_frames(spikes: zarr.Array, url: str, start: int, stop: int, region: tuple = ()) -> np.ndarray:
    """Frames ``[start, stop)`` of a spike array (rows and packed columns ``region``), refusing to
    read a missing chunk as zeros.

    The writer stores every chunk, empty or not (``write_empty_chunks``), so a chunk that is not
    there is lost data, which Zarr would silently fill with zeros.
    """
    from zarr.core.sync import sync

    step = spikes.chunks[0]
    prefix = f"{spikes.store_path.path}/" if spikes.store_path.path else ""
    for index in range(start // step, -(-stop // step)):
        key = prefix + spikes.metadata.encode_chunk_key((index, 0, 0))
        if not sync(spikes.store.exists(key)):
            raise InputError(f"spike store {url}: the chunk of frames {index * step}..{(index + 1) * step - 1} is "
                             f"missing (lost data)")
    try:
        return spikes[(slice(start, stop), *region)]
    except (RuntimeError, ValueError) as error:
        raise InputError(f"spike store {url}: frames {start}..{stop - 1} cannot be read, a chunk is damaged "
                         f"({describe(error)})") from None


def open_spike_store(url: str, *, allow_incomplete: bool = False) -> SpikeStore:
    """Open and check a spike store; an error if it is missing, malformed or unfinished."""
    group = open_group(url, "spike store")
    if is_video_store(group):
        source = group.attrs.get("source")
        raise InputError(f"{describe_video_store(url, group)}, not a spike store: give the spike store it was made "
                         f"from{f' ({source})' if source else ''}")
    try:
        store = SpikeStore(url, group)
    except InputError:
        raise
    except (ValueError, TypeError, KeyError, AttributeError, zarr.errors.BaseZarrError) as error:  # damaged arrays
        raise InputError(f"cannot read spike store {url}: its Zarr metadata is damaged or not a spike store's "
                         f"({describe(error)})") from None
    if not (allow_incomplete or store.complete):
        raise InputError(f"spike store {url} is incomplete (state {store.attrs.get('state')!r}): its writer did not finish")
    return store


class SpikeStoreWriter:
    """Creates a spike store (metadata first), fills it by regions, then marks it complete."""

    def __init__(self, url: str, meta: SpikeMeta, n_frames: int, *, chunk_frames: int | None = None):
        """Write the group and array metadata at ``url``, which the caller has claimed."""
        self.url = url
        self.chunk_frames = chunk_frames or chunk_frames_for(meta, n_frames)
        self.group = zarr.open_group(zarr_store(url, read_only=False), mode="w",
                                     attributes={**meta.attrs(), "frames": n_frames, "state": "writing"})
        self.spikes = self.group.create_array(
            SPIKES,
            shape=(n_frames, meta.height, packed_width(meta.width)),
            chunks=(self.chunk_frames, meta.height, packed_width(meta.width)),
            dtype=np.uint8,
            fill_value=0,
            compressors=ZstdCodec(level=CODEC_LEVEL),
            dimension_names=("t", "y", "xbyte"),
            attributes={"units": SPIKES_UNITS, "packing": SPIKES_PACKING, "fps": meta.fps, "width": meta.width},
            # Write every chunk: skipping all-zero ones costs a full scan of the data (halving
            # write speed) and makes "chunk exists" meaningless; an empty chunk is ~20 bytes.
            config={"write_empty_chunks": True},
        )

    @classmethod
    def reopened(cls, url: str) -> "SpikeStoreWriter":
        """The writer of the unfinished store at ``url`` (which the caller has claimed), to fill its remaining
        regions and finish it (``ingest --resume``); opening it writes nothing."""
        writer = cls.__new__(cls)
        writer.url = url
        writer.group = zarr.open_group(zarr_store(url, read_only=False), mode="r+", use_consolidated=False)
        writer.spikes = writer.group[SPIKES].with_config({"write_empty_chunks": True})
        writer.chunk_frames = writer.spikes.chunks[0]
        return writer

    def add_array(self, name: str, shape: tuple, chunks: tuple, dtype, dimension_names: tuple,
                  attributes: dict | None = None, fill_value=0) -> None:
        """Declare another array of the store (``truth``, ``flow``, ``committed``, ...) before regions are filled.
        Dimension names mean one thing per store (xarray refuses two lengths under one name)."""
        self.group.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill_value,
                                compressors=ZstdCodec(level=CODEC_LEVEL), dimension_names=dimension_names,
                                attributes=attributes or {}, config={"write_empty_chunks": True})

    def write(self, start: int, packed: np.ndarray) -> None:
        """Write frames ``[start, start + len(packed))``; ``start`` must begin a chunk."""
        if start % self.chunk_frames:
            raise ValueError(f"region start {start} is not on a chunk boundary ({self.chunk_frames} frames)")
        with zarr.config.set(WRITE_CONFIG):
            self.spikes[start : start + packed.shape[0]] = packed

    def finish(self, **attrs) -> None:
        """Record final attributes, consolidate the metadata, and mark the store complete (the last write)."""
        self.group.attrs.update(attrs)
        self.group.attrs["identity"] = recording_identity(dict(self.group.attrs), self.spikes)
        remove_partial_writes(self.url)  # a worker killed mid-write leaves its temporary file
        consolidate(self.url)
        # reopened: the group held here knows nothing of the consolidated copy, and would drop it on writing
        self.group = zarr.open_group(zarr_store(self.url, read_only=False), mode="r+")
        self.group.attrs["state"] = "complete"




def write_region(url: str, name: str, start: int, data: np.ndarray) -> None:
    """Fill ``name[start : start + len(data)]`` of the store at ``url`` (run by workers).

    The region must cover whole chunks along the first axis (or end the array), so that
    no two writers ever touch the same chunk.
    """
    array = zarr.open_array(zarr_store(url, read_only=False), path=name, mode="r+")
    array = array.with_config({"write_empty_chunks": True})  # a runtime setting: not stored
    chunk = array.chunks[0]
    stop = start + data.shape[0]
    if start % chunk or (stop % chunk and stop != array.shape[0]):
        raise ValueError(f"region {start}:{stop} of {name} does not cover whole chunks of {chunk}")
    with zarr.config.set(WRITE_CONFIG):
        array[start:stop] = data


def ingest_task_arrays(url: str) -> tuple[zarr.Array, zarr.Array]:
    """The spike array and the task record (``committed``) of a store being ingested in parallel, opened for
    its tasks' writes (``write_empty_chunks``, a runtime setting: every chunk is written, empty or not)."""
    writer = SpikeStoreWriter.reopened(url)
    return writer.spikes, writer.group[COMMITTED]
