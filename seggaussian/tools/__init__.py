"""Tools that are not the pipeline: they measure and stress it, they never produce a dataset.

- Stage sweeps (CLI ``seggaussian bench --stage ...``; "stage sweep" in the code, so that "bench" keeps one
  meaning, the model evaluation ``ovgaussian bench``): ``stage_sweep`` (entry point), ``sweep_config``
  (configuration), ``sweep_data`` (raw tree, scenes, oracle Gaussians), ``pareto`` (rows, result, Pareto
  front), one module per stage (``sweep_fit``, ``sweep_transfer``, ``sweep_render``, ``sweep_build``) and
  ``sweep_report`` (Markdown tables, verdicts, plot).
- ``stress``: the numerical-stability suite of the dataset package (CLI ``seggaussian stress``); the model
  package adds its loss cases (``ovgaussian.train.stress_losses``) through the CLI.
- ``fuzz``: seeded file fuzzing of the readers (mutants classified as accepted, clean error, non-finite, crash or
  hang); ``fuzz_splat`` adds the non-PLY splat formats as targets.

Nothing in the pipeline (``seggaussian.build.dataset`` and the stages it runs) imports this package.
"""
