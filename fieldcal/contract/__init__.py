"""The contract every layer may name (the bottom of docs/architecture.md): nothing here
imports another fieldcal package.

- :mod:`.schemas`: the JSON and Arrow schemas of sessions, documents and tables.
- :mod:`.goniometer_schema`: the columns of a goniometer frame's measurement.
- :mod:`.names`: the ids and file names a session may use.
- :mod:`.fingerprint`: the fingerprint of a calibration's inputs.
- :mod:`.compiled`: the switch between the Numba kernels and their NumPy references.

:mod:`fieldcal.errors` (the exceptions) belongs to this layer too.
"""
