"""Progress bars (rich) on standard error, for anything longer than a few seconds; none at all once
:func:`set_quiet` (``cscsr --quiet``), and no other line that is neither a result nor a warning or error
(a job's dashboard link: :func:`is_quiet`)."""

import contextlib
import sys
from collections.abc import Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn, TransferSpeedColumn

_quiet = False


def set_quiet(quiet: bool) -> None:
    """Turn every progress bar of this process off (or back on)."""
    global _quiet
    _quiet = bool(quiet)


def is_quiet() -> bool:
    """Whether this process was asked for results, warnings and errors only (``cscsr --quiet``)."""
    return _quiet


@contextlib.contextmanager
def progress_bar(description: str, total: int, *, done: int = 0, unit: str = "frames",
                 enabled: bool = True) -> Iterator:
    """Yield ``advance(n)``; draws a bar with count, rate and time left while enabled. ``done``: of ``total`` done
    before (what a resume finds committed), shown from the start and not counted in the rate."""
    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn(unit)]
    columns += [TransferSpeedColumn()] if unit == "bytes" else []
    columns += [TimeRemainingColumn()]
    console = Console(stderr=True)
    # nothing at all where stderr is no terminal (rich would still end the bar with an empty line), unless forced
    # (FORCE_COLOR, rich's is_terminal)
    with Progress(*columns, console=console, disable=_quiet or not enabled or not console.is_terminal,
                  transient=not sys.stderr.isatty()) as bar:
        task = bar.add_task(description, total=total, completed=done)
        yield lambda n: bar.advance(task, n)
