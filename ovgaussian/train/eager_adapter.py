"""The per-Gaussian stage and a per-row loss on its output in one pass over row chunks, gradients taken in the forward.

At the paper's scale (3 x 1,000,000 Gaussians) the adapter runs in row chunks under activation checkpointing, so each
chunk's adapter forward ran twice (once for the values, again in backward to rebuild its graph), and the 3D text loss
on its output took another pass. :func:`semantic_with_row_loss` runs, per chunk of one scene's rows, the adapter and
the row loss with their graph, and takes that chunk's gradients with respect to its voxel features and the
parameters right away (as ``ovgaussian.train.eager_rows`` does for the loss alone). It returns the semantic vectors
(for rendering) and the per-scene loss sums. Their backward:

- the loss sums' part is the stored gradients times each scene's incoming scalar (exact: linear);
- the semantic vectors' part (the 2D losses, through ``M = W S``) reaches only the rows that contribute to a sampled
  pixel: the adapter is recomputed with its graph for those rows alone (a few percent of a scene's Gaussians);
- both land on the voxel features through the transpose of the Gaussians' gather (``PointGather.scatter``: an
  index-add per corner), and on the parameters.

Every adapter forward over all rows happens once, and its backward once; the recomputation covers the rendered
rows only. With ``rows`` (``step_losses.term_rows``: the labelled Gaussians and the rendered ones) the per-Gaussian
stage skips the Gaussians no loss reads. Peak memory is a chunk's graph plus one gradient the size of the
per-Gaussian voxel features.
The one-piece computation (``net(...)`` then the losses) is the reference; the tests compare values and every
parameter's gradient.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from ovgaussian.model import network as model
from ovgaussian.sparse.devoxelize import PointGather
from ovgaussian.train.eager_rows import accumulate, gradients


def semantic_with_row_loss(
    net,  # ovgaussian.model.network.OVGaussianNet with an adapter
    means: Tensor,  # [N, 3]
    attributes: Tensor,  # [N, 11]
    batch_index: Tensor,  # [N] non-decreasing scene index
    num_scenes: int,
    row_loss: Callable[..., Tensor],  # (semantic rows [n, S], *row tensor chunks, *loss params) -> scalar
    row_tensors: tuple[Tensor, ...],  # [N, ...] each, chunked with the rows (e.g. labels)
    loss_params: tuple[Tensor, ...],  # passed whole to every chunk (e.g. the decoder's Gram terms)
    chunk_rows: int | None = None,
    rows: Tensor | None = None,  # [R] increasing rows whose vectors and loss terms are wanted; None: all
) -> tuple[Tensor, Tensor]:  # semantic [N or R, S], loss sums [num_scenes]
    """``(net(means, attributes, batch_index, rows), sums)`` with ``sums[b]`` = the sum over scene ``b``'s row chunks
    of ``row_loss`` (module docstring). Chunks of ``chunk_rows`` (default ``model.CHECKPOINT_ROWS``) never cross a
    scene boundary. With ``rows`` the voxels still pool every Gaussian; the per-Gaussian stage and the row loss run
    on those rows only (``row_tensors`` are given for every Gaussian and taken at ``rows``)."""
    if not net.config.use_adapter:
        raise ValueError("semantic_with_row_loss: the network has no adapter")
    if attributes.requires_grad or means.requires_grad:
        raise ValueError("semantic_with_row_loss: gradients of the Gaussians' attributes are not supported")
    n = batch_index.shape[0]
    if any(t.shape[0] != n for t in row_tensors):
        raise ValueError("semantic_with_row_loss: row tensors must have one row per Gaussian")
    if n > 1 and bool((batch_index[1:] < batch_index[:-1]).any()):
        raise ValueError("semantic_with_row_loss: batch_index must be non-decreasing (scenes one after another)")
    chunk_rows = model.CHECKPOINT_ROWS if chunk_rows is None else int(chunk_rows)
    if chunk_rows < 1:
        raise ValueError(f"semantic_with_row_loss: chunk_rows must be >= 1, got {chunk_rows}")
    voxel_features, point_gather, attributes = net.voxel_stage(means, attributes, batch_index)
    if rows is not None:
        if rows.ndim != 1 or (rows.shape[0] > 1 and bool((rows[1:] <= rows[:-1]).any())):
            raise ValueError("semantic_with_row_loss: rows must be increasing row indices")
        point_gather, attributes, batch_index = point_gather.take(rows), attributes[rows], batch_index[rows]
        row_tensors = tuple(t[rows] for t in row_tensors)
    counts = torch.bincount(batch_index.cpu(), minlength=num_scenes).tolist()
    chunks, start = [], 0
    for scene, count in enumerate(counts):
        for s in range(start, start + count, chunk_rows):
            chunks.append((s, min(s + chunk_rows, start + count), scene))
        start += count
    adapter_params = tuple(net.adapter.parameters())
    meta = (net.adapter, row_loss, chunks, num_scenes, len(adapter_params), len(row_tensors), chunk_rows)
    return _AdapterRowLoss.apply(meta, voxel_features, *point_gather, attributes, *adapter_params, *row_tensors,
                                 *loss_params)


class _AdapterRowLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, meta, voxel_features, gather_rows, gather_weights, attributes, *inputs):  # noqa: D102
        adapter, row_loss, chunks, num_scenes, num_adapter, num_rows, _ = meta
        adapter_params = inputs[:num_adapter]
        row_tensors = inputs[num_adapter:num_adapter + num_rows]
        needs = ctx.needs_input_grad[5:]
        leaves = [p.detach().requires_grad_(need)
                  for p, need in zip(inputs[num_adapter + num_rows:], needs[num_adapter + num_rows:])]
        features = voxel_features.detach()
        point_gather = PointGather(gather_rows, gather_weights)
        n = gather_rows.shape[0]
        semantic = features.new_empty(n, adapter.mlp[-1].out_features)
        row_grads = features.new_zeros(n, features.shape[1]) if ctx.needs_input_grad[1] else None
        # per scene: gradients of its loss sum with respect to the adapter's parameters and the loss params
        param_grads: list[list[Tensor | None]] = [[None] * (num_adapter + len(leaves)) for _ in range(num_scenes)]
        sums = features.new_zeros(num_scenes)
        with torch.enable_grad():
            for start, end, scene in chunks:
                per_gaussian = point_gather.slice(start, end).gather(features).requires_grad_(row_grads is not None)
                rows_semantic = adapter(per_gaussian, attributes[start:end])
                semantic[start:end] = rows_semantic.detach()
                value = row_loss(rows_semantic, *(t[start:end] for t in row_tensors), *leaves)
                grads = gradients(value, (per_gaussian, *adapter_params, *leaves))
                if grads[0] is not None:
                    row_grads[start:end] = grads[0]
                for i, g in enumerate(grads[1:]):
                    param_grads[scene][i] = accumulate(param_grads[scene][i], g)
                sums[scene] += value.detach()
        ctx.save_for_backward(voxel_features, gather_rows, gather_weights, attributes)
        ctx.meta, ctx.row_grads, ctx.param_grads = meta, row_grads, param_grads
        return semantic, sums

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_semantic, grad_sums):  # noqa: D102
        voxel_features, gather_rows, gather_weights, attributes = ctx.saved_tensors
        point_gather = PointGather(gather_rows, gather_weights)
        adapter, _, chunks, num_scenes, num_adapter, num_rows, chunk_rows = ctx.meta
        row_grads, param_grads, ctx.row_grads, ctx.param_grads = ctx.row_grads, ctx.param_grads, None, None
        adapter_params = tuple(adapter.parameters())
        totals: list[Tensor | None] = [None] * len(param_grads[0])  # None: no gradient needed, or a zero one
        for scene in range(num_scenes):
            for i, g in enumerate(param_grads[scene]):
                totals[i] = accumulate(totals[i], g, grad_sums[scene])
        if row_grads is not None:
            for start, end, scene in chunks:
                row_grads[start:end] *= grad_sums[scene]
        recompute = row_grads is not None or any(p.requires_grad for p in adapter_params)
        if grad_semantic is not None and recompute:  # the rows that reach a loss through the semantic vectors
            rendered = torch.nonzero(grad_semantic.ne(0).any(1))[:, 0]
            for s in range(0, rendered.shape[0], chunk_rows):
                rows = rendered[s:s + chunk_rows]
                with torch.enable_grad():
                    per_gaussian = point_gather.take(rows).gather(voxel_features.detach()).requires_grad_(
                        row_grads is not None)
                    grads = gradients(adapter(per_gaussian, attributes[rows]), (per_gaussian, *adapter_params),
                                      grad_semantic[rows])
                if grads[0] is not None:
                    row_grads.index_add_(0, rows, grads[0])
                for i, g in enumerate(grads[1:]):
                    totals[i] = accumulate(totals[i], g)
        grad_features = None
        if row_grads is not None:
            grad_features = point_gather.scatter(row_grads, voxel_features.shape[0])
        return (None, grad_features, None, None, None, *totals[:num_adapter], *([None] * num_rows),
                *totals[num_adapter:])
