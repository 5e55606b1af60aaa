"""The OVGaussian network: voxelized Gaussians -> sparse U-Net -> voxel-to-point adapter -> s [N, 16].

Data flow of :meth:`OVGaussianNet.forward` (paper section 3, supplementary B):

1. ``attributes [N, 11]`` (see :func:`gaussian_attributes`; ``[N, 14]`` with normalized coordinates)
   are mean-pooled into voxels of ``config.voxel_size`` per scene (``ovgaussian.sparse.voxelize``).
2. A sparse U-Net in the MinkUNet34C layout maps them to voxel features ``[M, 16]``.
3. The voxel-to-point adapter fuses each Gaussian's voxel feature with its own attributes:

       m_i = MHA(Q(f_i), K(t_i), V(t_i))            f_i = voxel feature of g_i's voxel [16] (``devoxelize="trilinear"``:
                                                    a blend of the voxels around g_i, ``ovgaussian.sparse.devoxelize``)
       s_i = MLP(concat(m_i, f_i)) + f_i            MLP 27 -> 96 -> 96 -> 16 (ReLU between)

   Interpretation (the paper gives the equations and widths, not every detail): the keys and values
   are tokens made from the Gaussian's own attributes, one token per attribute group (colour,
   opacity, scales, rotation, and coordinates when enabled), each embedded by its own linear layer
   so that attention has something to choose between; the attention output is projected back to
   the attribute width (11), so that ``concat(m_i, f_i)`` has 11 + 16 = 27 channels, matching the
   first MLP width of supplementary B (16-d semantic vector + 4 + 3 + 3 + 1 attributes). The key
   projection has no bias (a bias shared by all keys cancels in the softmax and would get no
   gradient). The last MLP layer has no ReLU (its output is a residual that must be signed).
4. Decoders ``phi`` and ``psi``: MLP 16 -> 128 -> D with a ReLU after the hidden layer only (a ReLU
   on the output would confine the embeddings to the positive orthant, away from text embeddings).
"""

from __future__ import annotations

import math
from typing import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ovgaussian.model.config import NUM_GAUSSIAN_ATTRIBUTES, OVGaussianNetConfig
from ovgaussian.model.narrow_linear import narrow_linear
from ovgaussian.model.relu_mlp import relu_mlp
from ovgaussian.model.token_attention import token_attention_packed
from ovgaussian.sparse import (
    DownConv3d, SparseBatchNorm, SparseVoxels, SubmanifoldConv3d, UpConv3d, VoxelSites, voxel_geometry_features,
    voxelize_points,
)
from ovgaussian.sparse.devoxelize import PointGather, trilinear_gather
from seggaussian.core.constants import LOG_SCALE_FLOAT32_MAX, QUAT_NORM_EPS, SH_C0
from seggaussian.core.rotations import quats_to_rotmats_torch

