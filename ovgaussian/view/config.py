"""Configuration of ``ovgaussian view``: one frozen dataclass, no code."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

from ovgaussian.view.relevancy import CANONICAL_NEGATIVES, DEFAULT_THRESHOLD
from seggaussian.frames.frame_config import FrameConfig

#: Address the viewer binds by default: this machine only (``--host`` opens it to others deliberately).
DEFAULT_HOST = "127.0.0.1"
#: Port the viewer asks for by default (viser takes the next free one when it is busy).
DEFAULT_PORT = 8080

#: The viewer's colour modes, in the order of its dropdown.
MODES = ("rgb", "semantic", "instance", "predicted", "query")


@dataclass(frozen=True)
class ViewConfig:
    """One run of the viewer (or one ``--export``)."""

    scene: Optional[Path] = None
    """Splat file to view (3DGS PLY, compressed PLY, .splat, SPZ, .ksplat or glTF); optional with --dataset/--scene."""
    run: Optional[Path] = None
    """Run folder of ``ovgaussian train``: enables the predicted-labels and query modes (none: RGB and ground truth only)."""
    checkpoint: Optional[Path] = None
    """A checkpoint folder (RUN/checkpoints/epoch-XXXX); None takes the run's latest."""
    dataset: Optional[Path] = None
    """Dataset folder of ``seggaussian build`` holding the scene's ground-truth semantic and instance labels."""
    scene_id: Optional[str] = None
    """Scene id in --dataset (its Gaussians are shown when no SCENE file is given; else they must match SCENE's)."""
    cameras: Optional[Path] = None
    """JSON cameras file (``ovgaussian predict --cameras``'s format, in the scene's frame): the viewer opens at one
    and draws them all as clickable frustums. None: a dataset scene's view cameras; a bare splat opens at its centre."""
    vocabulary: tuple[str, ...] = ()
    """Class names of the predicted-labels mode (comma-separated); empty: the run's training vocabulary."""
    queries: str = ""
    """Free-text query to start with (comma-separated queries: each Gaussian goes to the most relevant one)."""
    mode: Optional[Literal["rgb", "semantic", "instance", "predicted", "query"]] = None
    """Colour mode to start with; None: query when --query is given, else rgb."""
    threshold: float = DEFAULT_THRESHOLD
    """Relevancy threshold of the query mode: Gaussians below it are greyed. The relevancy is calibrated (the query's
    probability against the vocabulary and the negatives, at its class's operating point fitted on the run's train
    rooms), so the default suits every phrase; the slider overrides."""
    calibrate: bool = True
    """Fit each vocabulary name's relevancy offset on the run's train rooms (once; cached in the run folder as
    relevancy_calibration.json). Off, or when those rooms cannot be read: every offset is 0."""
    negatives: tuple[str, ...] = CANONICAL_NEGATIVES
    """Canonical negative phrases, competitors of every query beside the vocabulary (LERF's: object, things, stuff,
    texture)."""
    host: str = DEFAULT_HOST
    """Address to bind: 127.0.0.1 (this machine only) by default; 0.0.0.0 opens the viewer to the network."""
    port: int = DEFAULT_PORT
    """Port to serve on (the next free one is taken when it is busy)."""
    export: Optional[Path] = None
    """Write the scene, coloured as --mode/--query say, to this file and exit: .html (self-contained page of
    viser's client with the scene embedded) or .viser (viser's scene recording)."""
    frame: FrameConfig = field(default_factory=FrameConfig)
    """The splat file's frame (``--transform``, ``--from-frame``), applied on reading."""
    on_invalid: Literal["error", "drop", "repair"] = "error"
    """What to do with invalid Gaussians in the input file (see seggaussian.io.ply.reader.read_gaussians_ply)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Device of the model (the scores are computed on the CPU)."""
