"""The camera model ``fieldcal-brown/1`` and its frames.

- :mod:`.camera`: correct / distort / project / unproject, pixel <-> image-plane mm.
- :mod:`.rotations`: rotation matrices, rotation vectors, omega-phi-kappa.

Conventions: ``docs/conventions.md``.
"""
