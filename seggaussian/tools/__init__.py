"""Tools that are not the pipeline: they measure and stress it, they never produce a dataset.

- ``sweep/``: the stage sweeps (CLI ``seggaussian bench --stage ...``; "stage sweep" in the code, so that "bench"
  keeps one meaning, the model evaluation ``ovgaussian bench``): ``sweep.run`` (entry point), ``sweep.config``
  (configuration), ``sweep.data`` (raw tree, scenes, oracle Gaussians), ``sweep.pareto`` (rows, result, Pareto
  front), one module per stage (``sweep.fit``, ``sweep.transfer``, ``sweep.render``, ``sweep.build``) and
  ``sweep.report`` (Markdown tables, verdicts, plot).
- ``ray_cluster``: a Ray cluster of several nodes on this machine, bound to 127.0.0.1 (tests and benchmarks of
  ``seggaussian build --executor ray``).
- ``stress``: the numerical-stability suite of the dataset package (CLI ``seggaussian stress``); the model
  package adds its loss cases (``ovgaussian.train.stress_losses``) through the CLI.
- ``fuzz/``: seeded file fuzzing of the readers (``fuzz.engine``: mutants classified as accepted, clean error,
  non-finite, crash or hang); ``fuzz.ply`` and ``fuzz.splat`` (the non-PLY splat formats) are the targets.

Nothing in the pipeline (``seggaussian.pipeline.dataset`` and the stages it runs) imports this package.
"""

__all__ = ["fuzz", "own_code", "ray_cluster", "stress", "sweep"]
