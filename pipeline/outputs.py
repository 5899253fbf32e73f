"""Outputs claimed before they are written: an existing output is refused unless the user asked to
replace it, never one that another live job is writing (``pipeline.lease``), and an output whose
writing fails is removed, so no half-written output stays to look complete."""

import contextlib
from collections.abc import Iterator

from pipeline.lease import check_free
from pipeline.storage import exists, remove
from stages.errors import InputError


def claim_output(url: str, *, overwrite: bool, flag: str = "--overwrite") -> None:
    """Refuse an existing output unless ``overwrite``; with it, clear the old output (never one that
    another live job is writing: see :mod:`pipeline.lease`)."""
    if exists(url):
        check_free(url)
        if not overwrite:
            raise InputError(f"output {url} already exists (pass {flag} to replace it)")
        remove(url)


@contextlib.contextmanager
def removed_on_failure(url: str) -> Iterator[None]:
    """Delete ``url`` if the block raises (or is interrupted): no half-written output stays."""
    try:
        yield
    except BaseException:
        with contextlib.suppress(Exception):
            remove(url)
        raise


@contextlib.contextmanager
def new_output(url: str, *, overwrite: bool, flag: str = "--overwrite") -> Iterator[None]:
    """Claim ``url`` for a new output (refusing an existing one first), removed if the block fails."""
    claim_output(url, overwrite=overwrite, flag=flag)
    with removed_on_failure(url):
        yield
