"""Measuring images: pixels in, image coordinates out.

- :mod:`.imageio`: reading and checking TIFF images, in one pass with their content hash.
- :mod:`.measurements`: the ``measurements`` table every detector returns, and the
  a-priori precision of a centre.
- :mod:`.discs`: sub-pixel centres of circular targets; its window stage in two engines,
  :mod:`.disc_windows` (the NumPy reference) and :mod:`.disc_kernel` (compiled with Numba).
- :mod:`.coded`: ArUco coded targets.
- :mod:`.targets`: the per-image composition (coded targets, then discs).
- :mod:`.spots`: the goniometer's collimated spot centroids.
- :mod:`.heap`: a worker process's freed frame memory kept for the next frame (glibc).
- :mod:`.warm`: the measuring path loaded and run once in a process before its first image.
"""
