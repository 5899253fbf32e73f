"""The ``cscsr`` command line's frame (Typer): the app, one-line errors and usage, logging options, the version,
and ``main``. The commands live beside it (``recordings``, ``network``, ``service``).
"""

import contextlib
import functools
import logging
import logging.handlers
import os
import signal
import sys
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from pipeline.compute import stopping
from stages.reconstruction.cfa import PATTERNS
from stages.reconstruction.methods import METHODS
from stages.capture.sps100 import LAYOUTS

# Click's usage error (Typer >= 0.17 vendors Click; older Typers use Click itself): found the same way in both
USAGE_ERROR = next(kind for kind in typer.BadParameter.__mro__ if kind.__name__ == "UsageError")


def _flags_take_no_value(display_type_rich):
    """Typer's help shows a flag (``--flip``, ``--resume``) as ``--flip <bool>``, as if it took a value, which
    ``--flip true`` then refuses: a flag is shown with no type."""
    @functools.wraps(display_type_rich)
    def shown(self, ctx):
        return None if getattr(self, "is_flag", False) else display_type_rich(self, ctx)
    return shown


if hasattr(typer.core, "TyperOption") and hasattr(typer.core.TyperOption, "display_type_rich"):
    typer.core.TyperOption.display_type_rich = _flags_take_no_value(typer.core.TyperOption.display_type_rich)


