"""The benchmark profile (``ovgaussian bench-suite``): ``profile`` runs the data, the trainings and every row of
Table 1 and the paper's Table 2; ``report`` writes their tables and checks; ``zoo`` scores the splat zoo (renditions
of the same rooms); ``config`` holds the rows and the schedule.
"""

__all__ = ["config", "profile", "report", "zoo"]