#: Attribute groups of :func:`gaussian_attributes`, in column order (name, width).
ATTRIBUTE_GROUPS = (("colour", 3), ("opacity", 1), ("scales", 3), ("quats", 4))
#: A scene whose half-extent is below this (metres; e.g. one Gaussian) is not rescaled when its
#: coordinates are normalized (avoids dividing by zero).
COORD_NORMALIZATION_MIN_EXTENT = 1e-6
#: ``input_encoding="robust"``: log-scales are measured in voxel edges (``log(scale / voxel_size)``) and clipped to
#: this range, e^-6 (a 0.25 mm splat at 10 cm voxels) to e^2 voxels: the thin and the room-sized Gaussians a fit
#: leaves behind saturate instead of dominating the input.
ROBUST_LOG_SCALE_RANGE = (-6.0, 2.0)
#: ``input_encoding="invariant"``: scales below this (metres) count as this before their logs are taken (a zero
#: scale would give -inf; 1e-30 is far below any splat's scale and far above float32's smallest normal).
INVARIANT_MIN_SCALE = 1e-30
#: ``input_encoding="invariant"``: log-ratios of sorted scales are clipped here (e^-6: a disc 400 times thinner than
#: wide reads as one 400 times thinner), so that the flattest Gaussians of a fit saturate.
INVARIANT_LOG_RATIO_MIN = -6.0
#: ``input_encoding="robust"``: coordinates are normalized by the per-axis quantile box at these levels (not the
#: bounding box, which one floater far outside the room stretches) and clipped to +-``ROBUST_COORD_CLIP``.
ROBUST_COORD_QUANTILES = (0.01, 0.99)
ROBUST_COORD_CLIP = 1.5
#: ``pool_weighting="opacity"``: smallest weight of a Gaussian, so a voxel of only transparent Gaussians still
#: gets the mean of its inputs rather than 0/0.
POOL_MIN_WEIGHT = 1e-3
#: Per-Gaussian stages (adapter, decoders) run in chunks of this many rows under activation
#: checkpointing when gradients are recorded: a chunk's activations are recomputed in backward instead
#: of kept (about 2.7 KB per Gaussian for the adapter, 4 KB for phi + its 384-d output: 20 GB at
#: 3 x 1,000,000 Gaussians otherwise). 32,768 rows keep a chunk's [rows, 96..128] activations in L3;
#: per 1,000,000 Gaussians (one thread) forward + backward took adapter 11.8 -> 6.8 s CPU and 3D text
#: loss 7.4 -> 5.4 s CPU against 262,144 rows; 8,192 and fewer rows were slower again (per-op overhead). The training
#: step's eager paths (``ovgaussian.train.eager_rows``, ``eager_adapter``: gradients taken in the forward, no
#: recomputation) use the same chunks and thresholds; 16,384 and 65,536 rows per chunk were 2 % and 6 % slower per
#: row there.
CHECKPOINT_ROWS = 1 << 15
#: Fewer rows than this are not checkpointed at all: their activations take at most about 1.4 GB (adapter) and
#: 2 GB (3D text loss), and recomputing them in backward costs about a third of those stages' backward (measured
#: at 1,000,000 rows; a demo step, 3 scenes of 15,000 Gaussians, 1.14 -> 0.97 s CPU: benchmarks/results/train.md,
#: "Threads and checkpointing").
CHECKPOINT_MIN_ROWS = 1 << 19


def checkpointed_rows(fn, *tensors: Tensor, chunk_rows: int | None = None, min_rows: int | None = None) -> list:
    """``fn`` applied to row chunks of ``tensors`` (same rows of each), each chunk under activation
    checkpointing, when gradients are recorded and there are more than ``min_rows`` (default
    :data:`CHECKPOINT_MIN_ROWS`) and ``chunk_rows`` rows; else ``[fn(*tensors)]``. Returns the per-chunk outputs.
    ``fn`` must treat rows independently (no batch statistics)."""
    from torch.utils.checkpoint import checkpoint

    rows = tensors[0].shape[0]
    chunk_rows = CHECKPOINT_ROWS if chunk_rows is None else int(chunk_rows)
    min_rows = CHECKPOINT_MIN_ROWS if min_rows is None else int(min_rows)
    if rows <= max(chunk_rows, min_rows) or not torch.is_grad_enabled():
        return [fn(*tensors)]
    # torch.split, not slicing: the gradient of each slice view would be a zero-filled copy of the whole
    # tensor (SliceBackward), one per chunk; split's one backward concatenates the chunks' gradients.
    chunks = zip(*(torch.split(t, chunk_rows) for t in tensors))
    return [checkpoint(fn, *parts, use_reentrant=False) for parts in chunks]


def canonical_quat_sign(quats: Tensor) -> Tensor:  # [N, 4] -> [N, 4]
    """``quats`` with each row's sign chosen so that its first non-zero component is positive (``w > 0``
    unless ``w == 0``, then ``x > 0``, ...). ``q`` and ``-q`` map to bitwise the same row (negation is exact
    and ``-0.0`` counts as zero); an all-zero row stays zero."""
    nonzero = quats != 0
    first = nonzero.to(torch.int8).argmax(dim=1, keepdim=True)  # index of the first non-zero component
    leading = quats.gather(1, first)
    return torch.where(leading < 0, -quats, quats)


