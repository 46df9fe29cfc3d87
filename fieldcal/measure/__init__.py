"""Measuring images: pixels in, image coordinates out.

- :mod:`.imageio`: reading and checking TIFF images.
- :mod:`.targets`: sub-pixel centroids of circular targets, the per-image measurement.
- :mod:`.coded`: ArUco coded targets.
- :mod:`.spots`: the goniometer's collimated spot centroids.
"""
