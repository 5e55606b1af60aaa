"""Open-vocabulary queries of a scene: ``query`` labels every Gaussian against free-text class names, ``config``
its configuration, ``view_labels`` a view's label map from per-Gaussian vectors (shared with bench), ``ensemble``
several runs as one predictor, ``faint_blend`` faint Gaussians' vectors read partly from their opaque neighbours.
"""

__all__ = ["config", "ensemble", "faint_blend", "query", "view_labels"]
