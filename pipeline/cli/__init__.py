"""The ``cscsr`` command line (Typer): thin wrappers that parse, call the pipeline, report. ``core`` holds the app
and its conventions; ``recordings``, ``network`` and ``service`` its commands, registered in that order
(``cscsr --help`` lists them so). Imports: every room of the pipeline (each command its job, when it runs).

Every failure is one line on standard error and a non-zero exit; set ``CSCSR_DEBUG=1`` for
the full traceback.
"""

from pipeline.compute import stopping  # noqa: F401, I001 - first of all: in a worker process of the command, Ctrl-C is ignored from here on
from pipeline.cli import recordings, network, service  # noqa: F401, I001 - their commands, registered in this order
from pipeline.cli.core import app, debugging, main  # noqa: F401

__all__ = ["app", "debugging", "main"]
