"""3DGS PLY files: ``reader`` (header, vertex table, Gaussians), ``writer`` (Gaussians to a vertex table and a
file) and ``reference`` (the plyfile-based reader the fast one is tested against).
"""

__all__ = ["reader", "reference", "writer"]
