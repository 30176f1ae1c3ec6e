"""User-facing errors.

Every mistake a user can make (a bad file, a wrong argument) raises a subclass of
:class:`DynBTFError` whose message names the file, field or argument and what was
expected. The command line prints these messages without a traceback.
"""

from __future__ import annotations

__all__ = ["DynBTFError", "FormatError", "InputError"]


class DynBTFError(ValueError):
    """Base class of errors caused by user input (files, arguments)."""


class FormatError(DynBTFError):
    """A file is missing, truncated, corrupt or of an unsupported version.

    The message always starts with the file's path.
    """

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class InputError(DynBTFError):
    """An argument has the wrong shape, type or value; the message names it."""
