"""The slow, obviously-correct reference the fast PLY reader (``reader.read_vertex_table``) is tested and
benchmarked against: the ``vertex`` element read through ``plyfile``.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["read_vertex_table_plyfile"]


def read_vertex_table_plyfile(path: str | os.PathLike) -> np.ndarray:
    """Slow reference reader: the ``vertex`` element through ``plyfile``, native byte order."""
    from plyfile import PlyData

    data = PlyData.read(str(path))["vertex"].data
    return np.asarray(data).astype(data.dtype.newbyteorder("="))
