"""Fork server for the SIGKILL tests: imports the heavy modules once, then runs each job in a forked child.

Protocol (one JSON object per line): the test writes ``{"job": NAME, "args": {...}}`` on stdin; the driver
forks, prints ``{"pid": PID}``, waits for the child and prints ``{"status": STATUS}`` (the raw wait status:
``-9`` when the test killed the child with SIGKILL). The child runs the job and ``os._exit``s. Only the
child is ever killed; nothing heavy runs in the driver before a fork (no thread pools to inherit).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent
# Run as a script, Python puts tests/ first on sys.path, where tests/seggaussian and tests/ovgaussian (the tests,
# mirroring the packages) would shadow the packages: the repository root goes first, then test_train's folder
# (its scene and config helpers).
sys.path[:0] = [str(TESTS.parent), str(TESTS / "ovgaussian")]


def job_build(root: str, out: str) -> None:
    from seggaussian.pipeline.dataset import build_dataset
    from seggaussian.pipeline.config import BuildConfig
    from seggaussian.labels.config import OracleConfig

    build_dataset(BuildConfig(source="synthetic", root=Path(root), out=Path(out), gaussians="oracle",
                              progress=False, oracle=OracleConfig(num_gaussians=300)))


def job_train(out: str, epochs: int) -> None:
    import torch

    from ovgaussian.run.checkpoint import CONFIG_NAME
    from ovgaussian.data.scene_source import InMemorySource
    from ovgaussian.train.loop import train
    from test_train import make_scene, text_stub, tiny_config, tiny_model_config

    torch.set_num_threads(1)
    out_path = Path(out)
    scenes = [make_scene(s, per_box=20, views=2) for s in range(2)]
    resume = (out_path / CONFIG_NAME).is_file()
    train(tiny_config(out_path, epochs, resume=resume), source=InMemorySource(scenes),
          model_config=tiny_model_config(12), text_embeddings=text_stub())


JOBS = {"build": job_build, "train": job_train}


def main() -> None:
    import seggaussian.pipeline.dataset  # noqa: F401 -- imported once, before any fork
    import ovgaussian.train.loop  # noqa: F401
    import test_train  # noqa: F401

    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            code = 0
            try:
                JOBS[request["job"]](**request["args"])
            except BaseException as exc:  # noqa: BLE001 -- reported to the test as a non-zero exit
                print(f"job failed: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
                code = 1
            os._exit(code)
        print(json.dumps({"pid": pid}), flush=True)
        _, status = os.waitpid(pid, 0)
        code = -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)
        print(json.dumps({"status": code}), flush=True)


if __name__ == "__main__":
    main()
