"""Keep the memory of one image for the next: glibc's allocator told not to hand it back.

A full-size frame is ~100 MB of file bytes and ~100 MB of pixels, allocated and freed once
per image. glibc serves blocks that large with ``mmap`` and returns them to the kernel when
they are freed (in a thread other than the main one always: its arenas grow by at most
64 MB), so every image is written into fresh pages from the kernel.
:func:`keep_freed_memory` sets, for the rest of the process, one malloc arena (threads
share the main heap), large blocks from the heap instead of ``mmap``, and no trimming of
freed memory at the heap's top: the process keeps the memory of its largest moment
instead of returning it, so its resident size stays at that peak (the peak itself does
not grow).

It takes effect only when called before the measuring threads first allocate, so it is
called where a process starts to measure: a Dask worker process's preload
(:mod:`flows.worker`), and ``fieldcal run`` / ``fieldcal fleet`` with the workers as threads
of their own process, first thing in the command (``flows.cli``). A standing 2-process
cluster measured the 72 bench frames in 19.5-19.8 s against 25.1-25.6 s without it
(images' work summed 22.5-22.9 s against 34.2-35.0 s; ``bench/README_flow.md``, fourth
stop); the default in-process run in 0.81-0.96x the time (fifth stop, three alternated
pairs). Called in a process whose threads have allocated already, the threads keep their
arenas and it changes nothing measurable. On a C library without ``mallopt`` (not glibc) it
does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["keep_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
MMAP_THRESHOLD_BYTES = 1 << 30
"""Blocks at least this large still come from ``mmap`` (1 GiB: beyond any frame)."""
TRIM_THRESHOLD_BYTES = 2**31 - 1
"""Free memory at the heap's top kept up to this size (the largest ``int``: all of it)."""

_DONE: dict = {}


def keep_freed_memory() -> bool:
    """Tell glibc's malloc to keep freed memory for reuse (module docstring); once per process.

    Returns
    -------
    bool
        Whether the settings took effect (False off Linux / glibc).
    """
    if "ok" in _DONE:
        return _DONE["ok"]
    ok = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
            mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
            ok = all(mallopt(param, value) == 1 for param, value in (
                (_M_ARENA_MAX, 1), (_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
                (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)))
        except (OSError, AttributeError):       # not glibc (musl has no mallopt)
            ok = False
    _DONE["ok"] = ok
    return ok
