"""Bit packing of spike frames: 8 pixels per byte along x, least significant bit first.

This is the at-rest layout of the ``spikes`` array (contract: ``np.packbits(..., axis=-1,
bitorder="little")``). A row whose width is not a multiple of 8 ends in a partly used
byte whose spare bits are zero.
"""

import numpy as np


def packed_width(width: int) -> int:
    """Bytes per packed row of ``width`` pixels."""
    return -(-width // 8)


def pack_rows(bits: np.ndarray) -> np.ndarray:
    """(..., W) 0/1 values -> (..., ceil(W/8)) uint8, LSB first."""
    return np.packbits(np.asarray(bits, dtype=np.uint8), axis=-1, bitorder="little")


def unpack_rows(packed: np.ndarray, width: int) -> np.ndarray:
    """(..., ceil(W/8)) uint8 -> (..., W) uint8 of 0/1, the inverse of :func:`pack_rows`."""
    return np.unpackbits(packed, axis=-1, count=width, bitorder="little")


def unpacked_bits(packed: np.ndarray, width: int) -> np.ndarray:
    """(..., ceil(W/8)) packed -> (..., W) bool (True = fired)."""
    return unpack_rows(packed, width).view(bool)


def count_spikes(packed: np.ndarray) -> int:
    """Number of set bits (spikes) in a packed array (popcount on 64-bit words: ~20x faster)."""
    flat = np.ascontiguousarray(packed).reshape(-1)
    whole = flat.size - flat.size % 8
    return int(np.bitwise_count(flat[:whole].view(np.uint64)).sum(dtype=np.int64)
               + np.bitwise_count(flat[whole:]).sum(dtype=np.int64))