def gaussian_attributes(gaussians: "Mapping[str, Tensor] | object") -> Tensor:
    """``[N, 11]`` float32 network inputs, columns in this order:

    0-2 ``colour``: DC colour ``0.5 + SH_C0 * f_dc`` (not clamped);
    3 ``opacity``: ``sigmoid(opacity_logits)``;
    4-6 ``scales``: ``exp(log_scales)`` in metres (log-scales clamped at ``LOG_SCALE_FLOAT32_MAX``);
    7-10 ``quats``: unit quaternions ``w, x, y, z`` (zero-norm rows become the identity), sign-canonical
    (:func:`canonical_quat_sign`): ``q`` and ``-q``, the same rotation, give the same row. Every path into
    the network (training, ``predict``, ``bench``) builds its inputs here, so this is the one place the
    sign is fixed.

    Args:
        gaussians: a ``seggaussian.core.gaussians.Gaussians`` or the mapping of its ``to_torch()``
            (``quats [N, 4]``, ``log_scales [N, 3]``, ``opacity_logits [N]``, ``sh [N, K, 3]``).
    """
    if hasattr(gaussians, "to_torch"):
        gaussians = gaussians.to_torch()
    tensors = {}
    for name in ("quats", "log_scales", "opacity_logits", "sh"):
        if name not in gaussians:
            raise ValueError(f"gaussian_attributes: missing field {name!r}")
        t = torch.as_tensor(gaussians[name]).float()
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"gaussian_attributes: field {name!r} contains NaN or Inf")
        tensors[name] = t
    quats = tensors["quats"]
    norms = quats.norm(dim=1, keepdim=True)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], device=quats.device).expand_as(quats)
    unit = canonical_quat_sign(torch.where(norms > QUAT_NORM_EPS, quats / norms.clamp_min(QUAT_NORM_EPS), identity))
    colour = 0.5 + SH_C0 * tensors["sh"][:, 0, :]
    opacity = torch.sigmoid(tensors["opacity_logits"].reshape(-1, 1))
    scales = torch.exp(tensors["log_scales"].clamp(max=LOG_SCALE_FLOAT32_MAX))
    return torch.cat([colour, opacity, scales, unit], dim=1)


def normalized_coordinates(means: Tensor, batch_index: Tensor) -> Tensor:
    """``[N, 3]`` positions minus their scene's bounding-box centre, over its largest half-extent."""
    num_scenes = int(batch_index.max()) + 1 if means.shape[0] else 0
    idx = batch_index.long()[:, None].expand(-1, 3)
    big = torch.finfo(means.dtype).max
    lo = means.new_full((num_scenes, 3), big).scatter_reduce(0, idx, means, reduce="amin")
    hi = means.new_full((num_scenes, 3), -big).scatter_reduce(0, idx, means, reduce="amax")
    centre = 0.5 * (lo + hi)
    half = (0.5 * (hi - lo)).amax(dim=1).clamp_min(COORD_NORMALIZATION_MIN_EXTENT)
    return (means - centre[batch_index]) / half[batch_index, None]


def robust_coordinates(means: Tensor, batch_index: Tensor) -> Tensor:
    """``[N, 3]`` positions minus the centre of their scene's ``ROBUST_COORD_QUANTILES`` box (per axis), over that
    box's largest half-extent, clipped to ``+-ROBUST_COORD_CLIP``: a few floaters far outside the room move no
    other Gaussian's coordinates (a bounding box would)."""
    out = torch.empty_like(means)
    low_q, high_q = ROBUST_COORD_QUANTILES
    for scene in torch.unique(batch_index):
        rows = torch.nonzero(batch_index == scene).reshape(-1)
        pts = means[rows]
        n = pts.shape[0]
        lo = pts.kthvalue(1 + int(low_q * (n - 1)), dim=0).values
        hi = pts.kthvalue(1 + int(high_q * (n - 1)), dim=0).values
        half = (0.5 * (hi - lo)).amax().clamp_min(COORD_NORMALIZATION_MIN_EXTENT)
        out[rows] = ((pts - 0.5 * (lo + hi)) / half).clamp(-ROBUST_COORD_CLIP, ROBUST_COORD_CLIP)
    return out


