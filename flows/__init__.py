"""The orchestration layer of fieldcal: Prefect flows, the command line, the local Prefect server.

- :mod:`flows.calibrate`: ``calibrate-session``, one session -> one committed version
  (validate, measure the images as Prefect tasks on Dask, solve, commit); what it decides
  is in :mod:`fieldcal.pipeline` and :mod:`fieldcal.batch`.
- :mod:`flows.fleet`: ``recalibrate-fleet``, every session of a root without a calibration,
  several at once on one Dask cluster; the scheduled deployment
  (:func:`flows.fleet.fleet_deployment`, ``deploy/prefect.yaml``). Scanning and selecting
  the sessions is :mod:`fieldcal.fleet`.
- :mod:`flows.cluster`: where the fan-out runs (a local Dask cluster or a scheduler address).
- :mod:`flows.hashcache`: image hashes remembered by file stamp (a rerun reads no image).
- :mod:`flows.server`: the Prefect API of a command (``PREFECT_API_URL``, else a local
  server kept in the background and shared by the commands).
- :mod:`flows.cli` (``fieldcal``), :mod:`flows.cli_products` (reports, exports),
  :mod:`flows.cli_common` (what the commands share), :mod:`flows.synth`, :mod:`flows.demo`.
- :mod:`flows.worker`: the Dask worker preload.

The library (``fieldcal``) never imports Prefect; these modules do.
"""
