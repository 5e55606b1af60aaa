"""A short fit and a short training, each printed as a hash, for tests/test_reproducibility.py (a fresh process
per call).

    python tests/repro_driver.py RAW SCENE OUT

Prints ``fit=<sha256 of the PLY bytes>`` and ``train=<sha256 of every checkpoint tensor and the metrics lines>``
(the fit of SCENE under RAW to OUT/fit.ply, a training of two in-memory scenes in OUT/run). The test runs it with an
empty ``NUMBA_CACHE_DIR`` (every numba kernel compiled in that process) and again with the filled one (every kernel
loaded from the cache).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent
# As a script, Python puts tests/ first on sys.path, where tests/ovgaussian would shadow the package: the
# repository root goes first, then the folder of test_train (as kill_driver.py does).
sys.path[:0] = [str(TESTS.parent), str(TESTS / "ovgaussian")]

#: Fit length: enough steps for the rasterizer's backward kernel and one densification to run.
FIT_ITERATIONS = 30
#: Epochs of the training (every epoch's checkpoint enters the digest).
TRAIN_EPOCHS = 2


def train_digest(out: Path) -> str:
    """sha256 over every tensor of every checkpoint (sorted) and the step and epoch metrics of a run folder."""
    from safetensors.torch import load_file

    from ovgaussian.run.folder import read_metrics

    h = hashlib.sha256()
    for path in sorted(out.glob("checkpoints/*/*.safetensors")):
        tensors = load_file(str(path))
        h.update(str(path.relative_to(out)).encode())
        for key in sorted(tensors):
            h.update(key.encode() + tensors[key].numpy().tobytes())
    for kind in ("step", "epoch"):
        h.update(json.dumps(read_metrics(out, kind), sort_keys=True).encode())
    return h.hexdigest()


def run_train(out: Path, epochs: int) -> str:
    from ovgaussian.data.scene_source import InMemorySource
    from ovgaussian.train.loop import train
    from test_train import make_scene, text_stub, tiny_config, tiny_model_config

    scenes = [make_scene(s, per_box=20, views=2) for s in range(2)]
    train(tiny_config(out, epochs), source=InMemorySource(scenes),
          model_config=tiny_model_config(12), text_embeddings=text_stub())
    return train_digest(out)


def run_fit(raw: Path, scene: str, out: Path) -> str:
    from seggaussian.fit.optimize import fit_to_ply
    from seggaussian.fit.config import FitConfig

    config = FitConfig().with_iterations(FIT_ITERATIONS)
    fit_to_ply("synthetic", raw, scene, out, config, seed=0, progress=False)
    return hashlib.sha256(out.read_bytes()).hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("raw", type=Path)
    parser.add_argument("scene")
    parser.add_argument("out", type=Path)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"fit={run_fit(args.raw, args.scene, args.out / 'fit.ply')}")
    print(f"train={run_train(args.out / 'run', TRAIN_EPOCHS)}")


if __name__ == "__main__":
    main()
