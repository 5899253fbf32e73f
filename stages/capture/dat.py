"""Raw ``.dat`` capture frames <-> packed store frames.

A ``.dat`` file has no header: frames back to back, each ``ceil(H*W_stored/8)`` bytes, pixel
``p = y*W_stored + x`` in bit ``p % 8`` (LSB first) of byte ``p // 8``. Some cameras store
``head_columns`` extra columns at the end of each row (the 400-pixel SPS10 rows are 416 wide;
SpikeCV's ``load_dat`` and Spike-Zoo's ``load_vidar_dat`` both drop the trailing 16), which
ingest drops and export writes back as zeros; ``head_at="start"`` reads stores written before
head columns were trailing. Real cameras store frames upside down (``flip``).

When ``W_stored`` and ``head_columns`` are multiples of 8 a .dat frame already *is* the
store layout (bytes are whole columns of 8 pixels), so conversion is slicing and row
reversal of bytes, never a bit decode. Other widths go through an unpack/repack.
"""

from dataclasses import dataclass

import numpy as np

from stages.capture.bits import pack_rows, packed_width, unpack_rows
from stages.errors import InputError

HEAD_SIDES = ("end", "start")  # where a row's header columns sit; "end" is the cameras' layout


def check_head_side(side: str) -> str:
    if side not in HEAD_SIDES:
        raise InputError(f"head columns at {side!r}: expected one of {', '.join(HEAD_SIDES)}")
    return side


@dataclass(frozen=True)
class DatLayout:
    """Geometry of one raw capture: the real image size plus how it sits in the file."""

    height: int
    width: int
    head_columns: int = 0
    flip: bool = False
    head_at: str = "end"
    offset = 0  # where frame 0 starts in the file (not a field: a .dat has no header)

    def __post_init__(self):
        for label, value in (("height", self.height), ("width", self.width)):
            if not isinstance(value, (int, np.integer)) or value <= 0:
                raise InputError(f"{label} must be a positive integer, got {value!r}")
        if self.head_columns < 0:
            raise InputError(f"head columns must be >= 0, got {self.head_columns}")
        check_head_side(self.head_at)

    @property
    def stored_width(self) -> int:
        return self.width + self.head_columns

    @property
    def first_column(self) -> int:
        """Where the image starts in a stored row."""
        return self.head_columns if self.head_at == "start" else 0

    @property
    def frame_bytes(self) -> int:
        """Bytes per frame in the .dat file."""
        return -(-self.height * self.stored_width // 8)

    @property
    def byte_aligned(self) -> bool:
        """True when conversion needs no bit decode (whole bytes map to whole bytes)."""
        return self.stored_width % 8 == 0 and self.head_columns % 8 == 0

    def frame_count(self, nbytes: int) -> int:
        """Frames in a file of ``nbytes``; an error naming the surplus if it does not divide."""
        frames, surplus = divmod(nbytes, self.frame_bytes)
        if surplus:
            raise InputError(
                f"capture size {nbytes} bytes is not a multiple of the frame size "
                f"{self.frame_bytes} bytes ({self.height}x{self.stored_width} pixels): "
                f"{surplus} bytes too many, or {self.frame_bytes - surplus} missing"
            )
        if frames == 0:
            raise InputError("capture is empty: no complete frame")
        return frames

    def to_packed(self, raw: np.ndarray, first_frame: int = 0) -> np.ndarray:
        """(n, frame_bytes) uint8 frames -> (n, H, ceil(W/8)) packed, upright (:func:`dat_to_packed`): what a
        layout of ``pipeline.stores.captures.RawCapture`` offers."""
        return dat_to_packed(raw, self)


def dat_to_packed(raw: np.ndarray, layout: DatLayout) -> np.ndarray:
    """(n, frame_bytes) uint8 .dat frames -> (n, H, ceil(W/8)) packed frames, upright."""
    n = raw.shape[0]
    if layout.byte_aligned:
        rows = raw.reshape(n, layout.height, layout.stored_width // 8)
        first = layout.first_column // 8
        packed = rows[:, :, first : first + layout.width // 8]
    else:
        bits = np.unpackbits(raw, axis=-1, count=layout.height * layout.stored_width, bitorder="little")
        first = layout.first_column
        bits = bits.reshape(n, layout.height, layout.stored_width)[:, :, first : first + layout.width]
        packed = pack_rows(bits)
    if layout.flip:
        packed = packed[:, ::-1]
    return np.ascontiguousarray(packed)


def packed_to_dat(packed: np.ndarray, layout: DatLayout) -> np.ndarray:
    """(n, H, ceil(W/8)) packed frames -> (n, frame_bytes) .dat frames (header columns zero)."""
    n = packed.shape[0]
    if layout.flip:
        packed = packed[:, ::-1]
    if layout.byte_aligned:
        rows = np.zeros((n, layout.height, layout.stored_width // 8), np.uint8)
        first = layout.first_column // 8
        rows[:, :, first : first + layout.width // 8] = packed
        return rows.reshape(n, layout.frame_bytes)
    bits = np.zeros((n, layout.height, layout.stored_width), np.uint8)
    bits[:, :, layout.first_column : layout.first_column + layout.width] = unpack_rows(packed, layout.width)
    return np.packbits(bits.reshape(n, -1), axis=-1, bitorder="little")


def check_packed_shape(packed: np.ndarray, height: int, width: int) -> None:
    """Reject packed frames whose shape does not match the declared image size."""
    expected = (height, packed_width(width))
    if packed.ndim != 3 or packed.shape[1:] != expected:
        raise InputError(f"packed frames have shape {packed.shape}, expected (T, {expected[0]}, {expected[1]})")
