"""Open-vocabulary methods without image weights, used by bench and predict: ``calibration`` (calibrated stacking),
``feature_synthesis`` (generative zero-shot features), ``config`` (the synthesis configuration).
"""

__all__ = ["calibration", "config", "feature_synthesis"]
