"""Colour filter array (CFA) patterns: names, validation, masks and orientation changes.

A pattern string names the colours of the top-left 2x2 cell row by row (``rggb``: R at
(0, 0), G at (0, 1) and (1, 0), B at (1, 1)). ``mono`` means no colour filter.
"""

import numpy as np

from stages.errors import InputError

BAYER_PATTERNS = ("rggb", "bggr", "grbg", "gbrg")
PATTERNS = BAYER_PATTERNS + ("mono",)

# OpenCV names a Bayer code by the second row's second and third pixels, so RGGB is "BG".
_OPENCV_BAYER = {"rggb": "BG", "bggr": "RG", "grbg": "GB", "gbrg": "GR"}


def check_cfa(cfa: str, height: int | None = None, width: int | None = None) -> str:
    """Return the normalised pattern name; reject unknown names and odd sizes for Bayer."""
    name = str(cfa).lower()
    if name not in PATTERNS:
        raise InputError(f"unknown CFA {cfa!r}: expected one of {', '.join(PATTERNS)}")
    if name != "mono":
        for label, size in (("height", height), ("width", width)):
            if size is not None and size % 2:
                raise InputError(f"{label} {size} is odd: a Bayer CFA ({name}) needs even height and width")
    return name


def flip_vertically(cfa: str, height: int) -> str:
    """The pattern as seen after flipping an image of ``height`` rows upside down."""
    if cfa == "mono" or height % 2:
        return cfa  # an odd number of rows keeps every row's parity
    return cfa[2:] + cfa[:2]


def flip_horizontally(cfa: str, width: int) -> str:
    """The pattern as seen after mirroring an image of ``width`` columns left to right."""
    if cfa == "mono" or width % 2:
        return cfa
    return cfa[1] + cfa[0] + cfa[3] + cfa[2]


def transpose(cfa: str) -> str:
    """The pattern as seen after swapping an image's rows and columns."""
    return cfa if cfa == "mono" else cfa[0] + cfa[2] + cfa[1] + cfa[3]


def colour_index(cfa: str, height: int, width: int) -> np.ndarray:
    """(H, W) int8 map of the colour each pixel sees: 0 R, 1 G, 2 B; -1 everywhere for mono."""
    if cfa == "mono":
        return np.full((height, width), -1, np.int8)
    cell = np.array([["rgb".index(c) for c in cfa[:2]], ["rgb".index(c) for c in cfa[2:]]], np.int8)
    return np.tile(cell, (height // 2, width // 2))


def opencv_bayer_code(cfa: str, suffix: str = "_VNG") -> int:
    """The OpenCV ``cvtColor`` code that demosaics this pattern to RGB (VNG by default)."""
    import cv2

    return getattr(cv2, f"COLOR_Bayer{_OPENCV_BAYER[cfa]}2RGB{suffix}")
