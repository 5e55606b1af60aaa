"""Fixtures shared by the build tests."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    """Three tiny synthetic rooms (two in the ScanNet++ layout, one in the Replica layout), 4 views of 48 pixels."""
    synthetic = pytest.importorskip("seggaussian.sources.synthetic.generate")
    root = tmp_path_factory.mktemp("raw")
    cfg = synthetic.SynthConfig(width=48, num_views=4)
    synthetic.synthesize(root / "scannetpp", 2, 0, "scannetpp", cfg)
    synthetic.synthesize(root / "replica", 1, 0, "replica", cfg)
    return root
