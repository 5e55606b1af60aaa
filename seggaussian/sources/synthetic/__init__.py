"""Procedural rooms written in the real ScanNet++ and Replica on-disk layouts: ``generate.synthesize`` is the entry
point; ``room`` assembles a furnished room from ``furniture`` pieces, ``mesh`` (its classes, mesh type and quad-grid
builder) and ``textures``; ``scannetpp`` and ``replica`` are the layout writers.
"""

__all__ = ["furniture", "generate", "mesh", "replica", "room", "scannetpp", "textures"]
