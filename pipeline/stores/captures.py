"""Raw captures (``.dat``, ``.npy``, ``.npz`` at any URL) read as a stream of packed blocks, or by frame range.

Each reader checks everything it can from sizes and headers before the first frame is
read, then yields ``(first_frame, packed_block)`` pairs of bounded size, so a capture larger
than memory goes through in constant memory.

A capture that is frames of a fixed size at a fixed offset (``.dat``, ``.npy``) is also *ranged*:
``read(start, stop)`` reads frames ``[start, stop)`` by one byte-range request, which is what a
parallel ingest's tasks do, each on its own worker (``pipeline.jobs.ingest``). What a capture offers:
``n_frames``, ``height``, ``width``, ``frame_bytes`` and ``offset`` (where frame 0 starts), ``ranged``,
``read``, ``blocks``, ``fingerprint``, ``unread_bytes`` (bytes at its end that are not read: 0 but for a
layout that reads a trailing partial frame) and ``unread_lead`` (bytes before its first whole frame: 0 but for a
layout that finds its first frame start). Another raw layout plugs in as a :class:`RawCapture` with a
layout object of its own: its ``frame_bytes``, ``offset``, ``frame_count(nbytes)`` and
``to_packed(raw, first_frame)`` ((n, frame_bytes) uint8 frames ``first_frame``.. -> (n, H, ceil(W/8)) packed,
upright), as :class:`stages.capture.dat.DatLayout` has, and ``check_tail(tail, first_frame)`` if its ``frame_count``
leaves a trailing partial frame (its bytes checked, an error if they are damaged); ``open_capture`` chooses it.
The megapixel camera's (``--layout sps100``, :class:`stages.capture.sps100.Sps100Layout`) is one: frames of a fixed
size from the first frame start, which is found in the capture's first bytes
(:func:`stages.capture.sps100.find_layout`) by every process that opens it, each task checking its own frames' tags,
the last task the trailing partial frame's as well (:meth:`RawCapture._packed`: the one place, for a stream
and for byte ranges alike).
"""

import hashlib

import tokenize
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from pipeline.stores.storage import check_not_empty, check_regular_file, resolve, unreachable
from stages.capture.spike_arrays import binary_to_packed, check_spike_array_header
from stages.capture import sps100
from stages.capture.dat import DatLayout
from stages.errors import InputError, describe

KINDS = (".dat", ".npy", ".npz")
RANGED_KINDS = (".dat", ".npy")  # read by frame range: what a parallel ingest reads
DEFAULT_NPZ_KEY = "spk"
ENDS_BYTES = 2**20  # bytes at each end of a capture that its fingerprint hashes


def _open(url: str):
    fs, path = resolve(url)
    if not fs.exists(path):
        raise InputError(_why_absent(fs, path, url))
    if fs.isdir(path):
        raise InputError(f"cannot read {url}: it is a directory, not a capture file")
    return fs, path


ARRAY_MAGIC = (b"\x93NUMPY", b"PK\x03\x04", b"PK\x05\x06")  # how a .npy and a .npz (a zip) begin


def _is_array_file(url: str) -> bool:
    """Whether the file at ``url`` begins as a ``.npy`` or ``.npz`` does (one read of its first bytes)."""
    fs, path = _open(url)
    return fs.cat_file(path, start=0, end=6).startswith(ARRAY_MAGIC)


def _why_absent(fs, path: str, url: str) -> str:
    """Why ``exists`` said no: fsspec's HTTP filesystem answers False for a host it cannot reach too
    (its ``info`` raises FileNotFoundError *from* the connection error), so ask about the cause."""
    try:
        fs.info(path)
    except OSError as error:
        if line := unreachable(error.__cause__ or error, [url]):
            return line
    return f"cannot read {url}: no such file"


def fingerprint(fs, path: str) -> dict:
    """What tells one capture from another cheaply, even at a terabyte: its size in bytes and a SHA-256 of
    its first and last :data:`ENDS_BYTES` (two range reads). ``ingest --resume`` compares it."""
    size = int(fs.size(path))
    digest = hashlib.sha256()
    for start, end in ((0, min(ENDS_BYTES, size)), (max(0, size - ENDS_BYTES), size)):
        digest.update(fs.cat_file(path, start=start, end=end) if end > start else b"")
    return {"bytes": size, "sha256_ends": digest.hexdigest()}


