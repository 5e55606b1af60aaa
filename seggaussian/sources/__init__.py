"""Scene sources (readers only; they never write into the raw tree) and the synthetic generator.

- ``scannetpp``: ScanNet++ DATA_ROOT reader (``list_scenes``, ``read_scene``).
- ``replica``: Replica rooms (habitat mesh + info, NICE-SLAM / Semantic-NeRF / self-rendered views).
- ``synthetic``: ``synthesize(out, num_scenes, seed, layout)`` writes procedural rooms in those layouts
  (the ``synthetic/`` package: ``room`` geometry, ``scannetpp`` / ``replica`` writers; views from ``camera_path``).
- ``raycast``: open3d mesh raycasting (RGB, labels, depth) with a slow reference.

Layouts, field by field: ``data_specs/SOURCES.md``.
"""

from seggaussian.sources._common import EmptySceneError, SourceError

__all__ = ["EmptySceneError", "SourceError"]
