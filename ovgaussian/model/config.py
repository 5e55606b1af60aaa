"""Configuration of the OVGaussian network (backbone, adapter, decoders). Data only, no torch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: MinkUNet34C (MinkowskiEngine / Pointcept): encoder widths 32, 64, 128, 256, decoder 256, 128, 96, 96.
MINKUNET34C_WIDTHS = (32, 64, 128, 256, 256, 128, 96, 96)
#: MinkUNet34C BasicBlocks per stage: encoder 2, 3, 4, 6, decoder 2, 2, 2, 2.
MINKUNET34C_BLOCKS = (2, 3, 4, 6, 2, 2, 2, 2)
#: A quarter of the MinkUNet34C widths, for tests and CPU training.
SLIM_WIDTHS = tuple(w // 4 for w in MINKUNET34C_WIDTHS)
#: Number of per-Gaussian attributes from ``gaussian_attributes``: colour 3, opacity 1, scales 3, quats 4.
NUM_GAUSSIAN_ATTRIBUTES = 11
#: Voxel inputs added by ``voxel_geometry``: the centres' mean offset (3) and covariance (6) inside the voxel.
VOXEL_GEOMETRY_WIDTH = 9


@dataclass(frozen=True)
class OVGaussianNetConfig:
    """Shape and switches of :class:`ovgaussian.model.network.OVGaussianNet`."""

    widths: tuple[int, ...] = MINKUNET34C_WIDTHS
    """Output channels of the 8 U-Net stages (4 encoder, 4 decoder); default MinkUNet34C."""
    blocks: tuple[int, ...] = MINKUNET34C_BLOCKS
    """Residual BasicBlocks per stage (4 encoder, 4 decoder); default MinkUNet34C."""
    stem_width: int = 32
    """Channels of the stem convolution (MinkUNet34C INIT_DIM = 32)."""
    stem_kernel_size: int = 5
    """Kernel of the stem submanifold convolution (MinkUNet34C: 5; 3 is cheaper)."""
    voxel_size: float = 0.05
    """Voxel edge in metres at the finest level (ScanNet-style 5 cm)."""
    max_grid_extent: int = 4096
    """Adaptive cap: a scene wider than this many voxels on some axis gets a larger voxel
    (extent / (max_grid_extent - 1)) instead of overflowing the key range; 4096 x 5 cm = 205 m."""
    grid_anchor: Literal["min", "lattice"] = "min"
    """Where the voxel grid lies (``ovgaussian.sparse.voxelize_points``): ``min`` = from the scene's minimum corner
    (one floater outside the room then moves every voxel boundary); ``lattice`` = on multiples of 16 voxels (the
    coarsest level's stride) in the frame of the positions given (``predict`` and ``bench`` recentre a scene by a
    multiple of it, so two splats of one room share every level's grid)."""
    surface_radius: float = 0.0
    """Reach (metres) of the projection that places each Gaussian on its splat's own surface before the network
    voxelizes a splat it labels (predict, bench, the viewer: ``ovgaussian.model.surface``; the thick shells a
    photometric fit leaves about its surfaces collapse onto them, a thin surface barely moves); training shows the
    splats as they are. 0 voxelizes the centres as they are."""
    use_coordinates: bool = False
    """Append 3 normalized coordinates (position minus scene centre, divided by the scene's
    half-extent, so in [-1, 1]) to the 11 attributes: backbone and adapter see 14 inputs."""
    input_encoding: Literal["raw", "robust", "invariant"] = "robust"
    """How the 11 physical attributes (and the coordinates) are fed to the network. ``raw``: as
    ``gaussian_attributes`` returns them (scales in metres, colour unclamped, coordinates over the bounding box), the
    encoding of runs trained before fitted splats were supported. ``robust``: what a fitted splat's heavy tails
    cannot throw off: colour clamped to [0, 1], log-scales relative to the voxel edge and clipped, coordinates over
    the 1 %..99 % quantile box of the scene and clipped to [-1.5, 1.5] (floaters far outside the room move nothing).
    ``invariant``: what the splat's making cannot move (``network.invariant_attributes``): colour clamped, the scales'
    shape without their size, the normal of flat Gaussians weighted by their flatness, no opacity (it only weights the
    pooling); coordinates as ``robust``. Densifying, subsampling, rescaling or reweighting a splat leaves each
    Gaussian's inputs unchanged."""
    pool_weighting: Literal["mean", "opacity"] = "opacity"
    """How a voxel's input features are pooled from its Gaussians: ``mean`` (each Gaussian counts once) or
    ``opacity`` (weighted by opacity, so the faint Gaussians a fit leaves everywhere count little)."""
    devoxelize: Literal["nearest", "trilinear"] = "nearest"
    """How a Gaussian reads the backbone's voxel features: ``nearest`` (its own voxel's row: every Gaussian of a voxel
    gets the same) or ``trilinear`` (a blend of the occupied voxels whose centres surround it, weighted by its
    position: ``ovgaussian.sparse.devoxelize``)."""
    voxel_geometry: bool = False
    """Append to each voxel's pooled inputs how its Gaussians' centres lie inside it: their mean offset from the voxel
    centre (3, in voxel edges, times 2) and their covariance (6: xx, yy, zz, xy, xz, yz, in voxel edges squared, times
    12), weighted as the pooling (``voxel_geometry_features``). A surface through the voxel shows as a flat covariance
    whose thin axis is its normal, which fitted Gaussians' own rotations do not give (the backbone sees
    ``num_attributes + 9`` inputs; the adapter's are unchanged)."""
    semantic_width: int = 16
    """Width of the per-Gaussian semantic vector s (paper: 16); also the backbone's output width."""
    use_adapter: bool = True
    """Voxel-to-point adapter (paper section 3); False: s = linear(voxel feature of the Gaussian)."""
    adapter_attention_width: int = 16
    """Width of the adapter's query/key/value projections."""
    adapter_heads: int = 4
    """Attention heads of the adapter (adapter_attention_width must be divisible by it)."""
    adapter_hidden: tuple[int, ...] = (96, 96)
    """Hidden widths of the adapter MLP (paper: 27 -> 96 -> 96 -> 16)."""
    decoder_hidden: int = 128
    """Hidden width of the decoders phi and psi (paper: 16 -> 128 -> D)."""
    embedding_width: int = 512
    """D: width of the text / teacher embeddings that phi and psi map into (paper: 512, CLIP)."""
    seed: int = 0
    """Seed of the parameter initialization (the same seed gives the same network)."""

    def __post_init__(self) -> None:
        if len(self.widths) != 8 or len(self.blocks) != 8:
            raise ValueError(f"widths and blocks need 8 stages, got {len(self.widths)} and {len(self.blocks)}")
        if min(self.widths) < 1 or min(self.blocks) < 0 or self.stem_width < 1:
            raise ValueError("widths and stem_width must be positive, blocks non-negative")
        if self.stem_kernel_size not in (1, 3, 5, 7):
            raise ValueError(f"stem_kernel_size must be 1, 3, 5 or 7, got {self.stem_kernel_size}")
        if not self.voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {self.voxel_size}")
        if self.input_encoding not in ("raw", "robust", "invariant"):
            raise ValueError(f"input_encoding must be 'raw', 'robust' or 'invariant', got {self.input_encoding!r}")
        if self.pool_weighting not in ("mean", "opacity"):
            raise ValueError(f"pool_weighting must be 'mean' or 'opacity', got {self.pool_weighting!r}")
        if not self.surface_radius >= 0:
            raise ValueError(f"surface_radius must be >= 0, got {self.surface_radius}")
        if self.grid_anchor not in ("min", "lattice"):
            raise ValueError(f"grid_anchor must be 'min' or 'lattice', got {self.grid_anchor!r}")
        if self.devoxelize not in ("nearest", "trilinear"):
            raise ValueError(f"devoxelize must be 'nearest' or 'trilinear', got {self.devoxelize!r}")
        if self.adapter_attention_width % self.adapter_heads:
            raise ValueError("adapter_attention_width must be divisible by adapter_heads")

    @property
    def num_attributes(self) -> int:
        """Per-Gaussian input width: 11, or 14 with coordinates."""
        return NUM_GAUSSIAN_ATTRIBUTES + (3 if self.use_coordinates else 0)

    @property
    def backbone_inputs(self) -> int:
        """Input width of the sparse U-Net: the pooled attributes, plus 9 with ``voxel_geometry``."""
        return self.num_attributes + (VOXEL_GEOMETRY_WIDTH if self.voxel_geometry else 0)

    @classmethod
    def slim(cls, **overrides) -> "OVGaussianNetConfig":
        """A quarter of the MinkUNet34C widths with a 3^3 stem (tests, CPU training)."""
        fields = dict(widths=SLIM_WIDTHS, stem_width=8, stem_kernel_size=3)
        fields.update(overrides)
        return cls(**fields)


#: Values of the fields added after runs were first saved, for a run folder whose config lacks them: such a run
#: was trained with these behaviours (``ovgaussian.run.checkpoint`` loads it with them, not with today's defaults).
LEGACY_FIELD_VALUES = {"input_encoding": "raw", "pool_weighting": "mean", "devoxelize": "nearest",
                       "voxel_geometry": False, "grid_anchor": "min"}
