"""OVGaussianNet: shapes, gradients to every parameter, determinism, degenerate scenes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ovgaussian.model.network import OVGaussianNet, gaussian_attributes, normalized_coordinates
from ovgaussian.model.config import MINKUNET34C_BLOCKS, MINKUNET34C_WIDTHS, OVGaussianNetConfig
from seggaussian.core.constants import SH_C0
from seggaussian.core.gaussians import Gaussians

#: Tiny widths so the tests stay fast; same layout as MinkUNet34C.
TINY = dict(widths=(4, 4, 8, 8, 8, 8, 4, 4), blocks=(1, 1, 1, 1, 1, 1, 1, 1), stem_width=4, stem_kernel_size=3,
            embedding_width=12, voxel_size=0.1)


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread: on this shared 2-core machine OpenMP barriers dominate otherwise."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def random_scenes(seed: int, sizes: tuple[int, ...], extent: float = 2.0):
    g = torch.Generator().manual_seed(seed)
    n = sum(sizes)
    means = torch.rand(n, 3, generator=g) * extent
    batch = torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes))
    raw = {
        "quats": torch.randn(n, 4, generator=g),
        "log_scales": torch.randn(n, 3, generator=g) - 3,
        "opacity_logits": torch.randn(n, generator=g),
        "sh": torch.randn(n, 1, 3, generator=g),
    }
    return means, gaussian_attributes(raw), batch


def test_gaussian_attributes_order_and_degenerate_rows():
    g = Gaussians.from_arrays(
        means=np.zeros((2, 3)), quats=[[2.0, 0, 0, 0], [0, 0, 0, 0]], log_scales=[[0.0, np.log(2), -1], [100, 0, 0]],
        opacity_logits=[0.0, 50.0], sh=np.array([[[1.0, 0, -1]], [[0, 0, 0]]]),
    )
    attrs = gaussian_attributes(g)
    assert attrs.shape == (2, 11) and attrs.dtype == torch.float32
    torch.testing.assert_close(attrs[0, :3], torch.tensor([0.5 + SH_C0, 0.5, 0.5 - SH_C0]))
    torch.testing.assert_close(attrs[:, 3], torch.tensor([0.5, 1.0]))
    torch.testing.assert_close(attrs[0, 4:7], torch.tensor([1.0, 2.0, np.exp(-1)], dtype=torch.float32))
    torch.testing.assert_close(attrs[:, 7:], torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]]))  # normalized; zero -> identity
    assert torch.isfinite(attrs).all()  # log-scale 100 is clamped, not inf
    with pytest.raises(ValueError, match="'quats'"):
        gaussian_attributes({**g.to_torch(), "quats": torch.tensor([[float("nan"), 0, 0, 0]] * 2)})
    with pytest.raises(ValueError, match="missing field 'sh'"):
        gaussian_attributes({k: v for k, v in g.to_torch().items() if k != "sh"})


def test_default_config_is_minkunet34c():
    config = OVGaussianNetConfig()
    assert config.widths == MINKUNET34C_WIDTHS == (32, 64, 128, 256, 256, 128, 96, 96)
    assert config.blocks == MINKUNET34C_BLOCKS == (2, 3, 4, 6, 2, 2, 2, 2)
    net = OVGaussianNet(OVGaussianNetConfig(embedding_width=8))
    assert len(net.backbone.encoder[3]) == 6 and net.backbone.head.in_features == 96
    # MinkUNet34C has about 37.9 million parameters (MinkowskiEngine: 37.85 M for 3 -> 20 channels)
    backbone_params = sum(p.numel() for p in net.backbone.parameters())
    assert 37.0e6 < backbone_params < 38.5e6


@pytest.mark.parametrize("use_adapter,use_coordinates", [(True, False), (False, False), (True, True)])
def test_every_parameter_gets_finite_nonzero_gradient(use_adapter, use_coordinates):
    config = OVGaussianNetConfig(**TINY, use_adapter=use_adapter, use_coordinates=use_coordinates)
    net = OVGaussianNet(config)
    means, attrs, batch = random_scenes(0, (700, 500))
    s = net(means, attrs, batch)
    assert s.shape == (1200, 16) and torch.isfinite(s).all()
    g = torch.Generator().manual_seed(1)
    e1, e2 = net.phi(s), net.psi(s)
    assert e1.shape == e2.shape == (1200, 12)
    loss = (e1 * torch.randn(e1.shape, generator=g)).sum() + (e2 * torch.randn(e2.shape, generator=g)).sum()
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


@pytest.mark.parametrize("use_coordinates", [False, True])
@pytest.mark.parametrize("rows", [0, 1, 257])
def test_adapter_forward_and_backward_equal_the_reference(use_coordinates, rows):
    """The fast adapter (block-diagonal token embedding, elementwise attention) against the einsum reference,
    values and every gradient (inputs and parameters), also for 0 and 1 rows and for large attribute values."""
    net = OVGaussianNet(OVGaussianNetConfig(**TINY, use_coordinates=use_coordinates, seed=3))
    g = torch.Generator().manual_seed(rows)
    width = net.config.num_attributes
    features = torch.randn(rows, 16, generator=g, dtype=torch.float64)
    attributes = torch.rand(rows, width, generator=g, dtype=torch.float64) * 4 - 2
    if rows > 1:
        attributes[0] *= 1e3  # saturated softmax
    adapter = net.adapter.double()
    outputs, grads = [], []
    for forward in (adapter.forward, adapter.forward_reference):
        f = features.clone().requires_grad_()
        a = attributes.clone().requires_grad_()
        out = forward(f, a)
        weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
        grads.append(torch.autograd.grad((out * weights).sum(), [f, a, *adapter.parameters()], allow_unused=True))
        outputs.append(out.detach())
    assert outputs[0].shape == (rows, 16)
    torch.testing.assert_close(outputs[0], outputs[1], rtol=1e-12, atol=1e-12)
    for fast, reference in zip(*grads):
        if rows == 0 and reference is None:
            continue
        torch.testing.assert_close(fast, reference, rtol=1e-10, atol=1e-12)


def test_adapter_and_decoder_shapes():
    config = OVGaussianNetConfig(**TINY)
    net = OVGaussianNet(config)
    f = torch.randn(7, 16)
    attrs = torch.rand(7, 11)
    assert net.adapter(f, attrs).shape == (7, 16)
    assert net.adapter.mlp[0].in_features == 27  # paper: 27 -> 96 -> 96 -> 16
    assert [m.out_features for m in net.adapter.mlp if isinstance(m, torch.nn.Linear)] == [96, 96, 16]
    rendered = torch.randn(5, 6, 16)  # a rendered semantic map [H, W, 16]
    assert net.phi(rendered).shape == (5, 6, 12) and net.psi(rendered).shape == (5, 6, 12)
    assert net.phi[0].out_features == 128


def test_same_seed_same_network_and_output():
    means, attrs, batch = random_scenes(2, (300, 200))
    a, b = OVGaussianNet(OVGaussianNetConfig(**TINY, seed=3)), OVGaussianNet(OVGaussianNetConfig(**TINY, seed=3))
    c = OVGaussianNet(OVGaussianNetConfig(**TINY, seed=4))
    for (n1, p1), (_, p2) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(p1, p2), n1
    assert not torch.equal(a.backbone.stem.conv.weight, c.backbone.stem.conv.weight)
    a.eval(), b.eval()
    out_a, out_b = a(means, attrs, batch), b(means, attrs, batch)
    assert torch.equal(out_a, out_b)
    assert torch.equal(out_a, a(means, attrs, batch))  # repeated call, bit-identical
    before = torch.get_rng_state()
    OVGaussianNet(OVGaussianNetConfig(**TINY))
    assert torch.equal(before, torch.get_rng_state())  # construction leaves the global RNG alone


def test_output_follows_a_permutation_of_the_gaussians():
    net = OVGaussianNet(OVGaussianNetConfig(**TINY)).eval()
    means, attrs, batch = random_scenes(5, (400, 300))
    perm = torch.randperm(700, generator=torch.Generator().manual_seed(6))
    torch.testing.assert_close(net(means, attrs, batch)[perm], net(means[perm], attrs[perm], batch[perm]),
                               atol=1e-5, rtol=1e-5)


def test_single_gaussian_scene_and_voxel_collisions_in_training():
    net = OVGaussianNet(OVGaussianNetConfig(**TINY))
    means, attrs, batch = random_scenes(7, (1, 6, 1))
    means[1:7] = means[1] + torch.linspace(0, 0.01, 6)[:, None]  # six Gaussians in one voxel
    s = net(means, attrs, batch)
    assert s.shape == (8, 16) and torch.isfinite(s).all()
    # Gaussians sharing a voxel get different vectors through the adapter (their own attributes)
    assert not torch.allclose(s[1], s[2])
    net.phi(s).sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
    one = net(means[:1], attrs[:1], torch.zeros(1, dtype=torch.long))
    assert one.shape == (1, 16) and torch.isfinite(one).all()


def test_empty_scene_and_bad_inputs():
    net = OVGaussianNet(OVGaussianNetConfig(**TINY))
    out = net(torch.zeros(0, 3), torch.zeros(0, 11), torch.zeros(0, dtype=torch.long))
    assert out.shape == (0, 16)
    means, attrs, batch = random_scenes(8, (10,))
    with pytest.raises(ValueError, match="attributes have 10 columns"):
        net(means, attrs[:, :10], batch)
    bad = means.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="means contain NaN"):
        net(bad, attrs, batch)


@pytest.mark.parametrize("encoding", ["raw", "robust"])
def test_coordinates_option_accepts_11_or_14_columns(encoding):
    """14 columns are inputs already prepared (encoded, coordinates appended): the network takes them as they are."""
    net = OVGaussianNet(OVGaussianNetConfig(**TINY, use_coordinates=True, input_encoding=encoding)).eval()
    means, attrs, batch = random_scenes(9, (200, 100))
    coords = normalized_coordinates(means, batch)
    assert coords.abs().max() <= 1.0 + 1e-6 and coords.abs().max() > 0.9
    prepared = net.prepare_inputs(means, attrs, batch)
    if encoding == "raw":
        torch.testing.assert_close(prepared, torch.cat([attrs, coords], 1))
    torch.testing.assert_close(net(means, attrs, batch), net(means, prepared, batch))


def test_trilinear_devoxelization_is_the_adapter_on_the_reference_blend():
    """With ``devoxelize="trilinear"`` the network's output is the adapter applied to the voxel features blended by
    the dense reference weights (written from positions), for all rows and for a subset; the gradients reach every
    parameter; and the same network with ``nearest`` differs (the blend is used, not the own voxel)."""
    from ovgaussian.sparse import voxelize_points
    from ovgaussian.sparse.reference import trilinear_gather_reference

    net = OVGaussianNet(OVGaussianNetConfig(**TINY, devoxelize="trilinear", seed=2))
    means, attrs, batch = random_scenes(4, (400, 300), extent=1.0)
    voxel_features, _, inputs = net.voxel_stage(means, attrs, batch)
    vox = voxelize_points(means, inputs, batch, net.config.voxel_size, net.config.max_grid_extent,
                          lattice=net.grid_lattice)
    sites = vox.voxels.sites
    blend = trilinear_gather_reference(sites.coords, sites.batch_index, means, batch, vox.voxel_size, vox.origin)
    want = net.adapter(blend.float() @ voxel_features, inputs)
    got = net(means, attrs, batch)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    rows = torch.tensor([650, 3, 77])
    torch.testing.assert_close(net(means, attrs, batch, rows=rows), want[rows], rtol=1e-4, atol=1e-5)
    got.pow(2).sum().backward()
    for name, p in net.named_parameters():
        if name.startswith(("phi", "psi")):
            continue
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name
    nearest = OVGaussianNet(OVGaussianNetConfig(**TINY, devoxelize="nearest", seed=2))
    assert not torch.allclose(nearest(means, attrs, batch), got.detach(), atol=1e-3)


def test_devoxelize_setting_is_checked():
    with pytest.raises(ValueError, match="devoxelize"):
        OVGaussianNetConfig(**TINY, devoxelize="cubic")
