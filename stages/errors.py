"""The one exception type that means "the input is wrong", and how any error is shown in one line."""


class InputError(ValueError):
    """Bad input: the message names the problem in one line and says what was expected."""


class InputTypeError(InputError, TypeError):
    """Bad input of the wrong type (``every="5"``, ``flip="no"``, ``out=None``), as only the Python API can
    pass it: a ``TypeError`` to Python callers, and an :class:`InputError` (one line) to the commands."""


def describe(error: BaseException) -> str:
    """An exception as one line of text (its message with whitespace folded, else its type's name)."""
    return " ".join(str(error).split()) or type(error).__name__


def not_ours_error(output, what: str, found: str) -> InputError:
    """The refusal of an output that exists and is not one that cscsr wrote, ``--overwrite`` or not: ``what``
    the command would replace (``a weights file``), ``found`` what is there (``a folder holding thesis.tex``)."""
    return InputError(f"output {output} already exists and is not {what} ({found}): cscsr replaces only its own "
                      f"outputs, even with --overwrite; choose another output, or move it away yourself")


def exists_error(output, flag: str = "--overwrite") -> InputError:
    """The refusal of an existing output of ours that the user did not ask to replace."""
    return InputError(f"output {output} already exists (pass {flag} to replace it)")


def unfinished_error(output, what: str, flag: str = "--overwrite") -> InputError:
    """The refusal of an existing output of ours that an interrupted run left unfinished (its ``state`` still
    "writing"), which the user did not ask to replace: ``what`` it is and who left it (``an incomplete spike store
    (state 'writing'), the leftover of an interrupted simulate``); ``flag`` what the command offers."""
    advice = ("pass --resume to finish it, or --overwrite to replace it" if "--resume" in flag
              else f"pass {flag} to replace it")
    return InputError(f"output {output} already exists: {what}; {advice}")
