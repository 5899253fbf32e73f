"""The megapixel (1000x1000, "SPS100") camera's raw PCIe captures <-> packed store frames.

**Built from the public reader's layout, not from a real capture.** The only public reader is SpikeCV's
``SpikeStream.get_sps100_matrix`` (``spkData/load_dat.py``) with its tag parser ``SPSParser``
(``spkData/sps_parser.py``); no capture with a known answer has been available to check this against.

The geometry (what this module assumes, in the public reader's terms):

- The capture is a stream of 16-byte packets, cut into *half-lines* of 64 bytes = 4 packets = 512 bits.
  Bits are numbered least significant first within each byte, as in a ``.dat`` (:mod:`stages.capture.dat`): bit
  ``b`` of a half-line is bit ``b % 8`` of its byte ``b // 8``.
- Bits 0..499 of a half-line are 500 pixels, 1 = fired; bits 500..511 are its 12-bit *tag*. Read as the
  public parser does, the last two bytes of the half-line's last packet as a little-endian ``v``: the
  line number ``(v >> 4) & 0x3FF`` (1..500) and the channel ``v >> 14`` (0..3). (Bits 0..3 of ``v`` are
  pixels 496..499.)
- A *frame* is 2000 half-lines (500 lines x 4 channels, each pair once): it starts at the half-line
  tagged line 500, channel 0 and ends at the one tagged line 500, channel 3. A capture may begin
  anywhere (mid-frame, mid-packet): the leading part before the first whole frame and a trailing partial
  frame are not read.
- Rows and columns *by position*, as the public reader reads them (it reads 1024-bit rows from the frame
  start): half-line ``k`` of a frame (0..1999, counted from its line-500-channel-0 half-line) holds row
  ``k // 2``, columns ``500 * (k % 2)`` .. ``500 * (k % 2) + 499``, pixel ``x`` of the half-line in column
  ``500 * (k % 2) + x``. The tags are checked, never used to place pixels: every frame repeats the first
  whole frame's (line, channel) sequence, so a mapping by tag, if a real capture shows one, is a fixed
  permutation of these rows and halves. (The public reader drops columns 500..511 and 1000..1011 of each
  1024-bit row; the tag bits are 500..511 and 1012..1023 by the layout above, which is what is dropped
  here.) Frames are upright as read (the public reader flips nothing); ``flip`` reverses rows as for
  ``.dat``.

Every half-line's tag is checked: the first whole frame's must be a valid sequence (:func:`find_layout`)
and every later frame must repeat it (:meth:`Sps100Layout.to_packed`), the trailing partial frame's whole
half-lines too (:meth:`Sps100Layout.check_tail`, read with the last frames), so a dropped or corrupted packet
is refused with the byte offset of the first packet whose tag does not fit (:class:`CaptureDamaged`); a
trailing partial frame whose packets are in sequence is a capture cut short, its bytes not read.
All of it vectorised: no Python loop per half-line.
"""

from dataclasses import dataclass

import numpy as np

from stages.errors import InputError

LAYOUTS = ("dat", "sps100")  # the raw layouts ingest reads: stages.capture.dat's frames, this module's packets

HEIGHT = WIDTH = 1000
PACKET_BYTES = 16
HALF_BYTES = 64  # a half-line: 4 packets, 512 bits
HALF_PIXELS = 500
HALVES = 2 * HEIGHT  # half-lines per frame
FRAME_BYTES = HALVES * HALF_BYTES  # 128,000
TAG_AT = HALF_BYTES - 2  # the tag's little-endian word: the last two bytes of a half-line
LINES, CHANNELS = 500, 4
START_TAG = LINES | (0 << 10)  # line 500, channel 0: the first half-line of a frame (tag = v >> 4)
END_TAG = LINES | (3 << 10)  # line 500, channel 3: the last
HEAD_BYTES = 2 * FRAME_BYTES + HALF_BYTES  # what finding the first whole frame reads: any start, one whole frame


class CaptureDamaged(InputError):
    """A capture's content is not what its format says: packets that do not follow its layout (a packet dropped or
    corrupted: one line naming the first bad packet's byte offset), or an array's spike values other than 0 and 1
    (``spike_arrays``). Found as its frames are read, and found again by any resume: the new store is removed."""


def check_layout(name: str) -> str:
    if name not in LAYOUTS:
        raise InputError(f"unknown raw layout {name!r}: expected one of {', '.join(LAYOUTS)}")
    return name


def _tag_words(data: np.ndarray) -> np.ndarray:
    """The 12-bit tags (``v >> 4``) of the little-endian words at ``data[..., 0]``, ``data[..., 1]``."""
    return (data[..., 0].astype(np.uint16) | (data[..., 1].astype(np.uint16) << 8)) >> 4