@contextlib.contextmanager
def usage_in_one_line(group: typer.Context | None = None):
    """A usage error (an unknown option or command, a value of the wrong type, a missing or extra argument)
    answered as every other bad input: ``error: <one line>`` on standard error and exit status 1, rather than
    Click's usage block with status 2. ``cscsr`` alone prints the help, status 0: asked for, not a mistake."""
    try:
        yield
    except USAGE_ERROR as error:
        if type(error).__name__ == "NoArgsIsHelpError":
            raise typer.Exit(0) from None  # the help was printed as the error was made (Typer's rich help)
        err.print(f"error: {usage_message(error, group)}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(1) from None


def usage_message(error, group: typer.Context | None = None) -> str:
    """``cscsr reconstruct: invalid value for '--every': ..., got 'abc' (see cscsr reconstruct --help)``; the
    command is the error's own, else the one ``group`` was invoking (Click leaves some errors without one)."""
    from stages.errors import describe

    message = describe(error.format_message()).rstrip(".")
    with contextlib.suppress(Exception):  # Typer's conversion keeps the value in pydantic's error, its cause
        message += f", got {error.__cause__.errors()[0]['input']!r}"
    context = getattr(error, "ctx", None)
    if (context is None or context is group) and group is not None and group.invoked_subcommand:
        where = f"{group.command_path} {group.invoked_subcommand}"
    else:
        where = context.command_path if context is not None else "cscsr"
    return f"{where}: {message[:1].lower()}{message[1:]} (see {where} --help)"


class OneLineUsageErrors(typer.core.TyperGroup):
    """The ``cscsr`` group: usage errors in parsing its own options and every command's are one line
    (:func:`usage_in_one_line`)."""

    def make_context(self, *args, **kwargs):
        with usage_in_one_line():
            return super().make_context(*args, **kwargs)

    def invoke(self, ctx):
        with usage_in_one_line(ctx):  # resolving the command, and parsing its arguments and options
            return super().invoke(ctx)


app = typer.Typer(cls=OneLineUsageErrors, no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  help="Reconstruction pipeline for colour spike cameras: ingest, inspect, export, reconstruct.")
# soft_wrap: a printed line is never broken at the terminal's width (a path in a result stays one line that
# a script can read, whatever the width or the path's length); tables still fit the width
err = Console(stderr=True, soft_wrap=True)
stdout = Console(soft_wrap=True)


def choices(names) -> str:
    """How ``--help`` shows an option's choices; the command checks the value itself, so that a bad one
    is the usual one-line error rather than Click's usage block."""
    return "[" + "|".join(names) + "]"


METHOD_CHOICES, CFA_CHOICES = choices(METHODS), choices(PATTERNS)
LAYOUT_CHOICES = choices(LAYOUTS)


def show_version(value: bool) -> None:
    if value:
        from cscsr import __version__

        print(f"cscsr {__version__}")
        raise typer.Exit()


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_TIME = "%Y-%m-%dT%H:%M:%S%z"  # ISO 8601, local time with its offset
log_level = logging.INFO  # set by --quiet / --verbose for the command that runs


@app.callback()
def options(context: typer.Context,
            version: Annotated[bool, typer.Option("--version", callback=show_version, is_eager=True,
                                                  help="Print the version and exit.")] = False,
            quiet: Annotated[bool, typer.Option("-q", "--quiet", help="No progress bars or log lines below "
                                                "warnings: results and errors only.")] = False,
            verbose: Annotated[bool, typer.Option("-v", "--verbose", help="Debug log lines, and Dask's own "
                                                  "warnings.")] = False) -> None:
    """Reconstruction pipeline for colour spike cameras: ingest, inspect, export, reconstruct."""
    global log_level
    from pipeline.compute.progress import set_quiet

    if quiet and verbose:
        err.print("error: -q/--quiet and -v/--verbose exclude each other: give one", markup=False, highlight=False)
        raise typer.Exit(1)
    log_level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    set_quiet(quiet)
    context.call_on_close(lambda: set_quiet(False))  # in-process callers (tests, the Python API) get them back
    send_logs(context)


class OneLineFormatter(logging.Formatter):
    """Each record one line, whatever it names: a newline or other control character in it (a file so named in
    an inbox) is shown escaped as Python shows it in a string (``\\n``, ``\\x1b``), so no name splits a line or
    forges one; printable text, names in any script included, is left as it is."""

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        if line.isprintable():
            return line
        return "".join(char if char.isprintable() else char.encode("unicode_escape").decode("ascii") for char in line)


def send_logs(context: typer.Context, path: str | None = None) -> None:
    """Our log records, timestamped one line each, to standard error or to the file ``path`` (appended; reopened
    when log rotation moves it away, as logrotate does), at the level --quiet / --verbose chose, until the command
    ends. Only the command line configures logging."""
    handler = (logging.handlers.WatchedFileHandler(path, encoding="utf-8") if path
               else logging.StreamHandler(sys.stderr))
    handler.setFormatter(OneLineFormatter(LOG_FORMAT, LOG_TIME))
    handler.set_name("cscsr")
    logger = logging.getLogger("cscsr")
    for old in [h for h in logger.handlers if h.get_name() == "cscsr"]:  # --log-file replaces standard error
        logger.removeHandler(old)
        old.close()
    logger.addHandler(handler)
    logger.setLevel(log_level)

    def restore() -> None:
        logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
        handler.close()

    context.call_on_close(restore)


def command_line(context: typer.Context) -> str:
    """The running command as one would retype it: its name, arguments, and every option not at its default."""
    words = ["cscsr", context.info_name]
    for param in context.command.params:
        value = context.params.get(param.name)
        if param.param_type_name == "argument":
            words.append(str(value))
        elif value != param.default and value is not None and value not in ((), []):
            if param.is_flag:
                words.append(param.opts[0] if value else param.secondary_opts[0])
            elif isinstance(value, (list, tuple)):  # a repeated option, e.g. --pictures A --pictures B
                for item in value:
                    words += [param.opts[0], str(item)]
            else:
                words += [param.opts[0], str(value)]
    return " ".join(words)


def debugging() -> bool:
    """``CSCSR_DEBUG=1`` (or ``true``, ``yes``) shows the traceback of a failure; unset, empty, ``0``, ``false``,
    ``no`` and anything else do not."""
    return os.environ.get("CSCSR_DEBUG", "").strip().lower() in ("1", "true", "yes")


INTERRUPTED_STATUS, TERMINATED_STATUS = 128 + signal.SIGINT, 128 + signal.SIGTERM  # the shells' convention


def one_line_errors(command):
    """Turn any exception into ``error: <one line>`` and exit status 1; Ctrl-C and SIGTERM (``pipeline.compute.stopping``)
    into ``error: interrupted`` / ``error: terminated (SIGTERM)`` and 130 / 143, once the clean-up has run."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except KeyboardInterrupt as interrupt:
            stopping.quiet_finalizers()
            terminated = isinstance(interrupt, stopping.Terminated)
            err.print(f"error: {'terminated (SIGTERM)' if terminated else 'interrupted'}", markup=False)
            raise typer.Exit(TERMINATED_STATUS if terminated else INTERRUPTED_STATUS) from None
        except Exception as error:
            if debugging():
                raise
            from pipeline.stores.storage import unreachable
            from stages.errors import describe

            message = describe(error)
            if reach := unreachable(error, [*args, *kwargs.values()]):
                message = reach
            elif isinstance(error, FileNotFoundError):
                message = f"cannot read {error.filename or message}: no such file or object"
            elif not isinstance(error, ValueError):
                message = f"{type(error).__name__}: {message}"
            err.print(f"error: {message}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None

    return wrapper


def command(*args, **kwargs):
    return lambda fn: app.command(*args, **kwargs)(one_line_errors(fn))


def counted(number: int, noun: str) -> str:
    """``1 task``, ``0 tasks``, ``2 tasks``: a count with its noun, singular for one."""
    return f"{number} {noun}{'' if number == 1 else 's'}"


def show_table(title: str, rows: dict) -> None:
    table = Table(title=title, show_header=False)
    for key, value in rows.items():
        table.add_row(key, f"{value:.6g}" if isinstance(value, float) else str(value))
    stdout.print(table)


# options several commands take
Workers = Annotated[Optional[int], typer.Option(help="Local Dask worker processes (default: one per core; at most "
                                                     "4 per core and 256).")]
Scheduler = Annotated[Optional[str], typer.Option(help="Dask scheduler address (default: DASK_SCHEDULER_ADDRESS, else Dask's "
                                                          "scheduler-address setting).")]


def main() -> None:
    stopping.interrupt_on(signal.SIGTERM)  # this process only: the Python API leaves its caller's signals alone
    stopping.mark_command_line()
    app(prog_name="cscsr")

