"""Command-line commands for reports, comparisons and exports (issue 6).

:func:`add_commands` is called by :mod:`fieldcal.cli` with its ``argparse`` sub-parsers;
each command registered here sets ``func`` (called with the parsed arguments, returns
the exit status).
"""

from __future__ import annotations


def add_commands(subparsers) -> None:
    """Register the report/compare/export/undistort commands (none yet)."""
    return None