def describe_tag(tag: int) -> str:
    return f"line {tag & 0x3FF}, channel {tag >> 10}"


def _tag_packet(half_line_start: int) -> int:
    """Byte offset of the packet that carries a half-line's tag (its last)."""
    return half_line_start + HALF_BYTES - PACKET_BYTES


@dataclass(frozen=True)
class Sps100Layout:
    """Where the first whole frame of a capture starts (``offset``, bytes), the (line, channel) sequence every
    frame repeats (``sequence``: 2000 little-endian uint16 tags, ``line | channel << 10``), and ``flip``. The
    layout object of :class:`pipeline.stores.captures.RawCapture` (``frame_bytes``, ``offset``, ``frame_count``,
    ``to_packed``)."""

    offset: int
    sequence: bytes
    flip: bool = False

    height = HEIGHT
    width = WIDTH
    frame_bytes = FRAME_BYTES
    head_columns = 0

    def __post_init__(self):
        if len(self.sequence) != 2 * HALVES:
            raise InputError(f"an sps100 tag sequence is {HALVES} tags, got {len(self.sequence) // 2}")

    @property
    def tags(self) -> np.ndarray:
        return np.frombuffer(self.sequence, "<u2")

    def frame_count(self, nbytes: int) -> int:
        """Whole frames in the ``nbytes`` from :attr:`offset` on (a trailing partial frame is not read, its
        packets checked: :meth:`check_tail`)."""
        frames = nbytes // FRAME_BYTES
        if frames == 0:
            raise InputError(f"capture holds no whole sps100 frame ({FRAME_BYTES} bytes) after its first frame "
                             f"start at byte {self.offset}")
        return frames

    def to_packed(self, raw: np.ndarray, first_frame: int = 0) -> np.ndarray:
        """(n, 128000) uint8 frames ``first_frame``.. -> (n, 1000, 125) packed frames, upright; every half-line's
        tag checked against :attr:`sequence` first (:class:`CaptureDamaged` names the first that differs)."""
        n = raw.shape[0]
        halves = raw.reshape(n, HALVES, HALF_BYTES)
        self._check_tags(halves, first_frame)
        return halves_to_packed(halves, flip=self.flip)

    def check_tail(self, tail: bytes, first_frame: int) -> None:
        """The bytes after the last whole frame (frame ``first_frame``, cut short), checked as any frame's: each
        whole half-line's tag against :attr:`sequence`, so a packet dropped or corrupted in the last frame is
        refused naming its byte offset as in any other (:class:`CaptureDamaged`); if they pass, they are a
        frame cut short, not read. (Bytes after the last whole half-line carry no tag: a packet dropped there
        cannot be told from a capture that ends there.)"""
        data = np.frombuffer(tail, np.uint8)
        if data.size >= FRAME_BYTES:
            raise ValueError(f"a tail is less than a frame ({FRAME_BYTES} bytes), got {data.size}")
        whole = data.size // HALF_BYTES
        self._check_tags(data[:whole * HALF_BYTES].reshape(1, whole, HALF_BYTES), first_frame)

    def _check_tags(self, halves: np.ndarray, first_frame: int) -> None:
        """Every tag of ``halves`` ((n, k, 64) uint8: frames ``first_frame``.., each its first k half-lines, all
        2000 but in a frame cut short) against the first k of :attr:`sequence`; :class:`CaptureDamaged` names
        the first that differs, by the byte offset of the packet that carries it."""
        count = halves.shape[1]
        tags = _tag_words(halves[:, :, TAG_AT:])
        bad = tags != self.tags[:count]
        if bad.any():
            frame, k = divmod(int(np.argmax(bad.ravel())), count)
            start = self.offset + (first_frame + frame) * FRAME_BYTES + k * HALF_BYTES
            raise CaptureDamaged(
                f"sps100 packets out of sequence at byte {_tag_packet(start)}: half-line {k} of frame "
                f"{first_frame + frame} is tagged {describe_tag(int(tags[frame, k]))}, where every frame repeats "
                f"the first whole frame's {describe_tag(int(self.tags[k]))} (a packet dropped or corrupted)")


