"""Seeded fuzzing of the readers: ``engine`` mutates files and classifies each mutant (accepted, clean error,
non-finite, crash, hang); ``ply`` and ``splat`` are the targets.
"""

__all__ = ["engine", "ply", "splat"]
