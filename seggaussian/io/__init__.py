"""Splat files in and out: 3DGS PLY (``ply/``), PlayCanvas compressed PLY, antimatter15 ``.splat``, ``.ksplat``,
Niantic SPZ and glTF (``KHR_gaussian_splatting``); ``formats`` detects and reads any of them, ``validate`` checks and
repairs what was read, ``importing`` is ``seggaussian import`` (any format to a validated PLY in the scene's frame),
``converting`` is ``seggaussian convert`` (any format to any) and ``inspection`` is ``seggaussian inspect`` of a file.
"""

__all__ = ["compressed_ply", "converting", "formats", "gltf", "gltf_container", "importing", "inspection", "ksplat",
           "ply", "splat", "splat_common", "spz", "spz_kernels", "validate"]
