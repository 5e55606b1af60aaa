"""Open-vocabulary methods without image weights, used by bench and predict: ``calibration`` (calibrated stacking),
``class_offsets`` (per-class score offsets fitted on the train split), ``feature_synthesis`` (generative
zero-shot features), ``config`` (the synthesis configuration).
"""

__all__ = ["calibration", "class_offsets", "config", "feature_synthesis"]
