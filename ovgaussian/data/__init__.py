"""Training data: ``scene_source`` (the split's shards, read and scanned), ``training_data`` (scenes prepared on
demand, one (scene, view) sample per step), ``augmentation`` and ``cache_budget`` (the run folder's cache size).
"""

__all__ = ["augmentation", "cache_budget", "scene_source", "training_data"]
