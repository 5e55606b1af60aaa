"""Training across nodes: torchrun with two node launchers (c10d rendezvous on 127.0.0.1, one gloo worker each)
against one node of two processes, and a node's worker killed mid-epoch under ``--max-restarts 1``.

The two launchers are two separate ``torchrun --nnodes 2 --nproc-per-node 1`` processes, as on two machines; every
address (the rendezvous store, the workers' store, gloo's sockets) is on the loopback interface.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from datetime import timedelta
from pathlib import Path
from typing import NamedTuple

import pytest
import torch
import torch.distributed as dist

from test_train import scenes, shard_dataset  # noqa: F401 -- the fixtures: four tiny scenes as shards

REPO = Path(__file__).resolve().parents[2]
WORKER = Path(__file__).resolve().parent / "node_worker.py"
#: Seconds one torchrun launch may take (a tiny run takes a few; a hung rendezvous fails the test, not CI).
LAUNCH_TIMEOUT_S = 150
#: Bounds on the rendezvous: seconds to wait for the other node, and after the last one joined.
RDZV_CONF = "join_timeout=60,last_call_timeout=1,close_timeout=10"


class RendezvousStore(NamedTuple):
    """The launchers' rendezvous store, hosted by the test on 127.0.0.1 (both launchers join it as clients)."""

    store: dist.TCPStore
    port: int


