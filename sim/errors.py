"""The one exception type for bad user input (files, arguments, actions)."""


class InputError(ValueError):
    """Bad user input. The message is one line naming the item (scenario id, case id, field)
    and the problem; the CLI prints it and exits with status 2 without writing any output."""
