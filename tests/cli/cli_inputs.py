"""Small valid inputs for the CLI tests (errors, file modes): one builder shared by those test files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.writer import write_gaussians_ply


def make_cli_inputs(root: Path) -> dict:
    """A PLY, a raw synthetic ScanNet++ tree (one scene), a dataset, a run folder, a bench JSON, a file."""
    from test_bench import _write_tiny_dataset
    from test_predict import _tiny_run

    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    rng = np.random.default_rng(0)
    n = 50
    g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                  np.full((n, 3), -3, np.float32), rng.normal(size=n).astype(np.float32),
                  rng.normal(size=(n, 1, 3)).astype(np.float32))
    write_gaussians_ply(root / "scene.ply", g)
    (scene_id,) = synthesize(root / "raw" / "scannetpp", 1, 0, "scannetpp", SynthConfig(width=32, num_views=3))
    dataset = _write_tiny_dataset(root / "tiny")
    run = _tiny_run(root / "run")
    (root / "bench.json").write_text(json.dumps({"results": []}))
    (root / "a_file").write_text("not a folder\n")
    return {"ply": root / "scene.ply", "raw": root / "raw", "dataset": dataset, "run": run,
            "bench_json": root / "bench.json", "file": root / "a_file", "scene_id": scene_id}
