"""HTML to PDF by headless Chromium's print-to-PDF (the certificate's ``--pdf``).

Chromium lays the page out with the same engine a user's browser prints it with, and
implements the CSS of paged media the certificate uses: ``@page`` size and margins, the
margin boxes (``@top-right``, ``@bottom-right``: the certificate number and "page N of M"
on every page, Chromium 131 and later), header rows that repeat where a table continues, and
``break-inside: avoid``. It runs as a subprocess with a fresh profile in a temporary folder,
no network, no GPU, no sandbox (a container's root has none), and Chromium's own header and
footer (date, file path) switched off.

Installing it: Debian / Ubuntu ``apt-get install chromium`` (Debian 12: Chromium 150+;
``.ci/run`` installs it with ``poppler-utils``, whose ``pdftoppm`` and ``pdftotext`` the tests
use to look at the pages); elsewhere any Chromium or Google Chrome. :func:`chromium` finds it
on the ``PATH`` as ``chromium``, ``chromium-browser``, ``google-chrome`` or
``google-chrome-stable``, or takes ``FIELDCAL_CHROMIUM`` (a path).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from fieldcal.errors import FieldcalError

__all__ = ["CHROMIUM_ENV", "CANDIDATES", "TIMEOUT_S", "chromium", "html_to_pdf", "PdfError"]

CHROMIUM_ENV = "FIELDCAL_CHROMIUM"
CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
TIMEOUT_S = 120.0
"""Longest wait for one page set [s] (a certificate takes 1-3 s)."""
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-extensions",
         "--no-default-browser-check", "--no-pdf-header-footer", "--hide-scrollbars")


class PdfError(FieldcalError):
    """Chromium is missing, or did not print the page."""


def chromium() -> str:
    """The Chromium executable (module docstring); :class:`PdfError` naming how to install it."""
    given = os.environ.get(CHROMIUM_ENV)
    if given:
        if shutil.which(given):
            return shutil.which(given)
        raise PdfError(f"{CHROMIUM_ENV}={given}: no such executable")
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    raise PdfError("a PDF needs Chromium (headless print-to-PDF), not found on the PATH: "
                   f"apt-get install chromium, or set {CHROMIUM_ENV}")


def html_to_pdf(html_path, pdf_path, *, timeout_s: float = TIMEOUT_S) -> Path:
    """Print ``html_path`` (a self-contained page) to ``pdf_path``; returns ``pdf_path``.

    The PDF is written beside its final name and moved there when complete, so a failed print
    leaves nothing that looks like a certificate.
    """
    exe = chromium()
    html_path = Path(html_path).resolve()
    pdf_path = Path(pdf_path)
    part = pdf_path.with_name(f".{pdf_path.name}.{os.getpid()}.part")
    with tempfile.TemporaryDirectory(prefix="fieldcal-chromium-") as profile:
        argv = [exe, *FLAGS, f"--user-data-dir={profile}", f"--print-to-pdf={part.resolve()}",
                html_path.as_uri()]
        try:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s,
                                  env=dict(os.environ, HOME=profile), check=False)
        except subprocess.TimeoutExpired:
            part.unlink(missing_ok=True)
            raise PdfError(f"Chromium did not print {html_path.name} within {timeout_s:g} s") from None
    if done.returncode != 0 or not part.is_file() or part.stat().st_size == 0:
        part.unlink(missing_ok=True)
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise PdfError(f"Chromium could not print {html_path.name} (exit {done.returncode}): {last}")
    os.replace(part, pdf_path)
    return pdf_path