def _read_range(fs, path: str, url: str, start: int, end: int, first_frame: int) -> bytes:
    """Bytes ``[start, end)`` of the file, all of them or an error naming the frame where it ended."""
    data = fs.cat_file(path, start=start, end=end) if end > start else b""
    if len(data) != end - start:
        raise InputError(f"{url} ended early near frame {first_frame}: it changed while being read")
    return data


@dataclass
class RawCapture:
    """A headerless capture of fixed-size frames: a ``.dat`` (:class:`stages.capture.dat.DatLayout`), or any layout
    that converts a frame's bytes to packed frames (see the module docstring); its frame count follows
    from its size."""

    url: str
    layout: DatLayout
    ranged = True

    def __post_init__(self):
        self.fs, self.path = _open(self.url)
        nbytes = self.fs.size(self.path) - self.offset
        self.n_frames = self.layout.frame_count(nbytes)
        self.unread_bytes = nbytes - self.n_frames * self.frame_bytes  # a trailing partial frame, checked when read
        self.unread_lead = self.offset  # bytes before frame 0: an sps100 capture begun mid-frame (a .dat's: none)

    @property
    def height(self) -> int:
        return self.layout.height

    @property
    def width(self) -> int:
        return self.layout.width

    @property
    def frame_bytes(self) -> int:
        return self.layout.frame_bytes

    @property
    def offset(self) -> int:
        return self.layout.offset

    def _span(self, start: int, stop: int) -> int:
        """Bytes that reading frames ``[start, stop)`` reads: theirs, and with the last frames the trailing partial
        frame's (:attr:`unread_bytes`), whose packets :meth:`_packed` checks."""
        return (stop - start) * self.frame_bytes + (self.unread_bytes if stop == self.n_frames else 0)

    def _packed(self, data: bytes, count: int, first_frame: int) -> np.ndarray:
        """``count`` frames from ``first_frame`` packed, and the bytes after them, in ``data`` only with the last
        frames (:meth:`_span`), checked by the layout as a frame cut short: in the stream of one process and in
        a parallel ingest's last task alike, after the frames before them (so the first damage is named)."""
        whole_bytes = count * self.frame_bytes
        raw = np.frombuffer(data, np.uint8, count=whole_bytes).reshape(count, self.frame_bytes)
        try:
            packed = self.layout.to_packed(raw, first_frame)
            if len(data) > whole_bytes:
                self.layout.check_tail(data[whole_bytes:], first_frame + count)
            return packed
        except InputError as error:  # the layout's own words, the same type (sps100.CaptureDamaged), and the URL
            raise type(error)(f"{self.url}: {error}") from None

    def read(self, start: int, stop: int) -> np.ndarray:
        """Packed frames ``[start, stop)``, upright: one byte-range read."""
        begin = self.offset + start * self.frame_bytes
        return self._packed(_read_range(self.fs, self.path, self.url, begin, begin + self._span(start, stop), start),
                            stop - start, start)

    def blocks(self, frames_per_block: int, skip=()) -> Iterator[tuple[int, np.ndarray]]:
        """``(first_frame, packed)`` of each block of ``frames_per_block`` frames in order, one stream; the
        blocks whose first frame is in ``skip`` are neither read nor yielded."""
        frame_bytes = self.frame_bytes
        with self.fs.open(self.path, "rb", block_size=frames_per_block * frame_bytes) as stream:
            for start in range(0, self.n_frames, frames_per_block):
                if start in skip:
                    continue
                count = min(frames_per_block, self.n_frames - start)
                stream.seek(self.offset + start * frame_bytes)
                span = self._span(start, start + count)
                data = stream.read(span)
                if len(data) != span:
                    raise InputError(f"{self.url} ended early at frame {start}: it changed while being read")
                yield start, self._packed(data, count, start)

    def fingerprint(self) -> dict:
        return fingerprint(self.fs, self.path)


