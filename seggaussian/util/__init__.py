"""Helpers that are not the domain: the allocator setting, atomic writes, JSON-ready values, per-scene seeds, config
field docs, the source closure of a module (build cache keys), numba's kernel cache folder and the thread caps of a
worker.
"""

__all__ = ["allocator", "atomic", "field_docs", "jsonsafe", "module_closure", "numba_cache", "seeds", "threads", "workers"]
