"""Per-scene seeds: one run seed mixed with a stable hash of each scene id (no global RNG state)."""

from __future__ import annotations

import hashlib


def scene_seed(seed: int, scene_id: str) -> int:
    """A per-scene seed: the run seed mixed with a stable hash of the scene id (64 bits)."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{scene_id}".encode()).digest()[:8], "little")
