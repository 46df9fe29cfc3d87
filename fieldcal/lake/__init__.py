"""The versioned data lake on Delta Lake tables (docs/lake.md).

``store`` (the :class:`~fieldcal.lake.store.Lake`: commits and readers), ``tables`` (the Delta
tables), ``observations`` (the measurement cache), ``parts`` (a version's parts checked in
memory), ``ids`` (names at the boundary), ``storage`` (files), ``history`` (read-only SQL,
time travel), ``check``, ``gc``, ``migrate`` (from the first layout), ``dictionary``
(``LAKE/README.md``).
"""