def encode_attributes(attributes: Tensor, voxel_size: float) -> Tensor:
    """``input_encoding="robust"`` of the 11 physical attributes (:func:`gaussian_attributes` columns):
    colour clamped to [0, 1]; opacity as is; scales as ``log(scale / voxel_size)`` clipped to
    ``ROBUST_LOG_SCALE_RANGE`` and halved (order 1); quaternions as is."""
    colour = attributes[:, 0:3].clamp(0.0, 1.0)
    opacity = attributes[:, 3:4]
    low, high = ROBUST_LOG_SCALE_RANGE
    log_scales = torch.log(attributes[:, 4:7].clamp_min(1e-30) / voxel_size).clamp(low, high) * 0.5
    return torch.cat([colour, opacity, log_scales, attributes[:, 7:11]], dim=1)


def invariant_attributes(attributes: Tensor) -> Tensor:
    """``input_encoding="invariant"`` of the 11 physical attributes (:func:`gaussian_attributes` columns): only what
    the splat's making cannot move. Splitting a Gaussian into smaller copies (densification), subsampling, another
    Gaussian count, another metric scale or another opacity spread leave every column of every remaining Gaussian
    unchanged (the opacity still weights the voxel pooling, ``OVGaussianNet.pool_weights``):

    0-2 colour: DC colour clamped to [0, 1];
    3 a constant 1 (the opacity is no input);
    4-5 shape: ``log(s2 / s1)`` and ``log(s3 / s2)`` of the scales sorted ``s1 >= s2 >= s3``, clipped to
    ``INVARIANT_LOG_RATIO_MIN`` and halved (0, 0 for a sphere), metric size left out;
    6 planarity ``a = 1 - s3 / s2``: 0 for a sphere or a needle, towards 1 for a disc;
    7-10 the disc's normal ``n`` (the axis of the smallest scale), weighted by ``a`` so that a Gaussian without a
    thin axis gives none: ``a (3 n_z^2 - 1) / 2``, ``a (n_x^2 - n_y^2)``, ``a 2 n_x n_y``, ``a 2 |n_z| |n_xy|``.
    Each is the same for ``n`` and ``-n``, for ``q`` and ``-q``, and for every way of writing one ellipsoid (axes
    permuted with their scales); the first and last do not move under the training's rotations about z.
    """
    colour = attributes[:, 0:3].clamp(0.0, 1.0)
    constant = torch.ones_like(attributes[:, 3:4])
    log_scales = torch.log(attributes[:, 4:7].clamp_min(INVARIANT_MIN_SCALE))
    sorted_log, order = torch.sort(log_scales, dim=1, descending=True)
    shape = torch.stack([sorted_log[:, 1] - sorted_log[:, 0], sorted_log[:, 2] - sorted_log[:, 1]], dim=1)
    shape = shape.clamp(INVARIANT_LOG_RATIO_MIN, 0.0) * 0.5
    planarity = 1.0 - torch.exp(sorted_log[:, 2] - sorted_log[:, 1])  # [N] in [0, 1)
    rotmats = quats_to_rotmats_torch(attributes[:, 7:11])  # columns: the Gaussian's axes in the world
    thinnest = order[:, 2].reshape(-1, 1, 1).expand(-1, 3, 1)
    normal = rotmats.gather(2, thinnest).reshape(-1, 3)
    nx, ny, nz = normal.unbind(dim=1)
    horizontal = torch.sqrt((nx * nx + ny * ny).clamp_min(0.0))
    orientation = torch.stack([0.5 * (3.0 * nz * nz - 1.0), nx * nx - ny * ny, 2.0 * nx * ny,
                               2.0 * nz.abs() * horizontal], dim=1) * planarity[:, None]
    return torch.cat([colour, constant, shape, planarity[:, None], orientation], dim=1)


