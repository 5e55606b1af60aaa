"""Sparse voxel convolution against dense conv3d / conv_transpose3d and naive references."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from ovgaussian.sparse import (
    DownConv3d, SparseBatchNorm, SparseVoxels, SubmanifoldConv3d, UpConv3d, VoxelSites, pack_keys, sparse_conv,
    voxelize_points,
)
from ovgaussian.sparse.conv import sparse_conv_autograd
from ovgaussian.sparse.gather_gemm import gather_gemm_conv
from ovgaussian.sparse.gather_plan import build_gather_plan, flip_plan, gather_plans
from ovgaussian.sparse.kernel_map import KernelMap, build_submanifold_map
from ovgaussian.sparse.reference import (
    down_conv_dense, naive_submanifold_pairs, submanifold_conv_dense, up_conv_dense,
)
from ovgaussian.sparse.voxelize import COORD_MAX, unpack_keys


def random_sites(seed: int, num_scenes: int, shape: int, density: float) -> VoxelSites:
    g = torch.Generator().manual_seed(seed)
    occupied = torch.rand(num_scenes, shape, shape, shape, generator=g) < density
    b, x, y, z = occupied.nonzero().unbind(1)
    sites, _ = VoxelSites.from_coords(b, torch.stack([x, y, z], 1))
    return sites


def rand(seed: int, *shape: int, dtype=torch.float64) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def forward_backward(fn, features, weight, grad_seed=99):
    features = features.detach().clone().requires_grad_(True)
    weight = weight.detach().clone().requires_grad_(True)
    out = fn(features, weight)
    upstream = rand(grad_seed, *out.shape, dtype=out.dtype)
    (out * upstream).sum().backward()
    return out.detach(), features.grad, weight.grad


# --- keys and kernel maps ----------------------------------------------------------------------

def test_pack_unpack_roundtrip_and_order():
    coords = torch.tensor([[-5, 0, 3], [0, 0, 0], [COORD_MAX, -7, 2], [1, 2, 3]])
    batch = torch.tensor([0, 1, 2, 1])
    keys = pack_keys(batch, coords)
    b2, c2 = unpack_keys(keys)
    assert torch.equal(b2, batch) and torch.equal(c2, coords)
    lexi = sorted(range(4), key=lambda i: (int(batch[i]), *coords[i].tolist()))
    assert torch.argsort(keys).tolist() == lexi
    with pytest.raises(ValueError, match="voxel coordinates span"):
        pack_keys(torch.tensor([0]), torch.tensor([[COORD_MAX + 1, 0, 0]]))
    with pytest.raises(ValueError, match="batch_index"):
        pack_keys(torch.tensor([-1]), torch.tensor([[0, 0, 0]]))


@pytest.mark.parametrize("kernel_size", [3, 5])
@pytest.mark.parametrize("method", ["merge", "search"])
def test_submanifold_map_matches_naive_dict(kernel_size, method):
    sites = random_sites(0, 2, 6, 0.3)
    shifted, _ = VoxelSites.from_coords(sites.batch_index, sites.coords - 3)  # negative coordinates too
    for s in (sites, shifted):
        kmap = build_submanifold_map(s.keys, kernel_size, method)
        got = {(k, int(i), int(o)) for k in range(kmap.kernel_volume)
               for i, o in zip(kmap.in_indices[k], kmap.out_indices[k])}
        assert got == naive_submanifold_pairs(s, kernel_size)


def test_merge_and_search_maps_are_identical():
    for sites in (random_sites(30, 3, 12, 0.05), random_sites(31, 1, 5, 0.9), VoxelSites(torch.zeros(0, dtype=torch.int64))):
        a, b = build_submanifold_map(sites.keys, 3, "merge"), build_submanifold_map(sites.keys, 3, "search")
        for x, y in zip(a.in_indices + a.out_indices, b.in_indices + b.out_indices):
            assert torch.equal(x, y)


def test_kernel_maps_are_cached_per_sites():
    sites = random_sites(1, 1, 6, 0.3)
    assert sites.submanifold_map(3) is sites.submanifold_map(3)
    assert sites.downsample()[0] is sites.downsample()[0]
    assert sites.downsample()[0].stride == 2


# --- convolutions against dense -------------------------------------------------------------------

@pytest.mark.parametrize("kernel_size", [1, 3, 5])
def test_submanifold_conv_matches_dense_conv3d(kernel_size):
    sites = random_sites(2, 2, 8, 0.25)
    features, weight = rand(3, len(sites), 4), rand(4, kernel_size**3, 4, 5)
    conv = SubmanifoldConv3d(4, 5, kernel_size).double()

    def sparse(f, w):
        if kernel_size == 1:
            return f @ w[0]
        return sparse_conv(f, w, sites.submanifold_map(kernel_size))

    got = forward_backward(sparse, features, weight)
    want = forward_backward(lambda f, w: submanifold_conv_dense(f, sites, w, kernel_size, (8, 8, 8), 2), features, weight)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)
    # the module path gives the same forward
    with torch.no_grad():
        conv.weight.copy_(weight)
    torch.testing.assert_close(conv(SparseVoxels(features, sites)).features, want[0], atol=1e-10, rtol=1e-10)


METHODS = [("gemm", "numba"), ("gemm", "torch"), ("scatter", "numba"), ("scatter", "torch")]


@pytest.mark.parametrize("method,backend", METHODS)
@pytest.mark.parametrize("kernel_size", [3, 5])
def test_every_method_and_backend_matches_dense_conv3d_float64(method, backend, kernel_size):
    sites = random_sites(40, 2, 9, 0.3)
    features, weight = rand(41, len(sites), 3), rand(42, kernel_size**3, 3, 4)
    kmap = sites.submanifold_map(kernel_size)
    got = forward_backward(lambda f, w: sparse_conv(f, w, kmap, method, backend), features, weight)
    want = forward_backward(
        lambda f, w: submanifold_conv_dense(f, sites, w, kernel_size, (9, 9, 9), 2), features, weight)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)


def test_submanifold_conv_float32_matches_dense_and_plain_autograd():
    sites = random_sites(5, 2, 10, 0.2)
    features, weight = rand(6, len(sites), 8, dtype=torch.float32), rand(7, 27, 8, 8, dtype=torch.float32)
    kmap = sites.submanifold_map(3)
    plain = forward_backward(lambda f, w: sparse_conv_autograd(f, w, kmap), features, weight)
    want = forward_backward(lambda f, w: submanifold_conv_dense(f, sites, w, 3, (10, 10, 10), 2), features, weight)
    for method, backend in METHODS:
        got = forward_backward(lambda f, w: sparse_conv(f, w, kmap, method, backend), features, weight)
        for a, b, c in zip(got, want, plain):
            torch.testing.assert_close(a, b, atol=5e-5, rtol=1e-5)
            torch.testing.assert_close(a, c, atol=5e-5, rtol=1e-5)


def plan_pairs(plan) -> set[tuple[int, int, int]]:
    """``(offset, in_row, out_row)`` triples of a plan (absent neighbours skipped)."""
    pairs = set()
    if plan.identity_offset >= 0:
        pairs |= {(plan.identity_offset, i, i) for i in range(plan.num_out)}
    for k, (ins, outs) in enumerate(zip(plan.residual_in, plan.residual_out)):
        pairs |= {(k, int(i), int(o)) for i, o in zip(ins, outs)}
    for group in plan.groups:
        for row, nbrs in zip(group.rows.tolist(), group.neighbours.tolist()):
            for k, j in zip(group.offsets.tolist(), nbrs):
                if j < plan.num_in:
                    pairs.add((k, j, row))
    return pairs


def map_pairs(kmap) -> set[tuple[int, int, int]]:
    return {(k, int(i), int(o)) for k in range(kmap.kernel_volume)
            for i, o in zip(kmap.in_indices[k], kmap.out_indices[k])}


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("min_group_rows,max_groups", [(1, 10**6), (4, 10**6), (10**9, 10**6), (1, 2)])
def test_gather_plan_covers_every_row_once_and_every_pair(min_group_rows, max_groups, backend):
    sites = random_sites(43, 2, 7, 0.35)
    maps = [sites.submanifold_map(3), sites.downsample()[1], sites.downsample()[1].transposed()]
    if backend == "numba":  # a 125-offset map: patterns over several mask words (once is enough)
        maps.append(sites.submanifold_map(5))
    for kmap in maps:
        plan = build_gather_plan(kmap, min_group_rows=min_group_rows, max_groups=max_groups, backend=backend)
        rows = torch.cat([g.rows for g in plan.groups] + [torch.zeros(0, dtype=torch.int64)])
        assert rows.unique().numel() == rows.numel()  # each output row in at most one group
        assert plan_pairs(plan) == map_pairs(kmap)
        # ... and each pair exactly once: in a group, in the residual, or as the identity offset
        in_groups = sum(int((g.neighbours < plan.num_in).sum()) for g in plan.groups)
        in_residual = sum(int(t.numel()) for t in plan.residual_in)
        identity = plan.num_out if plan.identity_offset >= 0 else 0
        assert in_groups + in_residual + identity == sum(int(t.numel()) for t in kmap.in_indices)
        if min_group_rows == 1 and max_groups > 10**5:  # each pattern its own group: no absent neighbour
            assert all(bool((g.neighbours < kmap.num_in).all()) for g in plan.groups)
        if min_group_rows == 10**9:  # no group: everything in the residual
            assert len(plan.groups) == 0
        assert len(plan.groups) <= max_groups + 1


def conv_cases(sites: VoxelSites, sizes: tuple[int, ...]) -> list:
    """``(kernel map, dense reference (features, weight) -> out, input rows, kernel volume)`` for the submanifold maps
    of ``sizes`` on ``sites`` (an 8^3 grid, 2 scenes), its down map and its up map."""
    coarse, down = sites.downsample()
    cases = [(sites.submanifold_map(k), lambda f, w, k=k: submanifold_conv_dense(f, sites, w, k, (8, 8, 8), 2),
              len(sites), k**3) for k in sizes]
    return cases + [
        (down, lambda f, w: down_conv_dense(f, sites, coarse, w, (8, 8, 8), 2), len(sites), 8),
        (down.transposed(), lambda f, w: up_conv_dense(f, coarse, sites, w, (4, 4, 4), 2), len(coarse), 8),
    ]


def forced_plans(kmap: KernelMap, min_group_rows: int, backend: str):
    """``(plan, transposed plan)`` of ``kmap`` with groups from ``min_group_rows`` rows."""
    plan = build_gather_plan(kmap, min_group_rows=min_group_rows, backend=backend)
    plan_t = flip_plan(plan) if kmap.symmetric else build_gather_plan(
        kmap.transposed(), min_group_rows=min_group_rows, backend=backend)
    return plan, plan_t


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("min_group_rows", [1, 3, 10**9])
def test_gemm_with_forced_groupings_matches_dense_float64(min_group_rows, backend):
    """Groups only, groups + residual, residual only: all equal dense conv3d (forward and backward)."""
    for i, (kmap, dense, rows, k_vol) in enumerate(conv_cases(random_sites(54, 2, 8, 0.3), (3, 5))):
        plan, plan_t = forced_plans(kmap, min_group_rows, backend)
        if min_group_rows == 1:
            assert plan.groups and plan_t.groups
        f, w = rand(55 + i, rows, 3), rand(60 + i, k_vol, 3, 2)
        got = forward_backward(lambda a, b: gather_gemm_conv(a, b, kmap, backend, (plan, plan_t)), f, w)
        want = forward_backward(dense, f, w)
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("min_group_rows", [1, 10**9])
def test_one_pass_backward_equals_the_two_separate_gradients(min_group_rows, backend):
    """``plan_backward`` (both gradients from one gather of ``grad_out``, used when both are needed) against
    ``apply_plan`` on the transposed plan and ``plan_weight_grad`` on the plan (the paths taken when only one
    is needed), on a submanifold map and on down and up maps; and each single-gradient path against dense."""
    from ovgaussian.sparse.gather_gemm import apply_plan, block_ops, plan_backward, plan_weight_grad

    for i, (kmap, dense, rows, k_vol) in enumerate(conv_cases(random_sites(71, 2, 8, 0.35), (3,))):
        plan, plan_t = forced_plans(kmap, min_group_rows, backend)
        if min_group_rows == 1:
            assert plan_t.groups
        f, w = rand(72 + i, rows, 4), rand(76 + i, k_vol, 4, 5)
        grad_out = rand(80 + i, kmap.num_out, 5)
        ops = block_ops(backend, f)
        grad_f, grad_w = plan_backward(f, grad_out, w, plan_t, ops)
        torch.testing.assert_close(grad_f, apply_plan(grad_out, w.transpose(1, 2), plan_t, ops), atol=1e-12, rtol=0)
        torch.testing.assert_close(grad_w, plan_weight_grad(f, grad_out, plan, ops), atol=1e-12, rtol=0)
        # single gradients through autograd: frozen weight (input gradient only), input without gradient
        conv = lambda a, b: gather_gemm_conv(a, b, kmap, backend, (plan, plan_t))  # noqa: E731
        want = forward_backward(dense, f, w)
        f_only = f.clone().requires_grad_(True)
        (conv(f_only, w) * rand(99, kmap.num_out, 5)).sum().backward()
        w_only = w.clone().requires_grad_(True)
        (conv(f, w_only) * rand(99, kmap.num_out, 5)).sum().backward()
        torch.testing.assert_close(f_only.grad, want[1], atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(w_only.grad, want[2], atol=1e-10, rtol=1e-10)


def test_flipped_plan_of_a_submanifold_map_is_the_transposed_plan():
    sites = random_sites(44, 1, 8, 0.3)
    kmap = sites.submanifold_map(3)
    plan, plan_t = gather_plans(kmap)
    assert plan_pairs(flip_plan(plan)) == plan_pairs(build_gather_plan(kmap.transposed())) == map_pairs(kmap.transposed())
    assert gather_plans(kmap) is gather_plans(kmap)  # cached on the map
    assert kmap.transposed() is kmap.transposed() and kmap.transposed().transposed() is kmap


def test_plan_groups_by_pattern_on_a_plane():
    """A 6 x 6 plane: interior sites see the 9 in-plane offsets, border sites fewer (residual)."""
    x, y = torch.meshgrid(torch.arange(6), torch.arange(6), indexing="ij")
    coords = torch.stack([x.reshape(-1), y.reshape(-1), torch.zeros(36, dtype=torch.long)], 1)
    sites, _ = VoxelSites.from_coords(torch.zeros(36, dtype=torch.long), coords)
    plan = build_gather_plan(sites.submanifold_map(3), min_group_rows=16)
    # 16 interior rows see the 8 in-plane offsets around the centre; the border rows (5 or 3
    # neighbours: 8 gathered would exceed RESIDUAL_COST_RATIO times that) go to the residual
    assert plan.identity_offset == 13
    assert len(plan.groups) == 1 and plan.groups[0].offsets.tolist() == [1, 4, 7, 10, 16, 19, 22, 25]
    interior = ((sites.coords[:, 0] % 5 != 0) & (sites.coords[:, 1] % 5 != 0)).nonzero().squeeze(1)
    assert torch.equal(plan.groups[0].rows, interior)
    assert bool((plan.groups[0].neighbours < 36).all())
    assert set(torch.cat(plan.residual_out).tolist()) == set(range(36)) - set(interior.tolist())
    # a row whose pattern is a large part of a group's joins it and sends the rest to the residual
    sites2, _ = VoxelSites.from_coords(torch.zeros(37, dtype=torch.long), torch.cat([coords, torch.tensor([[2, 2, 1]])]))
    plan2 = build_gather_plan(sites2.submanifold_map(3), min_group_rows=5)  # 7 rows keep the plain pattern
    row = int(((sites2.coords == torch.tensor([2, 2, 0])).all(1)).nonzero())
    assert row in plan2.groups[0].rows.tolist()
    assert [(k, int(o)) for k, t in enumerate(plan2.residual_out) for o in t if int(o) == row] == [(14, row)]
    assert plan_pairs(plan2) == map_pairs(sites2.submanifold_map(3))
    assert plan_pairs(plan) == map_pairs(sites.submanifold_map(3))


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_map_with_two_inputs_per_offset_goes_to_the_residual(backend):
    kmap = KernelMap((torch.tensor([0, 1]),), (torch.tensor([0, 0]),), (False,), 2, 1)
    plan = build_gather_plan(kmap, min_group_rows=1, backend=backend)
    assert plan.groups == () and plan_pairs(plan) == {(0, 0, 0), (0, 1, 0)}
    f, w = rand(45, 2, 3), rand(46, 1, 3, 2)
    for method in ("gemm", "scatter"):
        got = forward_backward(lambda a, b: sparse_conv(a, b, kmap, method, backend), f, w)
        want = forward_backward(lambda a, b: (a[0:1] + a[1:2]) @ b[0], f, w)
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)
    with pytest.raises(ValueError, match="method"):
        sparse_conv(f, w, kmap, "dense")


def test_sparse_map_gets_no_groups():
    """Under MIN_PAIRS_PER_ROW_FOR_GROUPS non-identity pairs per row: residual only, same result."""
    sites = random_sites(56, 1, 12, 0.02)
    kmap = sites.submanifold_map(3)
    assert sum(int(t.numel()) for t in kmap.in_indices) - len(sites) < len(sites)
    plan = build_gather_plan(kmap)
    assert plan.groups == () and plan_pairs(plan) == map_pairs(kmap)


@pytest.mark.parametrize("method", ["gemm", "scatter"])
def test_nan_feature_reaches_exactly_its_neighbours(method):
    sites = random_sites(47, 1, 6, 0.4)
    kmap = sites.submanifold_map(3)
    f = rand(48, len(sites), 2)
    f[3, 1] = float("nan")
    out = sparse_conv(f, rand(49, 27, 2, 2), kmap, method)
    reads_row_3 = torch.zeros(len(sites), dtype=torch.bool)
    for k in range(27):
        reads_row_3[kmap.out_indices[k][kmap.in_indices[k] == 3]] = True
    assert torch.equal(torch.isnan(out).any(1), reads_row_3)


@pytest.mark.parametrize("method,backend", METHODS)
def test_down_and_up_conv_match_dense(method, backend):
    sites = random_sites(8, 2, 8, 0.3)
    coarse, kmap = sites.downsample()
    features, w_down = rand(9, len(sites), 3), rand(10, 8, 3, 6)
    got = forward_backward(lambda f, w: sparse_conv(f, w, kmap, method, backend), features, w_down)
    want = forward_backward(lambda f, w: down_conv_dense(f, sites, coarse, w, (8, 8, 8), 2), features, w_down)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)
    # coarse sites are exactly the occupied 2x2x2 cells
    expected = torch.unique(pack_keys(sites.batch_index, sites.coords // 2))
    assert torch.equal(coarse.keys, expected)

    coarse_features, w_up = rand(11, len(coarse), 6), rand(12, 8, 6, 3)
    got = forward_backward(lambda f, w: sparse_conv(f, w, kmap.transposed(), method, backend), coarse_features, w_up)
    want = forward_backward(lambda f, w: up_conv_dense(f, coarse, sites, w, (4, 4, 4), 2), coarse_features, w_up)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)


def test_down_conv_with_negative_coordinates_uses_floor():
    coords = torch.tensor([[-1, -1, -1], [-2, 0, 1], [1, 1, 1]])
    sites, _ = VoxelSites.from_coords(torch.zeros(3, dtype=torch.long), coords)
    coarse, kmap = sites.downsample()
    assert sorted(map(tuple, coarse.coords.tolist())) == [(-1, -1, -1), (-1, 0, 0), (0, 0, 0)]
    # shifting by a whole coarse voxel (+2) keeps the row order and must not change the result
    shifted, _ = VoxelSites.from_coords(sites.batch_index, sites.coords + 2)
    assert torch.equal(shifted.coords, sites.coords + 2)
    f, w = rand(13, 3, 2), rand(14, 8, 2, 2)
    torch.testing.assert_close(sparse_conv(f, w, shifted.downsample()[1]), sparse_conv(f, w, kmap))
    torch.testing.assert_close(shifted.downsample()[0].coords, coarse.coords + 1)


def test_modules_chain_down_up_restores_fine_sites():
    sites = random_sites(15, 1, 8, 0.3)
    x = SparseVoxels(rand(16, len(sites), 4, dtype=torch.float32), sites)
    down, up = DownConv3d(4, 8), UpConv3d(8, 4)
    y = up(down(x), sites)
    assert y.sites is sites and y.features.shape == (len(sites), 4)
    with pytest.raises(ValueError, match="not the downsampling"):
        up(down(x), random_sites(17, 1, 8, 0.3))


def test_empty_input_gives_empty_output_and_zero_weight_gradient():
    sites = VoxelSites(torch.zeros(0, dtype=torch.int64))
    for module, fine in ((SubmanifoldConv3d(3, 4), None), (DownConv3d(3, 4), None), (UpConv3d(3, 4), sites)):
        x = SparseVoxels(torch.zeros(0, 3, requires_grad=True), sites)
        y = module(x) if fine is None else module(x, fine)
        assert y.features.shape == (0, 4)
        y.features.sum().backward()
        assert torch.equal(module.weight.grad, torch.zeros_like(module.weight))
    assert len(sites.downsample()[0]) == 0


def test_single_voxel():
    sites, _ = VoxelSites.from_coords(torch.tensor([0]), torch.tensor([[3, 4, 5]]))
    f, w = rand(18, 1, 3), rand(19, 27, 3, 2)
    got = forward_backward(lambda a, b: sparse_conv(a, b, sites.submanifold_map(3)), f, w)
    want = forward_backward(lambda a, b: submanifold_conv_dense(a, sites, b, 3, (8, 8, 8), 1), f, w)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b)
    torch.testing.assert_close(got[0], f @ w[13])
    coarse, kmap = sites.downsample()
    assert coarse.coords.tolist() == [[1, 2, 2]]
    torch.testing.assert_close(sparse_conv(f, rand(20, 8, 3, 2), kmap), f @ rand(20, 8, 3, 2)[(1 * 2 + 0) * 2 + 1])


# --- batch norm -----------------------------------------------------------------------------------

def test_sparse_batch_norm_matches_batchnorm1d():
    bn, ref = SparseBatchNorm(5), nn.BatchNorm1d(5)
    with torch.no_grad():
        for m in (bn, ref):
            m.weight.copy_(rand(21, 5, dtype=torch.float32))
            m.bias.copy_(rand(22, 5, dtype=torch.float32))
    sites = random_sites(23, 1, 6, 0.3)
    f = rand(24, len(sites), 5, dtype=torch.float32) * 3 + 1
    for training in (True, False):
        bn.train(training), ref.train(training)
        a = f.clone().requires_grad_(True)
        b = f.clone().requires_grad_(True)
        out_a, out_b = bn(SparseVoxels(a, sites)).features, ref(b)
        torch.testing.assert_close(out_a, out_b)
        up = rand(25, *out_a.shape, dtype=torch.float32)
        (out_a * up).sum().backward(), (out_b * up).sum().backward()
        torch.testing.assert_close(a.grad, b.grad)
        torch.testing.assert_close(bn.running_mean, ref.running_mean)
        torch.testing.assert_close(bn.running_var, ref.running_var)


def test_sparse_batch_norm_one_and_zero_rows():
    bn = SparseBatchNorm(3)
    with torch.no_grad():
        bn.bias.copy_(torch.tensor([1.0, 2.0, 3.0]))
    one, _ = VoxelSites.from_coords(torch.tensor([0]), torch.tensor([[0, 0, 0]]))
    out = bn(SparseVoxels(torch.tensor([[5.0, -1.0, 2.0]]), one)).features
    torch.testing.assert_close(out, torch.tensor([[1.0, 2.0, 3.0]]))
    torch.testing.assert_close(bn.running_mean, torch.tensor([0.5, -0.1, 0.2]))
    torch.testing.assert_close(bn.running_var, torch.ones(3))
    empty = VoxelSites(torch.zeros(0, dtype=torch.int64))
    assert bn(SparseVoxels(torch.zeros(0, 3), empty)).features.shape == (0, 3)


# --- voxelization ---------------------------------------------------------------------------------

def test_voxelize_points_mean_pools_per_scene_and_voxel():
    g = torch.Generator().manual_seed(26)
    points = torch.rand(200, 3, generator=g) * 0.5
    points[:10] = points[10]  # collisions: exact duplicates
    features = torch.randn(200, 4, generator=g, requires_grad=True)
    batch = (torch.arange(200) % 3)
    vox = voxelize_points(points, features, batch, voxel_size=0.1, max_grid_extent=1000)
    pooled, inverse = vox.voxels.features, vox.point_to_voxel
    # naive: group by (batch, floor((p - scene min) / size))
    groups: dict = {}
    for i in range(200):
        b = int(batch[i])
        lo = points[batch == b].double().min(0).values
        key = (b, *torch.floor((points[i].double() - lo) / 0.1).long().tolist())
        groups.setdefault(key, []).append(i)
    assert len(groups) == len(vox.voxels.sites)
    for key, members in groups.items():
        row = int(inverse[members[0]])
        assert all(int(inverse[m]) == row for m in members)
        assert (int(vox.voxels.sites.batch_index[row]), *vox.voxels.sites.coords[row].tolist()) == key
        torch.testing.assert_close(pooled[row], features[members].mean(0))
    pooled.sum().backward()
    assert torch.isfinite(features.grad).all() and (features.grad > 0).all()


def test_voxelize_adaptive_cap_and_bad_input():
    points = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [5.0, 1.0, 0.0]])
    vox = voxelize_points(points, torch.ones(3, 1), torch.zeros(3, dtype=torch.long), 0.05, max_grid_extent=101)
    assert vox.voxel_size.tolist() == pytest.approx([0.1])
    assert int(vox.voxels.sites.coords.max()) == 100
    bad = points.clone()
    bad[1, 2] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        voxelize_points(bad, torch.ones(3, 1), torch.zeros(3, dtype=torch.long), 0.05, 101)
    empty = voxelize_points(torch.zeros(0, 3), torch.zeros(0, 2), torch.zeros(0, dtype=torch.long), 0.05, 101)
    assert empty.voxels.features.shape == (0, 2) and len(empty.voxels.sites) == 0


def test_kernel_size_outside_the_key_margin_is_rejected():
    sites = random_sites(32, 1, 4, 0.5)
    with pytest.raises(ValueError, match="odd, positive"):
        build_submanifold_map(sites.keys, 19)
    with pytest.raises(ValueError, match="odd, positive"):
        build_submanifold_map(sites.keys, 4)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_gather_plan_of_a_map_with_unsorted_pairs(backend):
    """Pairs in any order within an offset give the same plan pairs and the same conv (other fill path)."""
    sites = random_sites(50, 1, 7, 0.3)
    kmap = sites.submanifold_map(3)
    g = torch.Generator().manual_seed(51)
    perms = [torch.randperm(rows.numel(), generator=g) for rows in kmap.in_indices]
    shuffled = KernelMap(tuple(r[p] for r, p in zip(kmap.in_indices, perms)),
                         tuple(r[p] for r, p in zip(kmap.out_indices, perms)), (False,) * 27, kmap.num_in, kmap.num_out)
    plan = build_gather_plan(shuffled, backend=backend)
    assert plan.identity_offset == -1 and plan_pairs(plan) == map_pairs(kmap)
    f, w = rand(52, len(sites), 3), rand(53, 27, 3, 2)
    torch.testing.assert_close(sparse_conv(f, w, shuffled, backend=backend), sparse_conv(f, w, kmap, "scatter"),
                               atol=1e-12, rtol=1e-12)


def test_wide_convs_use_the_grouped_plan_and_narrow_ones_the_residual_plan():
    from ovgaussian.sparse.gather_gemm import MIN_GROUPED_CHANNELS

    x, y = torch.meshgrid(torch.arange(12), torch.arange(12), indexing="ij")  # a plane: 100 interior rows
    coords = torch.stack([x.reshape(-1), y.reshape(-1), torch.full((144,), 3)], 1)
    sites, _ = VoxelSites.from_coords(torch.zeros(144, dtype=torch.long), coords)
    kmap = sites.submanifold_map(3)
    for c_in, key in ((MIN_GROUPED_CHANNELS, "plans"), (MIN_GROUPED_CHANNELS - 1, "residual_plans")):
        f, w = rand(58, len(sites), c_in), rand(59, 27, c_in, 3)
        got = forward_backward(lambda a, b: sparse_conv(a, b, kmap), f, w)
        want = forward_backward(lambda a, b: submanifold_conv_dense(a, sites, b, 3, (12, 12, 12), 1), f, w)
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)
        assert key in kmap.cache
    assert kmap.cache["plans"][0].groups and not kmap.cache["residual_plans"][0].groups
