"""Exception classes of fieldcal.

Every error a user can cause says *what* is wrong and *where* (file, row, field,
image) in one line, so the CLI can print ``str(err)`` and exit non-zero.
"""

from __future__ import annotations


class FieldcalError(Exception):
    """Base class of every error fieldcal raises on purpose."""


class InputError(FieldcalError, ValueError):
    """Bad input: a file, a field or an argument that is not what the contract allows.

    Parameters
    ----------
    message : str
        What is wrong.
    where : str, optional
        The file (and row, field or JSON pointer) it was found in; prefixed to the message.
    """

    def __init__(self, message: str, where: str | None = None):
        self.where = where
        self.reason = message
        super().__init__(f"{where}: {message}" if where else message)


class GeometryError(FieldcalError):
    """The observations cannot determine what was asked (too few, coplanar, degenerate)."""


class ConvergenceError(FieldcalError):
    """An iterative solver did not converge."""


class ImageError(InputError):
    """An image that cannot be read or measured (corrupt, truncated, unsupported)."""


class LakeError(FieldcalError):
    """The lake cannot be read or written consistently."""


def one_line(error) -> str:
    """One line describing an exception (its text, else its class name) or a text.

    White space, newlines included, is folded to single spaces.
    """
    if isinstance(error, BaseException):
        text = str(error) or type(error).__name__
    else:
        text = str(error)
    return " ".join(text.split())
