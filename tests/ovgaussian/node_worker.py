"""The worker of the torchrun tests across nodes (tests/ovgaussian/test_train_nodes.py): a tiny training run.

    torchrun ... tests/ovgaussian/node_worker.py OUT DATASET LOG [--kill-rank R --kill-at EPOCH STEP]

Trains ``test_train.tiny_config(OUT, 2)`` (text stub, tiny network) on the shards of DATASET with ``resume="auto"``,
the setting a restarted torchrun worker needs. Each step this worker takes is appended to LOG as a JSON line (rank,
process id, epoch, step). With ``--kill-rank R --kill-at EPOCH STEP`` the worker of rank R sends itself SIGKILL when
it reaches that step, once (the file ``LOG.killed`` records the kill; a restarted worker finds it): a node's worker
killed mid-epoch at a chosen step. (torchrun's ``TORCHELASTIC_RESTART_COUNT`` cannot say which launch this is: the
launcher of the surviving node restarts its workers for the membership change without counting a restart.)
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
# As a script, Python puts this folder first on sys.path, where nothing shadows the packages; the repository root
# goes first anyway (a checkout that is not installed), then this folder for test_train's helpers.
sys.path[:0] = [str(TESTS.parent), str(TESTS / "ovgaussian")]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("out", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("log", type=Path)
    parser.add_argument("--kill-rank", type=int, default=None)
    parser.add_argument("--kill-at", type=int, nargs=2, default=None, metavar=("EPOCH", "STEP"))
    args = parser.parse_args()

    import torch

    from ovgaussian.run.config import DataConfig
    from ovgaussian.train import loop
    from test_train import text_stub, tiny_config, tiny_model_config

    torch.set_num_threads(1)
    rank = int(os.environ["RANK"])
    killed_marker = Path(f"{args.log}.killed")
    take_step = loop.train_step

    def logged_step(run, epoch, step, *rest, **kwargs):
        with open(args.log, "a") as f:
            f.write(json.dumps({"rank": rank, "pid": os.getpid(), "epoch": epoch, "step": step}) + "\n")
        if rank == args.kill_rank and [epoch, step] == args.kill_at and not killed_marker.exists():
            killed_marker.write_text(f"{os.getpid()}\n")
            os.kill(os.getpid(), signal.SIGKILL)
        return take_step(run, epoch, step, *rest, **kwargs)

    loop.train_step = logged_step
    config = tiny_config(args.out, 2, resume="auto",
                         data=DataConfig(dataset=args.dataset, blend_top_k=8, pixels_per_view=256))
    loop.train(config, model_config=tiny_model_config(12), text_embeddings=text_stub())


if __name__ == "__main__":
    main()
