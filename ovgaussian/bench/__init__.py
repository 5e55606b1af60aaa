"""The benchmark (paper Table 1): ``evaluate.run_bench`` scores a run or a baseline (CSA, OVA, NVA, CDA in 3D and
2D), ``config`` its configuration, ``baselines`` the non-learned predictors, ``bootstrap`` the 95 % intervals.
"""

__all__ = ["baselines", "bootstrap", "config", "evaluate"]