def _relu(x: SparseVoxels) -> SparseVoxels:
    return SparseVoxels(torch.relu(x.features), x.sites)


class ConvBnRelu(nn.Module):
    """Submanifold conv (or down conv), batch norm, ReLU."""

    def __init__(self, conv: nn.Module, out_channels: int) -> None:
        super().__init__()
        self.conv, self.norm = conv, SparseBatchNorm(out_channels)

    def forward(self, x: SparseVoxels, *args) -> SparseVoxels:
        return _relu(self.norm(self.conv(x, *args)))


class BasicBlock(nn.Module):
    """Residual block: conv3-BN-ReLU-conv3-BN (+ 1x1 conv-BN shortcut when widths differ), ReLU."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv1, self.norm1 = SubmanifoldConv3d(in_channels, out_channels, 3), SparseBatchNorm(out_channels)
        self.conv2, self.norm2 = SubmanifoldConv3d(out_channels, out_channels, 3), SparseBatchNorm(out_channels)
        self.shortcut = (
            nn.Sequential(SubmanifoldConv3d(in_channels, out_channels, 1), SparseBatchNorm(out_channels))
            if in_channels != out_channels else None
        )

    def forward(self, x: SparseVoxels) -> SparseVoxels:
        y = self.norm2(self.conv2(_relu(self.norm1(self.conv1(x)))))
        residual = self.shortcut(x) if self.shortcut is not None else x
        return SparseVoxels(torch.relu(y.features + residual.features), x.sites)


def _blocks(in_channels: int, out_channels: int, count: int) -> nn.Sequential:
    layers = []
    for _ in range(count):
        layers.append(BasicBlock(in_channels, out_channels))
        in_channels = out_channels
    return nn.Sequential(*layers)


class SparseUNet(nn.Module):
    """MinkUNet34C layout: stem, 4 x (down conv + blocks), 4 x (up conv + skip concat + blocks), linear.

    Encoder stage i: ``DownConv(prev -> prev)``-BN-ReLU, then ``blocks[i]`` BasicBlocks to ``widths[i]``.
    Decoder stage j: ``UpConv(prev -> widths[4+j])``-BN-ReLU, concat with the encoder output of the same
    level (stem output for the last), ``blocks[4+j]`` BasicBlocks to ``widths[4+j]``.
    """

    def __init__(self, in_channels: int, out_channels: int, config: OVGaussianNetConfig) -> None:
        super().__init__()
        w, b = config.widths, config.blocks
        self.stem = ConvBnRelu(SubmanifoldConv3d(in_channels, config.stem_width, config.stem_kernel_size), config.stem_width)
        skip_widths = [config.stem_width]
        self.down, self.encoder = nn.ModuleList(), nn.ModuleList()
        prev = config.stem_width
        for i in range(4):
            self.down.append(ConvBnRelu(DownConv3d(prev, prev), prev))
            self.encoder.append(_blocks(prev, w[i], b[i]) if b[i] else nn.Sequential())
            prev = w[i] if b[i] else prev
            skip_widths.append(prev)
        self.up, self.decoder = nn.ModuleList(), nn.ModuleList()
        for j in range(4):
            self.up.append(ConvBnRelu(UpConv3d(prev, w[4 + j]), w[4 + j]))
            cat = w[4 + j] + skip_widths[3 - j]
            self.decoder.append(_blocks(cat, w[4 + j], b[4 + j]) if b[4 + j] else nn.Sequential())
            prev = w[4 + j] if b[4 + j] else cat
        self.head = nn.Linear(prev, out_channels)

    def forward(self, x: SparseVoxels) -> Tensor:
        """``[M, out_channels]`` features on the input sites."""
        x = self.stem(x)
        skips = [x]
        for down, blocks in zip(self.down, self.encoder):
            x = blocks(down(x))
            skips.append(x)
        for j, (up, blocks) in enumerate(zip(self.up, self.decoder)):
            skip = skips[3 - j]
            x = up(x, skip.sites)
            x = blocks(SparseVoxels(torch.cat([x.features, skip.features], dim=1), skip.sites))
        return self.head(x.features)


class VoxelToPointAdapter(nn.Module):
    """Attention from a Gaussian's voxel feature (query) to its attribute tokens (keys, values), then
    ``s = MLP(concat(m, f)) + f`` (module docstring: interpretation of the paper)."""

    def __init__(self, config: OVGaussianNetConfig) -> None:
        super().__init__()
        groups = [w for _, w in ATTRIBUTE_GROUPS] + ([3] if config.use_coordinates else [])
        self.group_widths = tuple(groups)
        a, s = config.adapter_attention_width, config.semantic_width
        self.heads = config.adapter_heads
        self.token_embed = nn.ModuleList(nn.Linear(g, a) for g in groups)
        self.query = nn.Linear(s, a)
        self.key = nn.Linear(a, a, bias=False)
        self.value = nn.Linear(a, a)
        self.out = nn.Linear(a, config.num_attributes)
        widths = [config.num_attributes + s, *config.adapter_hidden, s]
        layers: list[nn.Module] = []
        for i in range(len(widths) - 1):
            layers.append(nn.Linear(widths[i], widths[i + 1]))
            if i < len(widths) - 2:
                layers.append(nn.ReLU())
        self.mlp = nn.Sequential(*layers)

    def forward(self, voxel_features: Tensor, attributes: Tensor) -> Tensor:
        """``voxel_features [N, S]`` (per Gaussian), ``attributes [N, A]`` -> semantic ``[N, S]``.

        Same function as :meth:`forward_reference`, arranged for speed: the per-group token embeddings
        are one GEMM by their block-diagonal weight, and the attention over the ``T`` tokens (``d = 4``
        channels per head) is one loop over the rows, forward and backward
        (``ovgaussian.model.token_attention``), instead of ``einsum``, which becomes millions of tiny batched
        matmuls plus layout copies (elementwise torch products were 1.1-1.4x less CPU than ``einsum`` per 1,000,000
        Gaussians, ``benchmarks/results/paper_scale.md``; the row loop in benchmarks/results/train.md). The output
        projection ``out`` is folded into the MLP's first layer (below), so ``m`` is not formed.
        """
        n = attributes.shape[0]
        weight = torch.block_diag(*[embed.weight for embed in self.token_embed])  # [T * A_tok, A]
        bias = torch.cat([embed.bias for embed in self.token_embed])  # [T * A_tok]
        t, h = len(self.token_embed), self.heads
        tokens = narrow_linear(attributes, weight, bias).view(n, t, weight.shape[0] // t)  # [N, T, A_tok]
        d = tokens.shape[2] // h
        q = self.query(voxel_features).view(n, h, d)  # [N, H, d]
        # keys and values by one product, both without bias: [N * T, A_tok] x [A_tok, 2 A_tok] -> [N, T, 2, H, d]. The
        # key has none; the value's, b_v, is added after the attention: each row's weights over its tokens sum to 1,
        # so the attended row with it is the row without it plus b_v (folded into the MLP's bias below).
        kv_weight = torch.cat([self.key.weight, self.value.weight])
        kv = (tokens.reshape(n * t, tokens.shape[2]) @ kv_weight.T).view(n, t, 2, h, d)
        attended = token_attention_packed(q, kv).reshape(n, h * d)  # [N, H * d], without b_v
        # The output projection folded into the MLP's first layer: W1 [m | f] with m = W_out (a + b_v) + b_out is
        # (W1_m W_out) a + W1_f f + (b1 + W1_m b_out + W1_m W_out b_v). m is never formed, and the first layer reads
        # [a | f], 16 + 16 = 32 columns: MKL's products with a 27-column side ran at half the speed of 32
        # (32,768 rows, 2 threads).
        first, width = self.mlp[0], self.out.out_features
        w_m = first.weight[:, :width]
        w_a = w_m @ self.out.weight  # [hidden, H * d]
        folded = (torch.cat([w_a, first.weight[:, width:]], dim=1),
                  torch.addmv(torch.addmv(first.bias, w_m, self.out.bias), w_a, self.value.bias))
        return relu_mlp(self.mlp, torch.cat([attended, voxel_features], dim=1), first=folded) + voxel_features

    def forward_reference(self, voxel_features: Tensor, attributes: Tensor) -> Tensor:
        """:meth:`forward` written plainly (one embedding per group, ``einsum`` attention): the reference."""
        n = attributes.shape[0]
        chunks = torch.split(attributes, self.group_widths, dim=1)
        tokens = torch.stack([embed(c) for embed, c in zip(self.token_embed, chunks)], dim=1)  # [N, T, A]
        h, t = self.heads, tokens.shape[1]
        d = tokens.shape[2] // h
        q = self.query(voxel_features).reshape(n, h, d)  # [N, H, d]
        k = self.key(tokens).reshape(n, t, h, d)  # [N, T, H, d]
        v = self.value(tokens).reshape(n, t, h, d)
        logits = torch.einsum("nhd,nthd->nht", q, k) / math.sqrt(d)
        attended = torch.einsum("nht,nthd->nhd", torch.softmax(logits, dim=-1), v).reshape(n, h * d)
        m = self.out(attended)
        return self.mlp(torch.cat([m, voxel_features], dim=1)) + voxel_features


def _decoder(config: OVGaussianNetConfig) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(config.semantic_width, config.decoder_hidden), nn.ReLU(),
        nn.Linear(config.decoder_hidden, config.embedding_width),
    )


class OVGaussianNet(nn.Module):
    """Per-Gaussian semantic vectors from Gaussian positions and attributes, plus decoders phi, psi."""

    def __init__(self, config: OVGaussianNetConfig | None = None) -> None:
        super().__init__()
        config = config or OVGaussianNetConfig()
        self.config = config
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            self.backbone = SparseUNet(config.backbone_inputs, config.semantic_width, config)
            if config.use_adapter:
                self.adapter = VoxelToPointAdapter(config)
            else:
                self.point_head = nn.Linear(config.semantic_width, config.semantic_width)
            self.phi = _decoder(config)
            self.psi = _decoder(config)

    def prepare_inputs(self, means: Tensor, attributes: Tensor, batch_index: Tensor) -> Tensor:
        """Validate and return the ``[N, num_attributes]`` network inputs (coordinates appended if enabled)."""
        n = means.shape[0]
        if means.ndim != 2 or means.shape[1] != 3:
            raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
        if batch_index.shape != (n,):
            raise ValueError(f"batch_index must be [{n}], got {tuple(batch_index.shape)}")
        if attributes.ndim != 2 or attributes.shape[0] != n:
            raise ValueError(f"attributes must be [{n}, {self.config.num_attributes}], got {tuple(attributes.shape)}")
        if not bool(torch.isfinite(means).all()):
            raise ValueError("means contain NaN or Inf")
        if not bool(torch.isfinite(attributes).all()):
            raise ValueError("attributes contain NaN or Inf")
        width = attributes.shape[1]
        robust_coordinates_wanted = self.config.input_encoding != "raw"  # robust and invariant share them
        if width == NUM_GAUSSIAN_ATTRIBUTES and self.config.input_encoding == "robust":
            attributes = encode_attributes(attributes, self.config.voxel_size)
        elif width == NUM_GAUSSIAN_ATTRIBUTES and self.config.input_encoding == "invariant":
            attributes = invariant_attributes(attributes)
        if self.config.use_coordinates and width == NUM_GAUSSIAN_ATTRIBUTES:
            coordinates = (robust_coordinates if robust_coordinates_wanted else normalized_coordinates)(
                means.detach(), batch_index)
            attributes = torch.cat([attributes, coordinates], dim=1)
        elif width != self.config.num_attributes:
            raise ValueError(f"attributes have {width} columns, the config expects {self.config.num_attributes}")
        return attributes

    @property
    def grid_lattice(self) -> int | None:
        """Voxels between the grid origins allowed (``grid_anchor="lattice"``): the stride of the U-Net's coarsest
        level, so that every level's grid keeps its place; None for ``grid_anchor="min"``."""
        return 2 ** len(self.backbone.down) if self.config.grid_anchor == "lattice" else None  # stride-2 levels

    def pool_weights(self, attributes: Tensor) -> "Tensor | None":
        """``[N]`` weights of the Gaussians in their voxel's pooled input (``pool_weighting="opacity"``: the
        opacity, column 3 of the attributes as given to the network, before encoding, floored at
        ``POOL_MIN_WEIGHT``), or None for a plain mean."""
        if self.config.pool_weighting == "mean":
            return None
        return attributes[:, 3].detach().clamp_min(POOL_MIN_WEIGHT)

    def voxel_stage(self, means: Tensor, attributes: Tensor,
                    batch_index: Tensor) -> tuple[Tensor, PointGather, Tensor]:
        """The stage before the per-Gaussian one: ``(voxel_features [M, S], the Gaussians' PointGather (rows
        [N, K]), network inputs [N, A])`` (inputs checked and encoded, voxelized, the sparse U-Net; the gather is
        ``config.devoxelize``'s)."""
        weights = self.pool_weights(attributes)  # the given opacity: the invariant encoding does not keep it
        attributes = self.prepare_inputs(means, attributes, batch_index)
        vox = voxelize_points(means, attributes, batch_index, self.config.voxel_size, self.config.max_grid_extent,
                              weights=weights, lattice=self.grid_lattice)
        voxels = vox.voxels
        if self.config.voxel_geometry:
            geometry = voxel_geometry_features(vox.point_offsets, vox.point_to_voxel, len(voxels.sites), weights)
            voxels = voxels.replace(torch.cat([voxels.features, geometry.to(voxels.features.dtype)], dim=1))
        voxel_features = self.backbone(voxels)  # first: it builds the sites' kernel maps the trilinear gather reads
        if self.config.devoxelize == "trilinear":
            point_gather = trilinear_gather(vox.voxels.sites, vox.point_to_voxel, vox.point_offsets)
        else:
            point_gather = PointGather.nearest(vox.point_to_voxel)
        return voxel_features, point_gather, attributes

    def forward(
        self,
        means: Tensor,  # [N, 3] world positions, metres
        attributes: Tensor,  # [N, 11] from gaussian_attributes (or [N, 14] with coordinates appended)
        batch_index: Tensor,  # [N] scene of each Gaussian, 0..B-1
        rows: "Tensor | None" = None,  # [R] int64 Gaussians whose vectors are wanted; None: all
    ) -> Tensor:
        """Semantic vectors ``[N, semantic_width]`` (``[R, semantic_width]`` of ``rows``, in their order: the
        voxels still pool every Gaussian, only the per-Gaussian stage is restricted)."""
        voxel_features, point_gather, attributes = self.voxel_stage(means, attributes, batch_index)
        if rows is not None:
            point_gather, attributes = point_gather.take(rows), attributes[rows]
        per_gaussian = point_gather.gather(voxel_features)  # [N or R, S]
        if self.config.use_adapter:
            return torch.cat(checkpointed_rows(self.adapter, per_gaussian, attributes), dim=0)
        return self.point_head(per_gaussian)


__all__ = [
    "ATTRIBUTE_GROUPS", "OVGaussianNet", "OVGaussianNetConfig", "SparseUNet", "VoxelToPointAdapter",
    "VoxelSites", "canonical_quat_sign", "encode_attributes", "gaussian_attributes", "invariant_attributes",
    "normalized_coordinates",
    "robust_coordinates",
]
