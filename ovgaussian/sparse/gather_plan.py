"""Plans of the implicit-GEMM sparse conv (``gather_gemm``): a kernel map's output rows grouped by neighbour pattern.

For a kernel map in which every output row has at most one input per kernel offset (submanifold,
stride-2 down and transposed up convs), the ``[num_out, K]`` neighbour table ``nbr`` (input row per
offset, absent = ``num_in``) turns the convolution into ``out = im2col @ weight.reshape(K * C_in, C_out)``
with ``im2col[i] = concat_k x[nbr[i, k]]`` (zeros where absent).

Most of the ``K`` columns are empty on surface-like data (a voxel of a wall sees the 9 offsets of its
plane, not 27). Rows are therefore grouped by their *pattern* (the set of offsets with an input):
each group gathers and multiplies only its pattern's offsets. Patterns shared by at least
:data:`MIN_GROUP_ROWS` rows are the candidate groups (at most :data:`MAX_GROUPS`); every row joins
the candidate of least cost, counting each gathered slot 1 (its extra columns are zeros) and each
of its pairs outside the candidate's pattern :data:`RESIDUAL_COST_RATIO`, or no group when that
ratio times its pair count is cheaper. The pairs outside groups form a per-offset *residual* map
applied by gather, matmul and serial scatter-add. The identity offset (the centre of a submanifold
kernel) is one dense ``features @ weight[centre]`` and left out of the patterns.
On a scan-like surface this multiplies about 10 offsets per voxel for 9.6 real neighbours, in GEMMs
of inner dimension ``P * C_in`` (e.g. 256) instead of ``C_in``.

A submanifold map is symmetric (``nbr[i, k] = j`` iff ``nbr[j, K - 1 - k] = i``), so the plan of its
transposed map (the input gradient's) is its own plan with the offsets reversed (:func:`flip_plan`).
Maps with under :data:`MIN_PAIRS_PER_ROW_FOR_GROUPS` pairs per row get the residual-only plan; both kinds
are cached on the kernel map (:func:`gather_plans`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from torch import Tensor

import ovgaussian.sparse._numba_kernels as nk

if TYPE_CHECKING:
    from ovgaussian.sparse.kernel_map import KernelMap

#: A neighbour pattern shared by at least this many output rows gets its own GEMM group. Smaller:
#: fewer zero columns multiplied, but more (smaller) GEMMs and more Python overhead per call.
MIN_GROUP_ROWS = 64
#: At most this many pattern groups per map (the most frequent patterns are kept).
MAX_GROUPS = 96
#: Cost of a pair in the per-offset residual (gather, matmul, scatter-add) relative to one gathered
#: im2col slot of a group, used to assign rows to groups (module docstring). Measured on the
#: test VMs, a residual pair costs about twice a gathered im2col slot (surface benchmark: 9.6 pairs
#: per row by scatter took ~2x the time of 9.9 slots per row by GEMM), so 1.5 leans towards the GEMM.
RESIDUAL_COST_RATIO = 1.5
#: Maps with fewer (non-identity) pairs than this per output row get no groups, only the residual
#: (no neighbour table is built): with about one neighbour per row, as in uniformly random voxels,
#: grouping saves little GEMM time and its build costs more than it saves.
MIN_PAIRS_PER_ROW_FOR_GROUPS = 1.0
#: Bits used per int64 word of a pattern bit mask (below 63: no sign bit involved).
MASK_WORD_BITS = 60


class GatherGroup(NamedTuple):
    """Output rows that share one set of kernel offsets.

    Attributes:
        rows: ``[n]`` int64 output rows, increasing.
        offsets: ``[P]`` int64 kernel offsets gathered for these rows (the pattern).
        neighbours: ``[n, P]`` int64 input row per (row, offset); ``num_in`` where there is none.
    """

    rows: Tensor
    offsets: Tensor
    neighbours: Tensor


class GatherPlan(NamedTuple):
    """A kernel map as pattern groups of a neighbour table (see the module docstring).

    Attributes:
        groups: the groups; every output row is in at most one group (rows whose only input is the
            identity offset, and rows with a rare pattern, belong to none).
        residual_in: per offset ``k``, ``[R_k]`` input rows of the pairs not covered by a group
            (applied per offset by gather, matmul, serial scatter-add).
        residual_out: per offset ``k``, ``[R_k]`` their output rows (increasing).
        num_in: number of input rows (also the "absent" marker in ``neighbours``).
        num_out: number of output rows.
        kernel_volume: number of kernel offsets ``K`` of the weight.
        identity_offset: the offset whose pairs are ``(i, i)`` for every row (the centre of a
            submanifold kernel), applied as one dense ``features @ weight[k]`` and left out of the
            groups; -1 if none.
    """

    groups: tuple[GatherGroup, ...]
    residual_in: tuple[Tensor, ...]
    residual_out: tuple[Tensor, ...]
    num_in: int
    num_out: int
    kernel_volume: int
    identity_offset: int = -1


def _table_and_words_torch(kernel_map: "KernelMap", skip: int) -> tuple[Tensor, Tensor, int]:
    """``(table [M, K], words [M, W], collisions)``: neighbour table (``num_in`` where absent), pattern
    bit masks (bit ``k % MASK_WORD_BITS`` of word ``k // MASK_WORD_BITS``), and the number of pairs
    that landed on an already filled (row, offset) slot (then the table cannot express the map).
    Offset ``skip`` is left out (treated as absent)."""
    k_vol, m = kernel_map.kernel_volume, kernel_map.num_out
    table = torch.full((k_vol, m), kernel_map.num_in, dtype=torch.int64)
    for k in range(k_vol):
        if k != skip and kernel_map.out_indices[k].numel():
            table[k].index_copy_(0, kernel_map.out_indices[k], kernel_map.in_indices[k])
    present = table < kernel_map.num_in
    words = torch.zeros(m, max(1, -(-k_vol // MASK_WORD_BITS)), dtype=torch.int64)
    for k in range(k_vol):
        words[:, k // MASK_WORD_BITS] |= present[k].long() << (k % MASK_WORD_BITS)
    num_pairs = sum(int(rows.numel()) for k, rows in enumerate(kernel_map.out_indices) if k != skip)
    return table.t().contiguous(), words, num_pairs - int(present.sum())


def _table_and_words_numba(kernel_map: "KernelMap", skip: int) -> tuple[Tensor, Tensor, int]:
    """Same as :func:`_table_and_words_torch`, one pass over the pairs (numba)."""
    kept = [k != skip for k in range(kernel_map.kernel_volume)]
    counts = [int(rows.numel()) if keep else 0 for rows, keep in zip(kernel_map.out_indices, kept)]
    starts = np.zeros(len(counts) + 1, dtype=np.int64)
    starts[1:] = np.cumsum(counts)
    empty = [torch.zeros(0, dtype=torch.int64)]
    in_rows = torch.cat([rows for rows, keep in zip(kernel_map.in_indices, kept) if keep] or empty)
    out_rows = torch.cat([rows for rows, keep in zip(kernel_map.out_indices, kept) if keep] or empty)
    in_rows, out_rows = in_rows.numpy(), out_rows.numpy()
    table, words, collisions = nk.fill_neighbour_table(
        in_rows, out_rows, starts, kernel_map.num_in, kernel_map.num_out, MASK_WORD_BITS)
    return torch.from_numpy(table), torch.from_numpy(words), int(collisions)


def _unique_patterns(words: Tensor, k_vol: int) -> tuple[Tensor, Tensor, Tensor]:
    """Distinct rows of ``words [M, W]``: ``(patterns [U, K] bool, inverse [M], counts [U])``.

    Several words are combined by successive 1D ``unique`` (exact, and much faster than
    ``unique(dim=0)``).
    """
    m, num_words = words.shape
    if num_words == 1:
        key = words[:, 0]
    else:
        key = torch.zeros(m, dtype=torch.int64)
        for w in range(num_words):
            word_ids = torch.unique(words[:, w], return_inverse=True)[1]
            key = key * (int(word_ids.max()) + 1) + word_ids  # < M^2: exact in int64 for M < 3e9
            key = torch.unique(key, return_inverse=True)[1]
    ids, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
    if num_words == 1:
        distinct = ids[:, None]
    else:
        first = torch.full((ids.numel(),), m, dtype=torch.int64).scatter_reduce_(
            0, inverse, torch.arange(m), reduce="amin")
        distinct = words[first]
    k = torch.arange(k_vol, dtype=torch.int64)
    bits = (distinct[:, k // MASK_WORD_BITS] >> (k % MASK_WORD_BITS)) & 1
    return bits.bool(), inverse, counts


def build_gather_plan(
    kernel_map: "KernelMap", min_group_rows: int = MIN_GROUP_ROWS, max_groups: int = MAX_GROUPS,
    backend: str = "auto", min_pairs_per_row: float = MIN_PAIRS_PER_ROW_FOR_GROUPS,
) -> GatherPlan:
    """Group the output rows of ``kernel_map`` by neighbour pattern (module docstring).

    ``backend``: ``"numba"``, ``"torch"`` or ``"auto"`` (numba on CPU when it imports); same plan.
    A map that some output row reads twice through one offset (none built here) cannot be a
    neighbour table: it gets no groups, all its pairs go to the residual.
    """
    k_vol = kernel_map.kernel_volume
    m = kernel_map.num_out
    identity = [k for k in range(k_vol) if kernel_map.identity[k]] if kernel_map.num_in == m else []
    identity_offset = identity[0] if identity else -1
    if m == 0:
        empty = (torch.zeros(0, dtype=torch.int64),) * k_vol
        return GatherPlan((), empty, empty, kernel_map.num_in, 0, k_vol, identity_offset)
    empty = torch.zeros(0, dtype=torch.int64)
    residual_only = GatherPlan(
        (), tuple(empty if k == identity_offset else rows for k, rows in enumerate(kernel_map.in_indices)),
        tuple(empty if k == identity_offset else rows for k, rows in enumerate(kernel_map.out_indices)),
        kernel_map.num_in, m, k_vol, identity_offset,
    )
    num_pairs = sum(int(rows.numel()) for k, rows in enumerate(kernel_map.out_indices) if k != identity_offset)
    if num_pairs < min_pairs_per_row * m:
        return residual_only
    use_numba = resolve_backend(backend, kernel_map.out_indices[0]) == "numba"
    table, words, collisions = (_table_and_words_numba if use_numba else _table_and_words_torch)(
        kernel_map, identity_offset)
    if collisions:  # several inputs for one (row, offset): no neighbour table; the residual handles it
        return residual_only
    bits, inverse, counts = _unique_patterns(words, k_vol)  # bits [U, K]
    num_patterns = bits.shape[0]
    sizes = bits.sum(1)
    frequent = (counts >= min_group_rows) & (sizes > 0)
    frequent = frequent.nonzero().squeeze(1)
    if frequent.numel() > max_groups:
        frequent = frequent[torch.argsort(counts[frequent], descending=True, stable=True)[:max_groups]]
    # Smallest patterns first, ties: most rows first (a cost tie below goes to the first candidate).
    frequent = frequent[torch.argsort(sizes[frequent] * (m + 1) - counts[frequent], stable=True)]
    # Row cost with pattern u (|u| real neighbours) in candidate group c: |c| gathered slots plus
    # RESIDUAL_COST_RATIO per pair of u outside c (those go to the residual); alone: ratio * |u|.
    cand_bits = bits[frequent]  # [C, K]
    inside = bits.to(torch.float32) @ cand_bits.to(torch.float32).t()  # [U, C] |u & c|
    cost = sizes[frequent][None, :] + RESIDUAL_COST_RATIO * (sizes[:, None] - inside)
    alone = RESIDUAL_COST_RATIO * sizes.to(torch.float32)
    if frequent.numel():
        best_cost, best = cost.min(1)
        group_of_pattern = torch.where(best_cost < alone, best, -1)
    else:
        group_of_pattern = torch.full((num_patterns,), -1, dtype=torch.int64)
    group_of_pattern[sizes == 0] = -2  # no input besides the identity offset: nothing to gather
    group_of_row = group_of_pattern[inverse]
    order = torch.argsort(group_of_row, stable=True)
    rows_per_group = torch.split(order, torch.bincount(group_of_row + 2, minlength=frequent.numel() + 2).tolist())
    groups = []
    for candidate, rows in zip(frequent.tolist(), rows_per_group[2:]):
        if rows.numel():
            offsets = bits[candidate].nonzero().squeeze(1)
            if use_numba:
                neighbours = torch.from_numpy(nk.gather_table_block(table.numpy(), rows.numpy(), offsets.numpy()))
            else:
                neighbours = table.index_select(0, rows).index_select(1, offsets)
            groups.append(GatherGroup(rows, offsets, neighbours))
    # Residual: the pairs of each row at offsets outside its group's pattern (all of them if none).
    if use_numba:
        in_cat, out_cat, counts_k = nk.residual_pairs(
            table.numpy(), group_of_row.numpy(), cand_bits.to(torch.uint8).numpy(), kernel_map.num_in)
        split = counts_k.tolist()
        residual_in = torch.split(torch.from_numpy(in_cat), split)
        residual_out = torch.split(torch.from_numpy(out_cat), split)
    else:
        covered = torch.zeros(num_patterns, k_vol, dtype=torch.bool)
        in_group = group_of_pattern >= 0
        covered[in_group] = cand_bits[group_of_pattern[in_group]]
        residual_patterns = (bits & ~covered).any(1).nonzero().squeeze(1)
        residual_rows = torch.isin(inverse, residual_patterns).nonzero().squeeze(1)
        residual_mask = (bits & ~covered)[inverse[residual_rows]]  # [R, K]
        residual = table.index_select(0, residual_rows)  # [R, K]
        residual_in, residual_out = [], []
        for k in range(k_vol):
            has = residual_mask[:, k]
            residual_in.append(residual[has, k])
            residual_out.append(residual_rows[has])
    return GatherPlan(tuple(groups), tuple(residual_in), tuple(residual_out), kernel_map.num_in, kernel_map.num_out,
                      k_vol, identity_offset)


def flip_plan(plan: GatherPlan) -> GatherPlan:
    """Plan of the transposed map of a *symmetric* map: same rows and neighbours, offsets ``K - 1 - k``."""
    k_vol = plan.kernel_volume
    groups = tuple(GatherGroup(g.rows, k_vol - 1 - g.offsets, g.neighbours) for g in plan.groups)
    identity = k_vol - 1 - plan.identity_offset if plan.identity_offset >= 0 else -1
    return GatherPlan(
        groups, plan.residual_in[::-1], plan.residual_out[::-1], plan.num_out, plan.num_in, k_vol, identity)


def gather_plans(kernel_map: "KernelMap", grouped: bool = True) -> tuple[GatherPlan, GatherPlan]:
    """``(plan, transposed plan)`` of a map, cached in ``kernel_map.cache`` when it has one.

    ``grouped=False``: the residual-only plans (no neighbour table; the per-offset method).
    """
    key = "plans" if grouped else "residual_plans"
    cache = kernel_map.cache
    if cache is not None and key in cache:
        return cache[key]
    device = kernel_map.in_indices[0].device if kernel_map.in_indices else torch.device("cpu")
    if device.type != "cpu":  # a GPU map: the plans are built on the CPU (numba), then moved to the map's device
        plan, plan_t = (plan_to(p, device) for p in gather_plans(map_on_cpu(kernel_map), grouped))
    else:
        min_rows = MIN_PAIRS_PER_ROW_FOR_GROUPS if grouped else math.inf
        plan = build_gather_plan(kernel_map, min_pairs_per_row=min_rows)
        plan_t = flip_plan(plan) if kernel_map.symmetric else build_gather_plan(
            kernel_map.transposed(), min_pairs_per_row=min_rows)
    if cache is not None:
        cache[key] = (plan, plan_t)
        transposed_cache = kernel_map.transposed().cache
        if not kernel_map.symmetric and transposed_cache is not None:
            transposed_cache[key] = (plan_t, plan)
    return plan, plan_t


def map_on_cpu(kernel_map: "KernelMap") -> "KernelMap":
    """A copy of ``kernel_map`` with its index tensors on the CPU and an empty cache of its own."""
    return type(kernel_map)(
        tuple(t.cpu() for t in kernel_map.in_indices), tuple(t.cpu() for t in kernel_map.out_indices),
        kernel_map.identity, kernel_map.num_in, kernel_map.num_out, kernel_map.symmetric, {})


def plan_to(plan: GatherPlan, device: torch.device) -> GatherPlan:
    """``plan`` with every index tensor on ``device``."""
    groups = tuple(GatherGroup(g.rows.to(device), g.offsets.to(device), g.neighbours.to(device)) for g in plan.groups)
    return plan._replace(groups=groups, residual_in=tuple(t.to(device) for t in plan.residual_in),
                         residual_out=tuple(t.to(device) for t in plan.residual_out))


def resolve_backend(backend: str, x: Tensor) -> str:
    """``"numba"`` or ``"torch"``; ``"auto"`` is numba for CPU tensors (numba is a required dependency)."""
    if backend == "auto":
        return "numba" if x.device.type == "cpu" else "torch"
    if backend not in ("numba", "torch"):
        raise ValueError(f"backend must be 'auto', 'numba' or 'torch', got {backend!r}")
    return backend
