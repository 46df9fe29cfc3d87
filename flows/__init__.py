"""Prefect flows of fieldcal: thin wrappers that fan the work of :mod:`fieldcal.pipeline` out on Dask.

- :mod:`flows.calibrate`: ``calibrate-session``, one session -> one committed version
  (validate, measure the images as Prefect tasks on Dask, solve, commit).
- :mod:`flows.fleet`: ``recalibrate-fleet``, every session of a root without a calibration;
  the scheduled deployment (:func:`flows.fleet.fleet_deployment`, ``deploy/prefect.yaml``).
- :mod:`flows.cluster`: where the fan-out runs (a local Dask cluster or a scheduler address).
- :mod:`flows.hashcache`: image hashes remembered by file stamp (a rerun reads no image).
- :mod:`flows.worker`: the Dask worker preload.
- :mod:`flows.demo`: ``fieldcal demo``.

The library (``fieldcal``) never imports Prefect; these modules do.
"""
