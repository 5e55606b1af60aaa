"""Kernel maps: for each kernel offset, which input row feeds which output row.

A :class:`KernelMap` lists, per kernel offset ``k`` (offsets in ``(dx, dy, dz)`` lexicographic order,
the order of a dense ``conv3d`` weight's spatial dims), the pairs ``(in_indices[k][p],
out_indices[k][p])``: output row ``out`` receives ``features[in] @ weight[k]``.

Submanifold maps come from the sorted keys: the neighbour keys ``keys + delta(d)`` of one offset are
sorted too, so a linear merge of two sorted arrays finds every pair (numba, ``merge_lookup_pairs``);
the pure-torch ``torch.searchsorted`` version (``search_lookup_pairs``) is the reference and the
fallback. Offsets ``d`` and ``-d`` are mirror images of each other (``i + d = j`` iff ``j - d = i``), so
only half of them are looked up.
The stride-2, kernel-2 map needs no search: site ``c`` feeds ``floor(c / 2)`` through offset
``c mod 2``.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ovgaussian.sparse._numba_kernels import merge_pairs
from ovgaussian.sparse.keys import KEY_MARGIN, offset_key_delta, pack_keys


class KernelMap(NamedTuple):
    """Input/output row pairs per kernel offset.

    Attributes:
        in_indices: per offset, ``[P_k]`` int64 rows of the input features.
        out_indices: per offset, ``[P_k]`` int64 rows of the output features.
        identity: per offset, True when the pairs are ``(i, i)`` for every row (skip the gather).
        num_in: number of input rows.
        num_out: number of output rows.
        symmetric: True when output row ``i`` reads input ``j`` through offset ``k`` iff ``j`` reads ``i``
            through offset ``K - 1 - k`` (submanifold maps); the transposed map is then the same map
            with the offsets reversed.
        cache: per-map cache of derived data (the implicit-GEMM plans, the transposed map), or None.
    """

    in_indices: tuple[Tensor, ...]
    out_indices: tuple[Tensor, ...]
    identity: tuple[bool, ...]
    num_in: int
    num_out: int
    symmetric: bool = False
    cache: dict | None = None

    @property
    def kernel_volume(self) -> int:
        return len(self.in_indices)

    def transposed(self) -> "KernelMap":
        """The same pairs with inputs and outputs swapped (the map of the transposed conv).

        Cached: a cached map returns the same transposed map every call (whose transpose is this map).
        """
        if self.cache is not None and "transposed" in self.cache:
            return self.cache["transposed"]
        transposed = KernelMap(
            self.out_indices, self.in_indices, self.identity, self.num_out, self.num_in, self.symmetric,
            None if self.cache is None else {"transposed": self},
        )
        if self.cache is not None:
            self.cache["transposed"] = transposed
        return transposed


def kernel_offsets(kernel_size: int) -> list[tuple[int, int, int]]:
    """Offsets of an odd cubic kernel centred on the site, ``(dx, dy, dz)`` lexicographic."""
    if kernel_size < 1 or kernel_size % 2 == 0 or kernel_size // 2 > KEY_MARGIN:
        raise ValueError(f"submanifold kernel size must be odd, positive and <= {2 * KEY_MARGIN + 1}, got {kernel_size}")
    r = kernel_size // 2
    return list(itertools.product(range(-r, r + 1), repeat=3))


def lookup_keys(sorted_keys: Tensor, queries: Tensor) -> tuple[Tensor, Tensor]:
    """Rows of ``queries`` present in ``sorted_keys``: ``(query_rows [P], key_rows [P])``."""
    if sorted_keys.numel() == 0 or queries.numel() == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=sorted_keys.device)
        return empty, empty
    pos = torch.searchsorted(sorted_keys, queries)
    pos.clamp_(max=sorted_keys.numel() - 1)
    hit = sorted_keys[pos] == queries
    query_rows = hit.nonzero().squeeze(1)
    return query_rows, pos[query_rows]


def search_lookup_pairs(sorted_keys: Tensor, deltas: list[int]) -> list[tuple[Tensor, Tensor]]:
    """Per delta, the rows ``(i, j)`` with ``keys[j] == keys[i] + delta`` (``torch.searchsorted``)."""
    return [lookup_keys(sorted_keys, sorted_keys + delta) for delta in deltas]


def merge_lookup_pairs(sorted_keys: Tensor, deltas: list[int]) -> list[tuple[Tensor, Tensor]]:
    """Same result as :func:`search_lookup_pairs`, by a linear merge per delta (numba)."""
    keys = sorted_keys.contiguous().numpy()
    rows_i, rows_j, counts = merge_pairs(keys, np.asarray(deltas, dtype=np.int64))
    out = []
    for d, c in enumerate(counts.tolist()):
        out.append((torch.from_numpy(rows_i[d, :c].copy()), torch.from_numpy(rows_j[d, :c].copy())))
    return out


def build_submanifold_map(sorted_keys: Tensor, kernel_size: int, method: str = "auto") -> KernelMap:
    """Map of a submanifold conv: output sites = input sites = ``sorted_keys``.

    Args:
        method: ``"merge"`` (numba), ``"search"`` (pure torch), or ``"auto"`` (merge when numba imports).
    """
    offsets = kernel_offsets(kernel_size)
    num_offsets = len(offsets)
    center = num_offsets // 2
    m = sorted_keys.numel()
    in_idx: list[Tensor | None] = [None] * num_offsets
    out_idx: list[Tensor | None] = [None] * num_offsets
    identity = [False] * num_offsets
    arange = torch.arange(m, dtype=torch.int64, device=sorted_keys.device)
    in_idx[center], out_idx[center], identity[center] = arange, arange, True
    if method == "auto":
        method = "merge" if sorted_keys.device.type == "cpu" else "search"
    if method not in ("merge", "search"):
        raise ValueError(f"method must be 'auto', 'merge' or 'search', got {method!r}")
    deltas = [offset_key_delta(offsets[k]) for k in range(center)]
    lookup = merge_lookup_pairs if method == "merge" and m else search_lookup_pairs
    for k, (rows_i, rows_j) in enumerate(lookup(sorted_keys, deltas)):
        # Output site i reads input site j = i + d_k; the mirror offset -d_k pairs (out j, in i).
        in_idx[k], out_idx[k] = rows_j, rows_i
        mirror = num_offsets - 1 - k
        in_idx[mirror], out_idx[mirror] = rows_i, rows_j
    return KernelMap(tuple(in_idx), tuple(out_idx), tuple(identity), m, m, symmetric=True, cache={})


def build_downsample_map(batch_index: Tensor, coords: Tensor) -> tuple[Tensor, KernelMap]:
    """Coarser sites ``unique(floor(coords / 2))`` (sorted keys) and the kernel-2, stride-2 map.

    Offset index of fine site ``c`` is ``((cx mod 2) * 2 + cy mod 2) * 2 + cz mod 2``, the order of a
    dense ``conv3d`` weight's ``[2, 2, 2]`` spatial dims.
    """
    coarse = torch.div(coords, 2, rounding_mode="floor")
    parity = coords - 2 * coarse  # [M, 3] in {0, 1}
    offset = (parity[:, 0] * 2 + parity[:, 1]) * 2 + parity[:, 2]
    coarse_keys, inverse = torch.unique(pack_keys(batch_index, coarse), sorted=True, return_inverse=True)
    order = torch.argsort(offset, stable=True)
    counts = torch.bincount(offset, minlength=8).tolist()
    in_idx = tuple(torch.split(order, counts))
    out_idx = tuple(inverse[rows] for rows in in_idx)
    kmap = KernelMap(in_idx, out_idx, (False,) * 8, int(coords.shape[0]), int(coarse_keys.numel()), cache={})
    return coarse_keys, kmap
