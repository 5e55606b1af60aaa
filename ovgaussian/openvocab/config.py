"""Configuration of the open-vocabulary methods: one frozen dataclass, no code."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SynthesisConfig:
    """Generative zero-shot feature synthesis (ovgaussian.openvocab.feature_synthesis): generator and classifier training."""

    noise_width: int = 32
    """Width of the generator's Gaussian noise input (concatenated to the class's text embedding)."""
    hidden_width: int = 256
    """Width of the generator's hidden layer."""
    generator_steps: int = 1500
    """Adam steps of the generator (GMMN: multi-bandwidth Gaussian-kernel MMD per seen class)."""
    classes_per_step: int = 8
    """Seen classes whose MMD is summed per generator step."""
    samples_per_class: int = 128
    """Real and generated features per class in one MMD term."""
    kernel_bandwidths: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0, 4.0)
    """Bandwidths of the MMD's Gaussian kernels, in units of the standardized features."""
    learning_rate: float = 1e-3
    """Adam learning rate of the generator and of the classifier."""
    real_per_class: int = 2000
    """Real features per seen class kept (seeded subsample of the train split's Gaussians)."""
    synthetic_per_class: int = 2000
    """Generated features per unseen class for the classifier."""
    classifier_steps: int = 400
    """Full-batch Adam steps of the softmax classifier on real seen + synthetic unseen features."""
    seed: int = 0
    """Seed of the subsample, the noise and the initializations."""
