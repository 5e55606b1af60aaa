"""The benchmark profile (``ovgaussian bench-suite``): ``profile`` runs the data, the trainings and every row of
Table 1 and the paper's Table 2; ``config`` holds the rows and the schedule.
"""

__all__ = ["config", "profile"]
