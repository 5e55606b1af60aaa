"""Open-vocabulary queries of a scene: ``query`` labels every Gaussian against free-text class names, ``config``
its configuration, ``view_labels`` a view's label map from per-Gaussian vectors (shared with bench), ``ensemble``
several runs as one predictor.
"""

__all__ = ["config", "ensemble", "query", "view_labels"]
