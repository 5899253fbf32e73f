"""The one check of a number from outside (a flag, a sidecar, a store attribute): a number, in
range, finite, an integer where it must be; refused by name and value otherwise.

JSON and Python both read ``1e400`` as infinity and ``NaN`` as a number, and ``inf > 0`` holds,
so a plain ``value > 0`` lets infinity through; every number that reaches an output goes
through :func:`check_number` first, before any output exists.
"""

import math
import numbers

from stages.errors import InputError

FLOAT32_MAX = 3.4028234663852886e38  # larger values are infinite in the float32 arithmetic of images


def check_number(name: str, value, *, above: float | None = None, at_least: float | None = None,
                 at_most: float | None = None, integer: bool = False, why: str = "") -> None:
    """Refuse ``value`` unless it is a finite number (an integer if ``integer``) within the bounds.

    The error is one line naming ``name``, the broken rule and the value: ``--gain must be a finite
    number, got inf``, ``--workers must be <= 8 (4 per core), got 9``. ``why`` explains the upper
    bound.
    """
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise InputError(f"{name} must be {'an integer' if integer else 'a number'}, got {value!r}")
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
        raise InputError(f"{name} must be an integer, got {shown}")