def halves_to_packed(halves: np.ndarray, *, flip: bool = False) -> np.ndarray:
    """(n, 2000, 64) uint8 half-lines -> (n, 1000, 125) packed rows (LSB first). A row's first half gives its
    bytes 0..61 as they are and the low nibble of byte 62 (columns 496..499); its second half's 500 bits
    start at column 500, mid-byte: shifted by 4 bits, in byte operations only."""
    n = halves.shape[0]
    rows = halves.reshape(n, HEIGHT, 2, HALF_BYTES)
    left, right = rows[:, :, 0], rows[:, :, 1]
    packed = np.empty((n, HEIGHT, WIDTH // 8), np.uint8)
    packed[:, :, :62] = left[:, :, :62]
    packed[:, :, 62] = (left[:, :, 62] & 0x0F) | (right[:, :, 0] << 4)
    np.bitwise_or(right[:, :, :62] >> 4, right[:, :, 1:63] << 4, out=packed[:, :, 63:])
    return np.ascontiguousarray(packed[:, ::-1]) if flip else packed


def find_layout(head: bytes, *, flip: bool = False, complete: bool) -> Sps100Layout:
    """The layout of a capture from its first bytes ``head`` (:data:`HEAD_BYTES`, or all of a smaller capture:
    ``complete``): where its first whole frame starts and that frame's tag sequence, checked.

    The tags sit every 64 bytes; where the stream of half-lines is aligned is found as the byte phase (mod
    64) whose words are most often valid tags (line 1..500), so a capture cut at any byte is read. The first
    frame starts at the first half-line of that phase tagged line 500, channel 0; its 2000 tags must be every
    (line, channel) once, ending with line 500, channel 3. Anything else is refused in one line naming the
    first bad packet's byte offset."""
    data = np.frombuffer(head, np.uint8)
    if data.size < HALF_BYTES:
        raise InputError(f"capture is {data.size} bytes: not even one sps100 half-line ({HALF_BYTES} bytes)")
    words = _tag_words(np.lib.stride_tricks.sliding_window_view(data, 2))  # the word at every byte
    lines = words & 0x3FF
    valid = (lines >= 1) & (lines <= LINES)
    at = np.arange(TAG_AT, words.size)  # a word here ends a whole half-line (starting at >= 0)
    phase = int(np.argmax(np.bincount(at % HALF_BYTES, weights=valid[at], minlength=HALF_BYTES)))
    on_phase = at[at % HALF_BYTES == phase]
    if not valid[on_phase].any():
        raise InputError(f"no sps100 half-line tags in the first {data.size} bytes (no word 64 bytes apart reads "
                         f"a line 1..{LINES}): not an sps100 capture")
    starts = on_phase[words[on_phase] == START_TAG]
    if starts.size == 0:
        raise InputError(f"no sps100 frame start (a half-line tagged {describe_tag(START_TAG)}) in the first "
                         f"{data.size} bytes: not an sps100 capture")
    offset = int(starts[0]) - TAG_AT
    if offset + FRAME_BYTES > data.size:
        if complete:
            raise InputError(f"capture holds no whole sps100 frame ({FRAME_BYTES} bytes) after its first frame "
                             f"start at byte {offset}")
        raise InputError(f"no whole sps100 frame in the first {data.size} bytes (its first frame start is at byte "
                         f"{offset}): not an sps100 capture")
    tags = words[offset + TAG_AT + HALF_BYTES * np.arange(HALVES)]
    bad_k, why = _first_bad(tags)
    if bad_k is not None:
        where = _tag_packet(offset + bad_k * HALF_BYTES)
        raise CaptureDamaged(f"sps100 packets out of layout at byte {where}: half-line {bad_k} of the first frame "
                             f"(from byte {offset}) is tagged {describe_tag(int(tags[bad_k]))}: {why}")
    return Sps100Layout(offset, tags.astype("<u2").tobytes(), flip)


def _first_bad(tags: np.ndarray) -> tuple[int | None, str]:
    """The first of a frame's 2000 tags that breaks the layout, and why; (None, "") if none does."""
    found = []
    lines = tags & 0x3FF
    if (out := np.flatnonzero((lines < 1) | (lines > LINES))).size:
        found.append((int(out[0]), f"lines are 1..{LINES}"))
    order = np.argsort(tags, kind="stable")
    repeats = order[1:][tags[order[1:]] == tags[order[:-1]]]
    if repeats.size:
        k = int(repeats.min())
        first = int(np.flatnonzero(tags == tags[k])[0])
        found.append((k, f"half-line {first} has the same tag (each line and channel is once in a frame)"))
    ends = np.flatnonzero(tags[:-1] == END_TAG)
    if ends.size:
        found.append((int(ends[0]), f"a frame ends there, after {int(ends[0]) + 1} of its {HALVES} half-lines"))
    if tags[-1] != END_TAG:
        found.append((HALVES - 1, f"a frame's last half-line is tagged {describe_tag(END_TAG)}"))
    return min(found) if found else (None, "")
