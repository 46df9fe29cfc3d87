"""Progress of a calibration run, for people at a terminal (and nothing for pipes).

The flows (``flows/``) report what they do through :func:`emit`; by default nothing
listens. The command line installs a :class:`TerminalProgress` on standard error when
that is a terminal (:func:`listening`), so a person sees the extraction advance while a
script that pipes ``fieldcal run`` gets only the version on standard output.

Events (keyword fields):

- ``"stage"``: ``text`` (a step begins: validating, measuring, solving, committing);
- ``"images"``: ``done``, ``total``, ``cached``, ``bad`` (image extraction advanced;
  ``label``, default "measuring images", names other work counted in images, e.g.
  rendering);
- ``"note"``: ``text`` (a line worth showing: a bad image, the solver's progress).

Inside :func:`quiet` (a context variable, so it holds for the threads and tasks started
from there) events are dropped: the fleet runs several sessions at once and shows one line
per session instead of their interleaved image counts.

This module imports nothing beyond the standard library; it never imports Prefect.
"""

from __future__ import annotations

import contextlib
import contextvars
import sys
import threading
import time
from collections.abc import Callable

__all__ = ["emit", "listening", "quiet", "is_quiet", "TerminalProgress", "Sink"]

Sink = Callable[..., None]
_sinks: list[Sink] = []
_lock = threading.Lock()
_quiet = contextvars.ContextVar("fieldcal_progress_quiet", default=False)


def emit(event: str, **fields) -> None:
    """Send an event to every listening sink (none by default, none inside :func:`quiet`). Never raises."""
    if _quiet.get():
        return
    with _lock:
        sinks = list(_sinks)
    for sink in sinks:
        try:
            sink(event, **fields)
        except Exception:  # noqa: BLE001 - progress display must never break a calibration
            pass


@contextlib.contextmanager
def listening(sink: Sink | None):
    """Install ``sink(event, **fields)`` for the duration of the block (None: do nothing)."""
    if sink is None:
        yield None
        return
    with _lock:
        _sinks.append(sink)
    try:
        yield sink
    finally:
        with _lock:
            _sinks.remove(sink)
        close = getattr(sink, "close", None)
        if close is not None:
            close()


@contextlib.contextmanager
def quiet():
    """Drop the events emitted in this block (and in threads and tasks started from it)."""
    token = _quiet.set(True)
    try:
        yield
    finally:
        _quiet.reset(token)


def is_quiet() -> bool:
    """Whether events are dropped here (inside :func:`quiet`)."""
    return _quiet.get()


class TerminalProgress:
    """Renders events on a terminal stream: one self-updating line for the images.

    Parameters
    ----------
    stream : text stream
        Usually ``sys.stderr``.
    """

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self._line = ""
        self._t0 = None            # start of the current image count

    def _clear(self) -> None:
        if self._line:
            self.stream.write("\r" + " " * len(self._line) + "\r")
            self._line = ""

    def _print(self, text: str) -> None:
        self._clear()
        self.stream.write(text + "\n")
        self.stream.flush()

    def __call__(self, event: str, **f) -> None:
        if event == "images":
            done, total = int(f.get("done", 0)), int(f.get("total", 0))
            if self._t0 is None or done == 0:
                self._t0 = time.monotonic()
            width = 30
            filled = int(round(width * done / total)) if total else width
            extra = []
            if f.get("cached"):
                extra.append(f"{f['cached']} cached")
            if f.get("bad"):
                extra.append(f"{f['bad']} bad")
            label = str(f.get("label") or "measuring images")
            line = (f"{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}"
                    + (f" ({', '.join(extra)})" if extra else "")
                    + f"  {time.monotonic() - self._t0:5.1f} s")
            self._clear()
            self.stream.write(line)
            self.stream.flush()
            self._line = line
            if total and done >= total:
                self.stream.write("\n")
                self.stream.flush()
                self._line = ""
                self._t0 = None
        elif event in ("stage", "note"):
            text = str(f.get("text", ""))
            self._print(text if event == "note" else f"{text} ...")

    def close(self) -> None:
        if self._line:
            self.stream.write("\n")
            self.stream.flush()
            self._line = ""
