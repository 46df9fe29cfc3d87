"""Exception classes of fieldcal.

Every error a user can cause says *what* is wrong and *where* (file, row, field,
image) in one line, so the CLI can print ``str(err)`` and exit non-zero.
"""

from __future__ import annotations

import re


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


_ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]")
_ARROW = re.compile(r"\s*↳\s*")
_BACKTRACE = re.compile(r"\s*(Stack backtrace:\s*)?\b0: (<unknown>|\S+( at \S+)?)\s+1: .*$", re.S)


def one_line(error) -> str:
    """One line describing an exception (its text, else its class name) or a text.

    White space, newlines included, is folded to single spaces. Terminal colour codes and a
    Rust backtrace (delta-rs appends ``0: <unknown> 1: ...`` frames to some errors) are
    dropped, and delta-rs's ``↳`` between causes becomes ``:`` (issue 24, goal 3).
    """
    if isinstance(error, BaseException):
        text = str(error) or type(error).__name__
    else:
        text = str(error)
    text = _ARROW.sub(": ", _BACKTRACE.sub("", _ANSI.sub("", text)))
    return " ".join(text.split())
