"""OVGaussian training: ``loop.train`` (the loop, checkpoints, torchrun), ``step_losses`` (one step's losses:
network inputs, M = W S, per-scene terms), ``losses`` (paper eq. 3-5), ``schedule``, ``process_group`` (torchrun
glue) and ``stress_losses`` (the loss cases of ``seggaussian stress``).
"""

__all__ = ["loop", "losses", "process_group", "schedule", "step_losses", "stress_losses"]
