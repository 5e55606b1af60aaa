"""Procedural textures of the synthetic rooms: each a function of a surface point's metric surface coordinates
and world position to an RGB albedo in 0..1 (plain, stripes, checks, planks, wood grain, an abstract picture).

A texture draws its random parameters from the ``numpy.random.Generator`` passed in when it is made, never when
it is evaluated.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

Texture = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (st [n,2] metres, pos [n,3]) -> rgb [n,3] in 0..1


def _noise(rng: np.random.Generator, scale: float) -> Callable[[np.ndarray], np.ndarray]:
    """Smooth pseudo-noise in [-1, 1]: a sum of three random plane waves of wavelength ~``scale``."""
    freqs = rng.normal(size=(3, 3))
    freqs *= (2 * np.pi / scale) / np.linalg.norm(freqs, axis=1, keepdims=True)
    phases = rng.uniform(0, 2 * np.pi, size=3)

    def noise(pos: np.ndarray) -> np.ndarray:
        return np.sin(pos @ freqs.T + phases).mean(axis=1)

    return noise


def plain(color, rng, amount=0.05) -> Texture:
    base, noise = np.asarray(color, float), _noise(rng, 0.7)
    return lambda st, pos: base[None] * (1.0 + amount * noise(pos))[:, None]


def stripes(color_a, color_b, period, rng, axis=0) -> Texture:
    a, b, noise = np.asarray(color_a, float), np.asarray(color_b, float), _noise(rng, 0.5)

    def tex(st, pos):
        m = (np.floor(st[:, axis] / (period / 2)) % 2)[:, None]
        return (a * (1 - m) + b * m) * (1.0 + 0.04 * noise(pos))[:, None]

    return tex


def checker(color_a, color_b, period, rng) -> Texture:
    a, b, noise = np.asarray(color_a, float), np.asarray(color_b, float), _noise(rng, 0.6)

    def tex(st, pos):
        m = ((np.floor(st[:, 0] / period) + np.floor(st[:, 1] / period)) % 2)[:, None]
        return (a * (1 - m) + b * m) * (1.0 + 0.05 * noise(pos))[:, None]

    return tex


def planks(color, rng, width=0.18) -> Texture:
    base = np.asarray(color, float)
    shades = 1.0 + 0.12 * rng.uniform(-1, 1, size=64)
    phase = rng.uniform(0, 10, size=64)

    def tex(st, pos):
        row = np.floor(st[:, 1] / width).astype(np.int64) % 64
        grain = 1.0 + 0.06 * np.sin(st[:, 0] * 9.0 + phase[row] + 2.0 * np.sin(st[:, 1] * 20.0))
        seam = np.where((st[:, 1] % width) < 0.012, 0.75, 1.0)
        return base[None] * (shades[row] * grain * seam)[:, None]

    return tex


def wood(color, rng) -> Texture:
    base, phase = np.asarray(color, float), rng.uniform(0, 6)
    return lambda st, pos: base[None] * (1.0 + 0.08 * np.sin(st[:, 0] * 14.0 + phase + 3 * np.sin(st[:, 1] * 4.0)))[:, None]


def blobs(rng) -> Texture:
    """A colourful abstract picture."""
    colors = rng.uniform(0.1, 0.95, size=(3, 3))
    waves = rng.uniform(3, 12, size=(3, 2))
    phases = rng.uniform(0, 6, size=3)

    def tex(st, pos):
        w = np.stack([np.sin(st @ waves[k] + phases[k]) for k in range(3)], axis=1)
        w = np.exp(3 * w)
        w /= w.sum(axis=1, keepdims=True)
        return w @ colors

    return tex