@pytest.fixture
def rendezvous_store():
    """A TCPStore listening on 127.0.0.1 only (torch's own listens on every interface: a socket bound here is handed
    to it), for torchrun's c10d rendezvous (``is_host=false`` on every launcher)."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    store = dist.TCPStore("127.0.0.1", port, None, True, timedelta(seconds=60), wait_for_workers=False,
                          multi_tenant=True, master_listen_fd=listener.fileno())
    listener.detach()
    yield RendezvousStore(store, port)
    del store


def loopback_env() -> dict:
    """gloo and its TCP transport bind the loopback interface only; one thread per worker (2 shared cores). The
    workers' store is hosted by the rank-0 worker of each launch (TORCH_DISABLE_SHARE_RDZV_TCP_STORE=1), on
    MASTER_ADDR = --local-addr only (``ovgaussian.train.process_group.worker_store``), not shared with the launchers'
    rendezvous: the surviving node's launcher restarts its workers without counting a restart, so in a store shared
    over rounds its new worker would read the gloo address the killed worker left there."""
    return dict(os.environ, GLOO_SOCKET_IFNAME="lo", TP_SOCKET_IFNAME="lo", OMP_NUM_THREADS="1",
                TORCH_DISABLE_SHARE_RDZV_TCP_STORE="1",
                PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))


class Launches:
    """The torchrun launchers a test starts (each in its own process group); teardown ends those still running."""

    def __init__(self):
        self.procs: list[subprocess.Popen] = []

    def start(self, args: list[str], log: Path) -> subprocess.Popen:
        """Start ``torchrun ARGS``, its output to ``log``; its torchelastic_* log folder goes beside ``log`` (the
        launcher leaves it in the temporary directory)."""
        with open(log, "w") as out:
            proc = subprocess.Popen([sys.executable, "-m", "torch.distributed.run", *args], cwd=REPO,
                                    env=dict(loopback_env(), TMPDIR=str(log.parent)), stdout=out,
                                    stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append(proc)
        return proc

    def wait(self, procs: list[subprocess.Popen], logs: list[Path]) -> None:
        deadline = time.monotonic() + LAUNCH_TIMEOUT_S
        for proc, log in zip(procs, logs):
            try:
                code = proc.wait(timeout=max(1.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pytest.fail(f"torchrun still running after {LAUNCH_TIMEOUT_S} s:\n{log.read_text()[-3000:]}")
            assert code == 0, f"torchrun exited {code}:\n{log.read_text()[-3000:]}"

    def close(self) -> None:
        for proc in self.procs:  # the launcher's own process group: it and its workers, orphaned ones included
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:  # the group is gone: nothing left of that launch
                pass
            proc.wait(timeout=30)


@pytest.fixture
def launches():
    started = Launches()
    yield started
    started.close()


def run_nodes(launches: Launches, rendezvous: RendezvousStore, folder: Path, dataset: Path, nodes: int,
              kill: list[str] = ()) -> Path:
    """Train with ``nodes`` launchers of ``2 // nodes`` workers each (world size 2); returns the run folder."""
    out, steps = folder / "run", folder / "steps.jsonl"
    procs, logs = [], []
    for node in range(nodes):
        args = ["--nnodes", str(nodes), "--nproc-per-node", str(2 // nodes), "--rdzv-backend", "c10d",
                "--rdzv-endpoint", f"127.0.0.1:{rendezvous.port}", "--rdzv-id", folder.name,
                "--rdzv-conf", f"{RDZV_CONF},is_host=false", "--local-addr", "127.0.0.1", "--max-restarts", "1",
                "--monitor-interval", "0.5", str(WORKER), str(out), str(dataset), str(steps), *kill]
        logs.append(folder / f"node{node}.log")
        procs.append(launches.start(args, logs[-1]))
    launches.wait(procs, logs)
    return out


def final_weights(run: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    latest = json.loads((run / "checkpoints" / "latest.json").read_text())["path"]
    tensors = {}
    for name in ("model.safetensors", "optimizer.safetensors"):
        tensors.update({f"{name}:{k}": v for k, v in load_file(str(run / latest / name)).items()})
    return tensors


def step_log(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]


@pytest.mark.slow
def test_a_node_killed_mid_epoch_resumes_and_two_nodes_end_with_the_one_node_weights(shard_dataset, tmp_path,
                                                                                     launches, rendezvous_store):
    """Two nodes of one gloo worker each against one node of two: the same world size and rank slices, so the same
    samples on each rank, and gloo's all-reduce of two operands is one float addition, which commutes: the runs agree
    bit for bit, not only within a tolerance. The worker of rank 1 is killed in the second epoch; with
    ``--max-restarts 1`` both nodes' workers start again, resume from the epoch-1 checkpoint (``resume="auto"``) and,
    the trainer being deterministic, end with the uninterrupted one-node run's weights, momentum and metrics."""
    folders = {name: tmp_path / name for name in ("one_node", "two_nodes")}
    for folder in folders.values():
        folder.mkdir()
    one = run_nodes(launches, rendezvous_store, folders["one_node"], shard_dataset, 1)
    two = run_nodes(launches, rendezvous_store, folders["two_nodes"], shard_dataset, 2,
                    ["--kill-rank", "1", "--kill-at", "1", "1"])

    reference, weights = final_weights(one), final_weights(two)
    assert json.loads((two / "config.json").read_text())["world_size"] == 2
    assert sorted(weights) == sorted(reference)
    assert all(torch.equal(weights[k], reference[k]) for k in reference)
    assert (two / "metrics.jsonl").read_text() == (one / "metrics.jsonl").read_text()

    steps = step_log(folders["two_nodes"])
    killed_pid = int((folders["two_nodes"] / "steps.jsonl.killed").read_text())
    first = {s["pid"] for s in steps if s["epoch"] == 0}  # the first launch of each node's worker
    assert killed_pid in first and len(first) == 2
    # rank 1 reached the chosen step, and was killed there; afterwards both ranks ran in new processes that took only
    # the second epoch's steps: they resumed from the last checkpoint
    assert {"rank": 1, "pid": killed_pid, "epoch": 1, "step": 1} in steps
    again = sorted((s["rank"], s["epoch"], s["step"]) for s in steps if s["pid"] not in first)
    assert again == [(0, 1, 0), (0, 1, 1), (1, 1, 0), (1, 1, 1)]
    assert len({s["pid"] for s in steps} - first) == 2
