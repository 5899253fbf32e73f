"""A hold point for fault tests: tasks stop at a chosen count until a file appears.

Tests that kill a job mid-run need the kill to land while work remains, on any machine and
under any load. Racing a running job cannot promise that; a job that pauses can. With

    CSCSR_HOLD_AFTER_TASKS=N   CSCSR_HOLD_UNTIL=/path/to/file

in a worker's environment, the task after the N-th one that this worker process started
waits (polling) until the file exists, then goes on. The test waits for N tasks committed,
does its fault (kills the job, starts a rival job, ...), then creates the file or never does.
Unset (every real run), ``hold_point`` is one dictionary lookup.
"""

import os
import threading
import time

AFTER, UNTIL = "CSCSR_HOLD_AFTER_TASKS", "CSCSR_HOLD_UNTIL"
_started = 0
_lock = threading.Lock()


def hold_point() -> None:
    """Call at the start of a task: holds it if the environment asks (see the module docstring)."""
    global _started
    if AFTER not in os.environ:
        return
    with _lock:
        _started += 1
        started = _started
    if started > int(os.environ[AFTER]):
        release = os.environ.get(UNTIL, "")
        while not (release and os.path.exists(release)):
            time.sleep(0.02)


def hold_environment(after_tasks: int, until: str | os.PathLike) -> dict[str, str]:
    """The environment variables that hold a job's tasks after ``after_tasks`` until ``until`` exists."""
    return {AFTER: str(after_tasks), UNTIL: str(until)}
