"""The one check of a number from outside (a flag, a sidecar, a store attribute): a number, in
range, finite, an integer where it must be; refused by name and value otherwise.

JSON and Python both read ``1e400`` as infinity and ``NaN`` as a number, and ``inf > 0`` holds,
so a plain ``value > 0`` lets infinity through; every number that reaches an output goes
through :func:`check_number` first, before any output exists. :func:`check_flag` and :func:`check_text`
do the same for yes/no and text options, which only the Python API can pass with a wrong type.
"""

import math
import numbers

from stages.errors import InputError, InputTypeError

FLOAT32_MAX = 3.4028234663852886e38  # larger values are infinite in the float32 arithmetic of images


def as_float(value):
    """A real number (not a bool) as a Python float, anything else as it is, for the checks to name: so that
    ``fps=20000`` and ``--fps 20000`` record the same bytes."""
    return float(value) if isinstance(value, numbers.Real) and not isinstance(value, bool) else value


def check_number(name: str, value, *, above: float | None = None, at_least: float | None = None,
                 at_most: float | None = None, integer: bool = False, why: str = "") -> None:
    """Refuse ``value`` unless it is a finite number (an integer if ``integer``) within the bounds.

    The error is one line naming ``name``, the broken rule and the value: ``--gain must be a finite
    number, got inf``, ``--workers must be <= 8 (4 per core), got 9``. ``why`` explains the upper
    bound.
    """
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise InputTypeError(f"{name} must be {'an integer' if integer else 'a number'}, got {value!r}")
    shown = value.item() if hasattr(value, "item") else value  # numpy scalars as plain numbers
    if math.isinf(value):
        raise InputError(f"{name} must be a finite number, got {shown}")
    for sign, bound in ((">", above), (">=", at_least), ("<=", at_most)):
        if bound is None:
            continue
        inside = value > bound if sign == ">" else value >= bound if sign == ">=" else value <= bound
        if not inside:  # the first bound broken is named; NaN breaks every bound
            reason = f" ({why})" if why and sign == "<=" else ""
            raise InputError(f"{name} must be {sign} {bound:g}{reason}, got {shown}")
    if math.isnan(value):
        raise InputError(f"{name} must be a finite number, got {shown}")
    if integer and not isinstance(value, numbers.Integral):
        raise InputTypeError(f"{name} must be an integer, got {shown}")


def check_flag(name: str, value) -> None:
    """Refuse a yes/no option that is not ``True`` or ``False``: ``flip="no"`` is a true string, and taking
    it as true would replace or flip what the caller meant to keep."""
    if not isinstance(value, bool):
        raise InputTypeError(f"{name} must be True or False, got {value!r}")


def check_text(name: str, value, *, optional: bool = False) -> None:
    """Refuse a text option (a name, a path, a choice) that is not a string (or None, where ``optional``)."""
    if value is None and optional:
        return
    if not isinstance(value, str):
        raise InputTypeError(f"{name} must be a string{' or None' if optional else ''}, got {value!r}")
