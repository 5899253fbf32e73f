"""Stopping when asked: SIGTERM (``docker stop``, systemd, Kubernetes, ``kill``) handled as Ctrl-C is.

Python turns SIGINT into ``KeyboardInterrupt`` in the main thread, and every clean-up of this project runs on it
(unfinished outputs removed or left for ``--resume``, claims released, encoders, segment processes and local
clusters stopped, temporary files removed). SIGTERM's default ends the process at once and runs none of it, so
the command line's process and each segment process raise :class:`Terminated`, a ``KeyboardInterrupt``, instead.
"""

import signal
import sys

_handled: set = set()  # the signals interrupt_on handles in this process


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C raises ``KeyboardInterrupt``."""


def interrupt_on(*signals: signal.Signals) -> None:
    """Make the first of ``signals`` to arrive raise in the main thread (:class:`Terminated` for SIGTERM,
    ``KeyboardInterrupt`` for SIGINT) and ignore the ones after it, so that the clean-up it starts finishes (SIGKILL
    still ends the process at once). Python's own handler, not ``SIG_IGN``: processes started after it (workers,
    encoders) begin with the signals' defaults. Call it from the main thread."""
    received = []

    def stop(signum, frame) -> None:
        if received:
            return
        received.append(signum)
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    for signum in signals:
        signal.signal(signum, stop)
        _handled.add(signum)


def quiet_finalizers() -> None:
    """After an interrupt, in a process that :func:`interrupt_on` set up (the command line's, a segment's: it is about
    to exit), drop the errors of finalizers: an object whose construction the interrupt cut short can fail in its
    ``__del__`` (imageio's ``PillowPlugin``: ``AttributeError``), which Python prints as "Exception ignored in ..."
    with a traceback after the command's one line. Elsewhere (the Python API, tests) nothing changes."""
    if _handled:
        sys.unraisablehook = lambda unraisable: None
