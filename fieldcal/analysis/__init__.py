"""What a calibration means, computed below the methods, the lake and the products
(docs/architecture.md): numbers, never pages.

- :mod:`.uncertainty`: the calibration as a distribution; uncertainty maps of the correction.
- :mod:`.correction`: the correction field sampled on a pixel grid (what a version stores).
- :mod:`.change`: the per-quantity change tests and Holm's correction.
- :mod:`.compare`: two calibrations compared (differences, their sigmas, the change test).
"""
