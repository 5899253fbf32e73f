"""Parts of a recording: a time range (``--start``/``--stop``) and a region (``--region``), read from text and
checked against the recording, each refused in one line naming the problem.

Times are spike frames (``1200``) or seconds with a unit (``2.5s``, ``1500ms``), converted with the recording's
frame rate: spike frame ``i`` is taken at ``i / fps`` seconds, and a time in seconds means the first spike frame
at or after it (``ceil(seconds * fps)``, in exact decimal arithmetic: ``0.1s`` at 30000 fps is frame 3000). A
range ``[start, stop)`` holds the output frames whose centre lies in it (the centres of the whole recording).

A region ``Y0:Y1,X0:X1`` is in LR pixels, half-open like a Python slice, an end left out meaning the frame's
edge (``:,256:512``). For a Bayer CFA it starts on even rows and columns and has an even size, so that it sees the
frame's colour phase.
"""

import math
import re
from fractions import Fraction

from stages.errors import InputError, InputTypeError

UNITS = {"s": Fraction(1), "ms": Fraction(1, 1000)}
_TIME = re.compile(r"(?P<number>\d+(?:\.\d*)?|\.\d+)\s*(?P<unit>[a-zA-Zµ]*)")
_BOUND = re.compile(r"\d*")


def parse_time(name: str, value) -> int | Fraction | None:
    """``value`` (an int of spike frames, or text: ``1200``, ``2.5s``, ``1500ms``; None: not given) -> spike
    frames (int) or seconds (Fraction); refused in one line if malformed, negative or in another unit."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise InputTypeError(f"{name} must be spike frames (an integer) or seconds with a unit as text "
                             f"('2.5s'), got {value!r}")
    if isinstance(value, int):
        if value < 0:
            raise InputError(f"{name} must be >= 0 spike frames, got {value}")
        return value
    text = value.strip()
    if text.startswith("-"):
        raise InputError(f"{name} must be >= 0, got {value!r}")
    match = _TIME.fullmatch(text)
    if not match:
        raise InputError(f"{name} must be spike frames (1200) or seconds with a unit (2.5s, 1500ms), got {value!r}")
    number, unit = match["number"], match["unit"]
    if not unit:
        if "." in number:
            raise InputError(f"{name} {value!r}: spike frames are whole numbers; give seconds with a unit (2.5s)")
        return int(number)
    if unit not in UNITS:
        raise InputError(f"{name} {value!r}: unknown unit {unit!r}: give spike frames (1200) or seconds in s or ms "
                         f"(2.5s, 1500ms)")
    return Fraction(number) * UNITS[unit]


def spike_frame(time: int | Fraction, fps: float) -> int:
    """A parsed time (:func:`parse_time`) as a spike frame: frames as they are, seconds rounded up to a frame."""
    if isinstance(time, int):
        return time
    return math.ceil(time * Fraction(repr(float(fps))))  # the frame rate as written (20000.0, 29.97), exactly


def time_range(start, stop, n_frames: int, fps: float, centres: list[int], window: int,
               every: int) -> tuple[int, int]:
    """(start, stop) in spike frames of ``--start``/``--stop`` (parsed or not; None: the recording's ends), checked
    against a recording of ``n_frames`` whose output frames are centred on ``centres``: inside it, not empty or
    reversed, and holding at least one centre."""
    given = {"--start": parse_time("--start", start), "--stop": parse_time("--stop", stop)}
    first = 0 if given["--start"] is None else spike_frame(given["--start"], fps)
    last = n_frames if given["--stop"] is None else spike_frame(given["--stop"], fps)
    length = f"{n_frames} spike frames, 0..{n_frames - 1}, {n_frames / fps:g} s at {fps:g} fps"
    for name, frame, end in (("--start", first, n_frames - 1), ("--stop", last, n_frames)):
        if frame > end:  # --stop may be the recording's end (ranges are half-open)
            raise InputError(f"{name} {_shown(given[name], frame)} is outside the recording ({length})")
    shown = f"--start {_shown(given['--start'], first)} --stop {_shown(given['--stop'], last)}"
    if last < first:
        raise InputError(f"{shown} is reversed: --stop must come after --start")
    if last == first:
        raise InputError(f"{shown} is empty: --stop must come after --start")
    if first_at(centres, first, every) >= first_at(centres, last, every):  # no centre in [first, last)
        where = (f"{centres[0]}, {centres[1]}, ... {centres[-1]} (every {every})" if len(centres) > 2
                 else ", ".join(map(str, centres)) or "none")
        raise InputError(f"spike frames [{first}, {last}) hold no output frame: output frames are centred at spike "
                         f"frames {where}, where a window of {window} frames fits around the centre")
    return first, last


def first_at(centres: list[int], frame: int, every: int) -> int:
    """The index of the first of ``centres`` (arithmetic: W//2 + j*every, no scan of millions) at or after spike
    frame ``frame``; ``len(centres)`` if none is."""
    if not centres:
        return 0
    return min(len(centres), max(0, -(-(frame - centres[0]) // every)))


def _shown(given, frame: int) -> str:
    """How a bound is named in an error: as the user gave it, with its spike frame where it was a time."""
    if given is None or isinstance(given, int):
        return str(frame)
    return f"{float(given):g}s (spike frame {frame})"


def parse_region(value) -> tuple[int | None, int | None, int | None, int | None] | None:
    """``--region`` (text ``Y0:Y1,X0:X1``, an end left out for the frame's edge; or 4 integers y0, y1, x0, x1;
    None: the whole frame) -> (y0, y1, x0, x1), None for an edge; refused in one line if malformed."""
    if value is None:
        return None
    if isinstance(value, (tuple, list)):
        if len(value) != 4 or not all(isinstance(v, int) and not isinstance(v, bool) or v is None for v in value):
            raise InputTypeError(f"--region must be 'Y0:Y1,X0:X1' or 4 integers (y0, y1, x0, x1), got {value!r}")
        bounds = tuple(value)
    elif isinstance(value, str):
        parts = [part.split(":") for part in value.replace(" ", "").split(",")]
        if len(parts) != 2 or any(len(part) != 2 or not all(_BOUND.fullmatch(b) for b in part) for part in parts):
            raise InputError(f"--region must be Y0:Y1,X0:X1 in LR pixels (rows, then columns; e.g. 0:256,64:320), "
                             f"got {value!r}")
        bounds = tuple(int(b) if b else None for part in parts for b in part)
    else:
        raise InputTypeError(f"--region must be 'Y0:Y1,X0:X1' or 4 integers (y0, y1, x0, x1), got {value!r}")
    if any(b is not None and b < 0 for b in bounds):
        raise InputError(f"--region {_text(bounds)}: pixels are counted from 0, got a negative bound")
    return bounds


def region(value, height: int, width: int, cfa: str) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1) of ``--region`` (parsed or not; None: the whole frame), checked against a frame of
    ``height`` x ``width`` LR pixels under ``cfa``: inside it, not empty or reversed and, for a Bayer CFA, on even
    rows and columns with an even size (a tile reads its spikes from any column: ``reconstruct_tasks.tile_windows``
    shifts the packed bytes)."""
    bounds = parse_region(value)
    if bounds is None:
        return 0, height, 0, width
    y0, y1, x0, x1 = (d if b is None else b for b, d in zip(bounds, (0, height, 0, width)))
    shown = f"--region {_text((y0, y1, x0, x1))}"
    if y1 > height or x1 > width or y0 >= height or x0 >= width:
        raise InputError(f"{shown} is outside the recording ({height}x{width} LR pixels: rows 0:{height}, "
                         f"columns 0:{width})")
    for axis, a, b in (("rows", y0, y1), ("columns", x0, x1)):
        if b < a:
            raise InputError(f"{shown} is reversed: its {axis} end before they start")
        if b == a:
            raise InputError(f"{shown} is empty: it holds no {axis}")
    if cfa != "mono":
        for label, bound in (("Y0", y0), ("Y1", y1), ("X0", x0), ("X1", x1)):
            if bound % 2:
                raise InputError(f"{shown}: {label} {bound} is odd: the {cfa} CFA repeats every 2 pixels, so a "
                                 f"region starts on even rows and columns and has an even size")
    return y0, y1, x0, x1


def _text(bounds) -> str:
    y0, y1, x0, x1 = ("" if b is None else b for b in bounds)
    return f"{y0}:{y1},{x0}:{x1}"
