"""The model package's stress cases: training losses with extreme logits, zero vectors and empty valid sets
must give finite values and gradients. A ``StressFamily`` of the dataset package's stress suite
(``seggaussian.tools.stress``), added to ``seggaussian stress`` by the CLI.
"""

from __future__ import annotations

import numpy as np
import torch

from ovgaussian.train.losses import compute_text_logits, masked_cosine_loss, masked_cross_entropy
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.tools.stress import StressContext, StressFamily, require_finite

LOSS_KINDS = ("extreme_logits", "tiny_logits", "zero_vectors", "all_ignored")
#: Logit / feature scale of each kind (1.0 for the others).
LOSS_SCALES = {"extreme_logits": 1e4, "tiny_logits": 1e-30, "zero_vectors": 0.0}
#: Width of the generated features and text embeddings.
LOSS_FEATURE_DIM = 16
#: Temperature of the text logits in the cases (the training default's order of magnitude).
LOSS_TEMPERATURE = 0.07


def run_loss_case(rng: np.random.Generator, kind: str, context: StressContext | None = None) -> None:
    """Training losses with extreme logits, zero vectors and empty valid sets: finite values and gradients."""
    p, c, d = int(rng.integers(0, 30)), int(rng.integers(1, 8)), LOSS_FEATURE_DIM
    scale = LOSS_SCALES.get(kind, 1.0)
    logits = torch.tensor(rng.normal(size=(p, c)) * scale, requires_grad=True)
    labels = torch.as_tensor(rng.integers(0, c, size=p))
    if kind == "all_ignored":
        labels[:] = IGNORE_LABEL
    ce, _ = masked_cross_entropy(logits, labels)
    features = torch.tensor(rng.normal(size=(p, d)) * scale, requires_grad=True)
    text = torch.tensor(rng.normal(size=(c, d)))
    text_logits = compute_text_logits(features, text, LOSS_TEMPERATURE)
    ce2, _ = masked_cross_entropy(text_logits, labels)
    cos, _ = masked_cosine_loss(features, torch.zeros(p, d) if kind == "zero_vectors" else text[:1].expand(p, d),
                                torch.ones(p, dtype=torch.bool))
    (ce + ce2 + cos).backward()
    require_finite(f"losses {kind}", ce, ce2, cos, logits.grad, features.grad)
    return None


#: The loss family, run after the dataset families by ``seggaussian stress``.
LOSS_FAMILY = StressFamily("loss", LOSS_KINDS, run_loss_case)
