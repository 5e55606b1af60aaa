"""Procedural rooms written in the real ScanNet++ and Replica on-disk layouts: ``generate.synthesize`` is the entry
point; ``room`` the geometry, ``scannetpp`` and ``replica`` the layout writers.
"""

__all__ = ["generate", "replica", "room", "scannetpp"]
