"""How a spike camera's pixel resets after it fires: the one list of reset modes every recording records.

``subtract`` keeps the charge above the threshold (real cameras: a rate of ``α·I/θ``); ``zero`` drops it (the
paper's simulator: a rate of ``1/ceil(θ/(α·I))``). Kept apart from the sensor model (``stages.simulation.sensor``,
which compiles its kernels with numba on import) so that reading a recording's settings imports nothing heavy.
"""

from stages.errors import InputError

RESETS = ("subtract", "zero")


def check_reset(reset: str) -> str:
    """``reset`` if it is a reset mode, else one line naming the modes."""
    if reset not in RESETS:
        raise InputError(f"unknown reset mode {reset!r}: expected one of {', '.join(RESETS)}")
    return reset
