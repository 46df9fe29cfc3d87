"""fieldcal: geometric calibration of mapping cameras, field and goniometer methods.

The library is plain functions and small dataclasses over numpy / pyarrow; it never
imports Prefect (the flows in ``flows/`` wrap it). Conventions: ``docs/conventions.md``.
"""

__version__ = "0.1.0"
