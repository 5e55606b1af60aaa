"""Splat files in and out: 3DGS PLY (``ply/``), PlayCanvas compressed PLY, antimatter15 ``.splat``, ``.ksplat``
and Niantic SPZ; ``formats`` detects and reads any of them, ``validate`` checks and repairs what was read,
``importing`` is ``seggaussian import`` (any format to a validated PLY in the scene's frame) and ``inspection`` is
``seggaussian inspect`` of a file.
"""

__all__ = ["compressed_ply", "formats", "importing", "inspection", "ksplat", "ply", "splat", "splat_common", "spz",
           "spz_kernels", "validate"]
