"""Compiled kernels (Numba) with a NumPy fallback: one switch and one status for the package.

fieldcal's hot loops (the bundle's residuals and Jacobian, the assembly of the normal
equations) have a NumPy implementation, the reference, and a Numba kernel that does the
same arithmetic in one pass. Numba is a pinned dependency; its kernels are compiled on
first use and cached on disk (``cache=True``: a new process, e.g. a Dask worker, loads the
machine code instead of compiling). :func:`kernel` returns the compiled function after a
smoke test, or ``None`` when Numba is missing, cannot compile on this platform, or the
environment sets ``FIELDCAL_NUMBA=0``; callers then run the reference. :func:`status`
says, in one line per kernel, which is in use and why.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable

__all__ = ["numba", "kernel", "status", "statuses", "enabled", "switched_off", "SWITCHED_OFF"]

_log = logging.getLogger(__name__)

try:  # optional at run time: without it the NumPy references run
    import numba
except ImportError as _err:  # pragma: no cover - numba is a pinned dependency
    numba, _IMPORT_ERROR = None, _err
else:
    _IMPORT_ERROR = None

_KERNELS: dict[str, tuple[Callable | None, str]] = {}


SWITCHED_OFF = "switched off by FIELDCAL_NUMBA=0"
"""The status of every kernel, the disc kernel's included, when the environment says so."""


def switched_off() -> bool:
    """Whether the environment switches the compiled kernels off (``FIELDCAL_NUMBA`` 0, false, no, off)."""
    return os.environ.get("FIELDCAL_NUMBA", "1").strip().lower() in ("0", "false", "no", "off")


def enabled() -> bool:
    """Whether compiled kernels may be used (Numba importable, ``FIELDCAL_NUMBA`` not 0)."""
    return numba is not None and not switched_off()


def kernel(name: str, compiled: Callable | None, smoke: Callable[[Callable], None]) -> Callable | None:
    """The compiled kernel ``name`` after ``smoke(kernel)`` passed once in this process, or None.

    ``compiled`` is the ``numba.njit`` dispatcher (None when Numba is missing); ``smoke``
    calls it on a tiny problem and raises if the answer is wrong. Any failure (import,
    compilation, smoke test) means the NumPy reference runs; the reason is kept for
    :func:`status` and logged once.
    """
    if name in _KERNELS:
        return _KERNELS[name][0]
    if switched_off():
        _KERNELS[name] = (None, SWITCHED_OFF)
        return None
    try:
        if numba is None or compiled is None:
            raise _IMPORT_ERROR or ImportError("numba is not installed")
        smoke(compiled)
        _KERNELS[name] = (compiled, "compiled (numba)")
    except Exception as err:  # noqa: BLE001 - any failure to import or compile means: use NumPy
        first = str(err).splitlines()[0][:200] if str(err) else ""
        why = f"numba kernel unavailable ({type(err).__name__}: {first}); using the NumPy implementation"
        _log.info("%s: %s", name, why)
        _KERNELS[name] = (None, why)
    return _KERNELS[name][0]


def status(name: str) -> str:
    """One line: whether kernel ``name`` is compiled, and why not (after its first use)."""
    return _KERNELS.get(name, (None, "not used yet"))[1]


def statuses() -> dict[str, str]:
    """:func:`status` of every kernel used so far in this process, by name."""
    return {name: why for name, (_, why) in _KERNELS.items()}
