"""OVGaussian training: ``loop.train`` (the loop, checkpoints, torchrun), ``loader`` (each step's samples, drawn in
the training process or ahead in worker processes, and the step's phase timings), ``step_losses`` (one step's
losses: network inputs, M = W S, per-scene terms), ``losses`` (paper eq. 3-5), ``gram_logits`` (the 3D text logits in
Gram form with a hand-written backward; its row passes in numba: ``gram_rows``), ``eager_rows`` and ``eager_adapter``
(row-chunked sums whose gradients are taken in the forward, at the paper's scale), ``schedule``, ``process_group``
(torchrun glue) and ``stress_losses`` (the loss cases of ``seggaussian stress``).
"""

__all__ = ["eager_adapter", "eager_rows", "gram_logits", "gram_rows", "loader", "loop", "losses", "process_group",
           "schedule", "step_losses", "stress_losses"]