class ArrayCapture:
    """A (T, H, W) array of 0/1 in ``.npy`` or inside ``.npz``, streamed without loading it."""

    unread_bytes = unread_lead = 0  # no partial frame: its header says how many frames it holds, and where

    def __init__(self, url: str, *, key: str | None = None, flip: bool = False):
        self.url, self.flip = url, flip
        self.fs, self.path = _open(url)
        self.key = self._choose_key(key) if url.endswith(".npz") else None
        with self._stream() as stream:
            shape, self.dtype = self._read_header(stream)
            self.offset = stream.tell() if self.key is None else None  # where frame 0 starts in a .npy
        self.n_frames, self.height, self.width = shape
        self.frame_bytes = self.height * self.width * self.dtype.itemsize

    @property
    def ranged(self) -> bool:
        """A ``.npy`` is read by frame range; a ``.npz`` member (deflated, as a rule) only as one stream."""
        return self.key is None

    def read(self, start: int, stop: int) -> np.ndarray:
        """Packed frames ``[start, stop)`` of a ``.npy``: one byte-range read."""
        if not self.ranged:
            raise InputError(f"{self.url}: a .npz member is read as one stream, not by frame range")
        begin = self.offset + start * self.frame_bytes
        data = _read_range(self.fs, self.path, self.url, begin, begin + (stop - start) * self.frame_bytes, start)
        frames = np.frombuffer(data, self.dtype).reshape(stop - start, self.height, self.width)
        packed = binary_to_packed(frames, first_frame=start)
        return np.ascontiguousarray(packed[:, ::-1]) if self.flip else packed

    def fingerprint(self) -> dict:
        return fingerprint(self.fs, self.path)

    def _choose_key(self, key: str | None) -> str:
        with self.fs.open(self.path, "rb") as raw:
            try:
                names = [n[:-4] for n in zipfile.ZipFile(raw).namelist() if n.endswith(".npy")]
            except zipfile.BadZipFile:
                raise InputError(f"{self.url} is not a valid .npz archive") from None
        if key is None:
            key = DEFAULT_NPZ_KEY if DEFAULT_NPZ_KEY in names or len(names) != 1 else names[0]
        if key not in names:
            raise InputError(f"{self.url} has no array {key!r} (it holds {', '.join(names) or 'nothing'}); choose one with --key")
        return key

    def _stream(self):
        raw = self.fs.open(self.path, "rb")
        if self.key is None:
            return raw
        return _ClosingMember(raw, zipfile.ZipFile(raw).open(f"{self.key}.npy"))

    def _read_header(self, stream) -> tuple[tuple, np.dtype]:
        try:
            version = np.lib.format.read_magic(stream)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(stream)
        except (ValueError, SyntaxError, TypeError, tokenize.TokenError, zipfile.BadZipFile, zlib.error, EOFError) as error:
            raise InputError(f"{self.url} is not a valid .npy array: {describe(error)}") from None
        check_spike_array_header(shape, dtype)
        frame_bytes = int(np.prod(shape[1:], dtype=object)) * dtype.itemsize
        if self.key is None and frame_bytes * shape[0] > self.fs.size(self.path):  # checked before reading anything
            raise InputError(f"{self.url} is truncated: its header promises {shape[0]} frames of {frame_bytes} bytes, "
                             f"more than the file holds")
        if frame_bytes > 2**31:
            raise InputError(f"{self.url}: frames of shape {tuple(shape[1:])} are too large to be spike frames")
        if fortran:
            raise InputError(f"{self.url} holds a Fortran-ordered array; save it C-ordered (np.ascontiguousarray)")
        return shape, dtype

    def blocks(self, frames_per_block: int, skip=()) -> Iterator[tuple[int, np.ndarray]]:
        """As :meth:`RawCapture.blocks`; a skipped block of a ``.npz`` is still read (a stream), not packed."""
        frame_items = self.height * self.width
        with self._stream() as stream:
            self._read_header(stream)
            for start in range(0, self.n_frames, frames_per_block):
                count = min(frames_per_block, self.n_frames - start)
                nbytes = count * frame_items * self.dtype.itemsize
                if start in skip and self.ranged:
                    stream.seek(self.offset + (start + count) * self.frame_bytes)
                    continue
                try:
                    data = stream.read(nbytes)
                except (zlib.error, zipfile.BadZipFile, EOFError) as error:
                    raise InputError(f"{self.url} is damaged near frame {start}: {describe(error)}") from None
                if start in skip:
                    continue
                if len(data) != nbytes:
                    raise InputError(f"{self.url} is truncated: frame {start + len(data) // (frame_items * self.dtype.itemsize)} of {self.n_frames} is incomplete")
                frames = np.frombuffer(data, self.dtype).reshape(count, self.height, self.width)
                packed = binary_to_packed(frames, first_frame=start)
                yield start, np.ascontiguousarray(packed[:, ::-1]) if self.flip else packed


