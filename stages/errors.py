"""The one exception type that means "the input is wrong", and how any error is shown in one line."""


class InputError(ValueError):
    """Bad input: the message names the problem in one line and says what was expected."""


def describe(error: BaseException) -> str:
    """An exception as one line of text (its message with whitespace folded, else its type's name)."""
    return " ".join(str(error).split()) or type(error).__name__
