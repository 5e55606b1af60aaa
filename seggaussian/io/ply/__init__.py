"""3DGS PLY files: ``header`` (the PLY container: header, element extents), ``reader`` (vertex table, Gaussians),
``writer`` (Gaussians to a vertex table and a file) and ``reference`` (the plyfile-based reader the fast one is
tested against).
"""

__all__ = ["header", "reader", "reference", "writer"]
