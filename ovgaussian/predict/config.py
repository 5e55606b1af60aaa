"""Configuration of ``ovgaussian predict`` and the rendering defaults it shares with ``ovgaussian bench``: no code."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

#: Default accumulated-alpha threshold below which a rendered pixel has no prediction (IGNORE);
#: the same value the label maps of the dataset are rendered with (seggaussian.render.render_label_maps).
DEFAULT_MIN_ALPHA = 0.5
#: Image rows rendered at once by the 2D evaluation: 64 x 876 pixels x 16 contributors x 12 bytes ~ 11 MB
#: of blend weights at the paper's 584x876, instead of 98 MB for the whole view.
DEFAULT_BAND_ROWS = 64


@dataclass(frozen=True)
class PredictConfig:
    """One open-vocabulary query of a scene."""

    run: Path = Path("run")
    """Run folder of ``ovgaussian train``."""
    checkpoint: Optional[Path] = None
    """A checkpoint folder (RUN/checkpoints/epoch-XXXX); None takes the run's latest."""
    ensemble_runs: tuple[Path, ...] = ()
    """More runs that label the scene with ``run`` as one ensemble, their class scores averaged
    (ovgaussian.predict.ensemble), as ``ovgaussian bench --ensemble-run`` scores them; each at its latest
    checkpoint. Not with stacking_gamma."""
    vocabulary: tuple[str, ...] = ()
    """Free-text class names the Gaussians are labelled with (label i = vocabulary[i])."""
    prompt_ensemble: bool = False
    """Open vocabulary: embed each class name under several prompt templates, averaged (ovgaussian.text.prompt_ensemble)."""
    stacking_gamma: float = 0.0
    """Open vocabulary, calibrated stacking: subtract this from the scores of the names the run was trained on (take the gamma that `ovgaussian bench --stacking-run` records); 0: plain argmax."""
    class_offsets: Optional[Path] = None
    """A report of `ovgaussian bench --class-offsets` (its JSON): the per-class score offsets it records are added to
    the scores of the same class names (other names: 0), so predictions match what that bench scored. The runs must be
    the checkpoints that bench scored (--run and each --ensemble-run; compared by the weights' sha256 the report
    records). Not with stacking_gamma."""
    faint_neighbours: int = 0
    """Blend each Gaussian's semantic vector with those of its this many nearest Gaussians (itself included), by its
    opacity: an opaque one keeps its own, a faint one takes mostly its opaque neighbours' (ovgaussian.predict.
    faint_blend); 0 or 1: off. With class_offsets it must be the value that bench scored with (another is
    refused: the offsets were fitted on its scores)."""
    colour_mode: Literal["f_dc", "rgb", "both"] = "both"
    """Where the per-class colours go: overwrite the SH colour (f_dc, f_rest zeroed), add uchar
    red/green/blue properties, or both."""
    color_by: Literal["semantic", "none"] = "semantic"
    """``semantic``: paint each Gaussian in the fixed palette colour of its class (seggaussian.labels.palette) and
    write a legend (JSON + PNG) beside the output; ``none``: keep the scene's colours, add only the labels."""
    output_format: Optional[Literal["ply", "compressed_ply", "splat", "spz", "ksplat", "gltf"]] = None
    """Format of the output file; None takes it from the name (.compressed.ply, .splat, .spz, .ksplat, .glb/.gltf,
    else PLY). PLY and glTF keep the ``semantic`` labels; the other formats carry the class colours alone."""
    spz_version: Literal[2, 3, 4] = 3
    """SPZ version written when the output is SPZ (3: the newest the web viewers read; 4 writes zstd streams)."""
    min_alpha: float = DEFAULT_MIN_ALPHA
    """Pixels of label-map PNGs whose accumulated alpha is below this are written as IGNORE (0 in the colour PNG)."""
    blend_top_k: int = 16
    """Contributors kept per pixel when rendering label maps."""
    on_invalid: Literal["error", "drop", "repair"] = "error"
    """What to do with invalid Gaussians in the input PLY (see seggaussian.io.ply.reader.read_gaussians_ply)."""
    chunk_rows: int = 65536
    """Gaussians or pixels classified at once."""
    band_rows: int = DEFAULT_BAND_ROWS
    """Image rows of a label map whose blend weights are computed, rendered and classified at once."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Device of the model."""
