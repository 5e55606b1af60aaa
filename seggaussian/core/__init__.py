"""The domain types every stage shares: ``Gaussians`` (one 3DGS scene in memory), pinhole ``Camera`` (OpenCV
convention), unit quaternions (w, x, y, z), the ``Scene`` a source reader returns, class lists and vocabularies,
the toolkit's constants, and the one nearest-neighbour search over 3D points. numpy only; imports nothing else of
the package.
"""

__all__ = ["cameras", "classes", "constants", "gaussians", "knn", "rotations", "scene"]
