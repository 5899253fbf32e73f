"""The one exception type that means "the input is wrong", and how any error is shown in one line."""


class InputError(ValueError):
    """Bad input: the message names the problem in one line and says what was expected."""


class InputTypeError(InputError, TypeError):
    """Bad input of the wrong type (``every="5"``, ``flip="no"``, ``out=None``), as only the Python API can
    pass it: a ``TypeError`` to Python callers, and an :class:`InputError` (one line) to the commands."""


def describe(error: BaseException) -> str:
    """An exception as one line of text (its message with whitespace folded, else its type's name)."""
    return " ".join(str(error).split()) or type(error).__name__
