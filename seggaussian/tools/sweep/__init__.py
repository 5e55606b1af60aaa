"""Stage sweeps (``seggaussian bench --stage ...``): ``run`` is the entry point, ``config`` its configuration,
``data`` the raw tree and scenes, ``pareto`` rows and the Pareto front, one module per stage (``fit``, ``transfer``,
``render``, ``build``) and ``report`` (Markdown tables, verdicts, plot).
"""

__all__ = ["build", "config", "data", "fit", "pareto", "render", "report", "run", "transfer"]
