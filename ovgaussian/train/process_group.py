"""The torchrun glue of OVGaussian training: joining the process group, synchronized batch norm, gradient
and metric all-reduces.

With several processes (torchrun; gloo on CPU, NCCL on CUDA) each rank back-propagates its share of the
global batch and the gradients are summed over ranks with one all-reduce (what DistributedDataParallel's
reducer does; done by hand so that ablations leaving a decoder unused need no ``find_unused_parameters``),
and batch-norm statistics are synchronized over ranks (differentiable all-reduce), so P processes compute
the same step as one process up to float rounding. Without torchrun this is rank 0 of 1 and nothing is
communicated.
"""

from __future__ import annotations

import datetime
import os
import socket
import types
from typing import NamedTuple, Sequence

import torch
import torch.distributed as dist
import torch.distributed.nn.functional as dist_fn

from ovgaussian.sparse import SparseBatchNorm
from ovgaussian.sparse.voxelize import SparseVoxels


#: How long a process waits for the others at the store (torch's default for a process group).
STORE_TIMEOUT = datetime.timedelta(minutes=30)


class ProcessGroup(NamedTuple):
    """This process's place among the torchrun processes (rank 0 of 1 without torchrun)."""

    rank: int
    world_size: int


def torchrun_world_size() -> int:
    """The number of torchrun processes (env ``WORLD_SIZE``; 1 without torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def init_process_group(device: str) -> ProcessGroup:
    """Join the torchrun processes (env ``WORLD_SIZE`` > 1): gloo on CPU, NCCL on CUDA, through the store of
    ``worker_store`` (or, where torchrun's launcher hosts it, torchrun's env:// rendezvous)."""
    world_size = torchrun_world_size()
    if world_size <= 1:
        return ProcessGroup(0, 1)
    if not dist.is_initialized():
        backend = "nccl" if device == "cuda" else "gloo"
        store = worker_store(int(os.environ["RANK"]), world_size)
        if store is None:
            dist.init_process_group(backend=backend)
        else:
            dist.init_process_group(backend=backend, store=store, rank=int(os.environ["RANK"]), world_size=world_size)
    return ProcessGroup(dist.get_rank(), dist.get_world_size())


def worker_store(rank: int, world_size: int) -> dist.TCPStore | None:
    """The store the processes meet in when rank 0 hosts it (torchrun with ``TORCH_DISABLE_SHARE_RDZV_TCP_STORE=1``:
    a new store per launch, at ``MASTER_ADDR:MASTER_PORT``): rank 0 listens on ``MASTER_ADDR`` only, where torch's
    own store would listen on every interface. None where torchrun's launcher hosts the store
    (``TORCHELASTIC_USE_AGENT_STORE``, torchrun's default) or outside torchrun: env:// then."""
    if os.environ.get("TORCHELASTIC_USE_AGENT_STORE", "True") == "True" or "MASTER_ADDR" not in os.environ:
        return None
    address, port = os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"])
    if rank != 0:
        return dist.TCPStore(address, port, world_size, is_master=False, timeout=STORE_TIMEOUT)
    listener = socket.create_server((address, port), family=_address_family(address), backlog=max(128, world_size))
    try:
        store = dist.TCPStore(address, port, world_size, is_master=True, timeout=STORE_TIMEOUT,
                              master_listen_fd=listener.fileno())
    except BaseException:
        listener.close()
        raise
    listener.detach()  # the store owns the listening socket now
    return store


def _address_family(address: str) -> socket.AddressFamily:
    """The family of ``address`` (a name resolves to its first address)."""
    return socket.getaddrinfo(address, None, type=socket.SOCK_STREAM)[0][0]


def _synchronized_batch_norm_forward(module, x):
    """SparseBatchNorm forward with statistics over the rows of every process (two-pass, differentiable)."""
    if not module.training:
        return module._local_forward(x)
    features = x.features
    channels = features.shape[1]
    head = torch.cat([features.sum(0), features.new_tensor([float(features.shape[0])])])
    head = dist_fn.all_reduce(head)
    count = head[channels]
    mean = head[:channels] / count
    centred = features - mean
    sum_sq = dist_fn.all_reduce(centred.square().sum(0))
    var = sum_sq / count
    out = centred * torch.rsqrt(var + module.eps) * module.weight + module.bias
    with torch.no_grad():
        module.running_mean.mul_(1 - module.momentum).add_(module.momentum * mean)
        if float(count) > 1:
            module.running_var.mul_(1 - module.momentum).add_(module.momentum * var * count / (count - 1))
    return SparseVoxels(out, x.sites)


def synchronize_batch_norms(net) -> int:
    """Make every ``SparseBatchNorm`` of ``net`` use statistics over all processes; returns how many."""
    count = 0
    for module in net.modules():
        if isinstance(module, SparseBatchNorm):
            module._local_forward = module.forward
            module.forward = types.MethodType(_synchronized_batch_norm_forward, module)
            count += 1
    return count


def sum_gradients(net) -> None:
    """All-reduce (sum) the gradients of every parameter over the processes, in one flat buffer."""
    params = [p for p in net.parameters() if p.requires_grad]
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
    flat = torch.cat([p.grad.reshape(-1) for p in params])
    dist.all_reduce(flat)
    offset = 0
    for p in params:
        n = p.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p))
        offset += n


def reduce_sums(values: Sequence[float], group: ProcessGroup, device="cpu") -> list[float]:
    """Element-wise sum of float64 values over the processes (on ``device``: NCCL needs CUDA tensors)."""
    if group.world_size == 1:
        return list(values)
    t = torch.tensor(list(values), dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return t.tolist()


def broadcast_module(net) -> None:
    """Give every process rank 0's parameters and buffers."""
    for tensor in list(net.parameters()) + list(net.buffers()):
        dist.broadcast(tensor.data, src=0)


def barrier(group: ProcessGroup) -> None:
    """Wait for every process (nothing to wait for with one)."""
    if group.world_size > 1:
        dist.barrier()
