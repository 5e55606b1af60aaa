"""Open-vocabulary queries of a scene: ``query`` labels every Gaussian against free-text class names, ``config``
its configuration, ``view_labels`` a view's label map from per-Gaussian vectors (shared with bench).
"""

__all__ = ["config", "query", "view_labels"]
