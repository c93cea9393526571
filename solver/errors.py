"""Errors the user can cause, each naming the field at fault."""


class YauyauError(Exception):
    """Base class of the errors that are the user's to fix (never a traceback)."""


class SpecError(YauyauError, ValueError):
    """A model specification (or an input derived from it) is invalid.

    ``field`` is a dotted path into the spec, e.g. ``drift[0]`` or ``discretization.dt``.
    """

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class TooLarge(SpecError):
    """A spec whose arrays would not fit in memory (the service answers 413): ``field`` names the size
    to lower, the message the memory it would need, the limit and the largest value that fits."""


class InputError(YauyauError, ValueError):
    """Bad online input (increments, points, ...); ``field`` names it."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message

    def shifted(self, offset: int) -> "InputError":
        """This error about row j of a part starting at row ``offset``: ``increments[j]`` (any name)
        becomes ``increments[offset + j]``; another field stays as it is."""
        head, bracket, rest = self.field.partition("[")
        index, close, tail = rest.partition("]")
        if bracket and close and index.isdigit():
            return InputError(f"{head}[{offset + int(index)}]{tail}", self.message)
        return InputError(self.field, self.message)