class _ClosingMember:
    """A zip member stream that also closes the archive's underlying file."""

    def __init__(self, raw, member):
        self.raw, self.member = raw, member

    def read(self, n: int = -1) -> bytes:
        return self.member.read(n)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.member.close()
        self.raw.close()


def default_layout(url: str) -> str | None:
    """The raw layout a capture is read with when none is named: ``dat`` for a ``.dat``, else None (an array)."""
    return "dat" if _suffix(url) == ".dat" else None


def _suffix(url: str) -> str:
    return "." + str(url).rsplit(".", 1)[-1].lower() if "." in str(url) else ""


def open_sps100(url: str, *, height: int | None = None, width: int | None = None, flip: bool = False,
                head_columns: int = 0) -> RawCapture:
    """The megapixel camera's raw capture (:mod:`stages.capture.sps100`), whatever its name: 1000x1000 frames from its
    first frame start, found in its first :data:`stages.capture.sps100.HEAD_BYTES` (one range read)."""
    if head_columns:
        raise InputError("--head-columns applies to the .dat layout only: an sps100 capture's tag bits are dropped "
                         "by the layout")
    for label, given in (("height", height), ("width", width)):
        if given is not None and given != sps100.HEIGHT:
            raise InputError(f"--{label} {given} is inconsistent with the sps100 layout's fixed {sps100.HEIGHT}x"
                             f"{sps100.WIDTH} frames: leave --{label} out")
    fs, path = _open(url)
    size = int(fs.size(path))
    head = _read_range(fs, path, url, 0, min(size, sps100.HEAD_BYTES), 0)
    try:
        layout = sps100.find_layout(head, flip=flip, complete=size <= sps100.HEAD_BYTES)
    except InputError as error:
        raise type(error)(f"{url}: {error}") from None
    return RawCapture(url, layout)


def open_capture(url: str, *, height: int | None, width: int | None, flip: bool = False, head_columns: int = 0,
                 key: str | None = None, layout: str | None = None):
    """The reader for a capture, with the declared sizes checked: chosen by ``layout`` (a raw layout of
    :data:`stages.capture.sps100.LAYOUTS`, whatever the file's name), else by its extension."""
    check_not_empty(url)
    check_regular_file(url, "capture")  # a named pipe's reader waits for a writer; a folder is no capture
    suffix = _suffix(url)
    if layout is not None:
        sps100.check_layout(layout)
        if suffix in (".npy", ".npz") and _is_array_file(url):  # by its bytes: a raw capture may have any name
            raise InputError(f"--layout {layout} names a raw capture's layout, and {url} is a {suffix} array: leave "
                             f"--layout out")
    if key is not None and (layout is not None or suffix != ".npz"):  # before anything is read or created
        kind = f"an {layout}" if layout == "sps100" else f"a {layout or suffix or 'raw'}"
        raise InputError(f"--key names an array inside a .npz, and {url} is {kind} capture, which has none: leave "
                         f"--key out")
    if layout is not None:
        if layout == "sps100":
            return open_sps100(url, height=height, width=width, flip=flip, head_columns=head_columns)
        suffix = ".dat"
    if suffix == ".dat":
        if height is None or width is None:
            raise InputError("a .dat capture has no header: give both --height and --width")
        return RawCapture(url, DatLayout(height, width, head_columns, flip))
    if suffix in (".npy", ".npz"):
        if head_columns:
            raise InputError("--head-columns applies to .dat captures only")
        capture = ArrayCapture(url, key=key, flip=flip)
        for label, given, actual in (("height", height, capture.height), ("width", width, capture.width)):
            if given is not None and given != actual:
                raise InputError(f"--{label} {given} is inconsistent with the array's {label} {actual} in {url}")
        return capture
    raise InputError(f"unknown capture type {suffix or '(no extension)'} for {url}: expected one of {', '.join(KINDS)}, "
                     f"or name a raw layout with --layout ({', '.join(sps100.LAYOUTS)})")
