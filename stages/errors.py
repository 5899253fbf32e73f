"""The one exception type that means "the input is wrong", shown to users as one line."""


class InputError(ValueError):
    """Bad input: the message names the problem in one line and says what was expected."""
