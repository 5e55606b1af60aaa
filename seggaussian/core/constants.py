"""Every convention and numerical constant of the toolkit, defined once.

See ``data_specs/CONVENTIONS.md`` for the prose version of these rules.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

#: Folder holding the data files read by code (class lists, vocabularies, mappings, schemas): the
#: repository's top-level ``data_specs/``, installed as the package ``seggaussian.data_specs`` so that
#: an editable install and a wheel both find it.
DATA_SPECS_DIR = Path(str(files("seggaussian.data_specs")))

#: The single ignore label, used for Gaussians, points, label maps (uint16 PNG) and losses
#: (``ignore_index``). 65535 fits a 16-bit PNG and an int32 PLY property, and never collides
#: with a class id (0..99) or a realistic instance id.
IGNORE_LABEL = 65535

#: Zeroth-order real spherical-harmonic constant: colour = 0.5 + SH_C0 * f_dc.
SH_C0 = 0.28209479177387814
#: Normalization constants of the real SH bands 1..3 as the 3DGS reference evaluates them, signs included
#: (band 1 is ``-SH_C1 y, SH_C1 z, -SH_C1 x``); the basis itself is ``seggaussian.render.sh.evaluate_sh``.
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)
#: Highest SH degree the toolkit reads and renders.
MAX_SH_DEGREE = 3

# --- rasterization constants of the 3DGS reference (Kerbl et al. 2023) -----------------------
#: Added to the diagonal of every projected 2D covariance (pixels^2): a low-pass filter
#: that keeps sub-pixel Gaussians visible and the 2D covariance invertible.
COV2D_DILATION = 0.3
#: Upper clamp of a Gaussian's alpha at a pixel; keeps transmittance strictly positive so that
#: the backward pass can divide by (1 - alpha).
ALPHA_MAX = 0.99
#: Contributions with alpha below this are skipped (they change an 8-bit image by < 1 level).
ALPHA_MIN = 1.0 / 255.0
#: A pixel stops blending once its transmittance would fall below this.
TRANSMITTANCE_MIN = 1e-4
#: Gaussians closer to the camera than this (metres, camera z) are culled.
NEAR_PLANE = 0.01
#: Gaussians farther than this (metres, camera z) are culled.
FAR_PLANE = 1e10
#: Tile edge in pixels.
TILE_SIZE = 16
#: Radius of a projected Gaussian in standard deviations.
RADIUS_SIGMAS = 3.0
#: The Jacobian of the projection is evaluated with the Gaussian's image-plane position clamped to
#: this multiple of the half field of view (3DGS reference: 1.3), for Gaussians far off screen.
FOV_CLAMP = 1.3

# --- numerical guards ----------------------------------------------------------------------
#: Quaternions with a norm below this cannot be normalized (rotation undefined).
QUAT_NORM_EPS = 1e-12
#: exp(log_scale) overflows float32 above this (log(3.4e38) ~ 88.72).
LOG_SCALE_FLOAT32_MAX = 88.0
#: Opacity logits beyond +-this saturate float32 sigmoid to exactly 0 or 1.
OPACITY_LOGIT_SATURATION = 17.0

# --- benchmark classes ---------------------------------------------------------------------
#: The four classes never supervised in training (paper, section 4).
UNSEEN_CLASSES = ("curtain", "bookshelf", "sofa", "bed")


def read_class_names(path: Path | None = None) -> tuple[str, ...]:
    """ScanNet++ benchmark classes in ``top100.txt`` order; class id = index (0 = wall)."""
    path = path or DATA_SPECS_DIR / "top100.txt"
    names = tuple(line.strip() for line in path.read_text().splitlines() if line.strip())
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: duplicate class names")
    return names
