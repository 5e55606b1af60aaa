"""The per-scene stages of ``seggaussian build``, one module per stage (mode), each computing and writing its outputs.

    gaussians  gaussians_oracle | gaussians_scan | gaussians_fit | gaussians_import  -> gaussians_stage.parquet (+ oracle truth)
    transfer   transfer                                                              -> gaussians.parquet
    views      views                                                                 -> views.parquet

A stage module is the entry point of its stage's code: the build cache key of a stage hashes the source of
every seggaussian module that its module imports, transitively (``seggaussian.pipeline.cache``). So a stage
module imports what it runs, and nothing it does not run: the orchestration (mode choice, cache lookup,
executors) lives in ``seggaussian.pipeline.scene`` and ``seggaussian.pipeline.dataset``.
"""

__all__ = ["gaussians", "gaussians_fit", "gaussians_import", "gaussians_oracle", "gaussians_scan", "transfer", "views"]
