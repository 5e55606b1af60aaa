"""The one k-nearest-neighbour search of the toolkit over a fixed set of 3D points (scipy cKDTree or open3d's
index): the label transfer, its sweep, the oracle's spacing and the fit's initial scales all query through it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

#: Nearest-neighbour backends of ``nearest_neighbours`` (``TransferConfig.backend``).
KNN_BACKENDS = ("scipy", "open3d")

#: ``query(x [Q, 3], k) -> (distances [Q, k] ascending, indices [Q, k])`` over a fixed set of candidates.
KnnQuery = Callable[[np.ndarray, int], "tuple[np.ndarray, np.ndarray]"]


def nearest_neighbours(cand_points: np.ndarray, backend: str) -> KnnQuery:
    """The one k-nearest-neighbour search of the toolkit over ``cand_points`` ``[C, 3]``:
    ``query(x [Q, 3], k) -> (distances [Q, k] float64 ascending, indices [Q, k] int64)``.

    ``backend`` (``TransferConfig.backend``): ``scipy`` (cKDTree, on as many threads as torch's intra-op count, which
    ``seggaussian.util.threads.cap_threads`` caps in a scene worker; the answer is the same on any count) or
    ``open3d`` (its NNS index; it returns squared distances, square-rooted here). With no candidate every distance is
    inf and every index -1."""
    cand_points = np.ascontiguousarray(cand_points, dtype=np.float64)
    if backend not in KNN_BACKENDS:
        raise ValueError(f"transfer: backend must be 'scipy' or 'open3d', got {backend!r}")
    if not len(cand_points):
        return lambda x, k: (np.full((len(x), k), np.inf), np.full((len(x), k), -1, np.int64))
    if backend == "scipy":
        import torch
        from scipy.spatial import cKDTree

        tree = cKDTree(cand_points)

        def query(x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
            d, i = tree.query(x, k=k, workers=max(1, torch.get_num_threads()))
            return np.asarray(d, np.float64).reshape(len(x), k), np.asarray(i, np.int64).reshape(len(x), k)

        return query
    import open3d as o3d

    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(cand_points))
    nns.knn_index()

    def query(x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        if not len(x):
            return np.zeros((0, k)), np.zeros((0, k), np.int64)
        i, d2 = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(x, dtype=np.float64)), k)
        return np.sqrt(np.maximum(d2.numpy().astype(np.float64), 0.0)), i.numpy().astype(np.int64)

    return query
