"""Open-vocabulary query of a scene: label every Gaussian against free-text class names.

Flow: read a 3DGS PLY -> the trained network gives a semantic vector s per Gaussian -> phi(s) is
compared (cosine) with the text embeddings of the vocabulary -> label = argmax. The labelled scene is
written as a PLY with an int ``semantic`` property (index into the vocabulary) and per-class colours
(in ``f_dc`` with ``f_rest`` zeroed, and/or as uchar ``red, green, blue``), so any 3DGS or point-cloud
viewer shows the segmentation. For given cameras, label maps are rendered with the same M = W S path
as the benchmark (semantic vectors blended, then classified) and written as PNGs.

:class:`ModelPredictor` is also what ``ovgaussian bench`` scores.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple, Sequence

import cv2
import numpy as np
import torch

from ovgaussian.openvocab.calibration import stack_scores
from ovgaussian.openvocab.class_offsets import offsets_checkpoints, offsets_faint_neighbours, read_class_offsets
from ovgaussian.run.checkpoint import load_trained_model, weights_sha256
from ovgaussian.run.devices import resolve_device
from ovgaussian.model.network import gaussian_attributes
from ovgaussian.model.surface import surface_positions
from ovgaussian.predict.config import PredictConfig
from ovgaussian.predict.ensemble import EnsemblePredictor
from ovgaussian.predict.faint_blend import faint_blend
from ovgaussian.text.prompt_ensemble import PROMPT_TEMPLATES, ensemble_text_embeddings
from ovgaussian.text.encoders import load_or_encode_texts
from ovgaussian.run.config import TextConfig, config_from_dict
from ovgaussian.predict.view_labels import default_blend_functions, stream_view_labels
from seggaussian.util.atomic import atomic_path, ensure_writable_dir
from seggaussian.core.cameras import Camera
from seggaussian.core.constants import IGNORE_LABEL, SH_C0, read_class_names
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import format_for_output, read_gaussians, write_gaussians
from seggaussian.labels.palette import build_legend, palette, write_legend

#: Lower bound of a decoded vector's norm before cosine similarity (a zero vector scores 0, not NaN).
COSINE_NORM_EPS = 1e-12


# ---------------------------------------------------------------------------------------------
# the model as a predictor
# ---------------------------------------------------------------------------------------------
class ModelPredictor:
    """A trained OVGaussianNet plus its text encoder, as a benchmark predictor.

    ``encode`` gives the 16-d semantic vectors s (blended linearly for 2D); ``classify`` decodes them
    with phi and scores them by cosine against the L2-normalized text embeddings of the classes.
    """

    name = "model"

    def __init__(self, model, text_config, *, checkpoint: Path | None = None, text_cache: Path | None = None,
                 device: str = "cpu", prompt_templates: Sequence[str] = (), trained_names: Sequence[str] = (),
                 faint_neighbours: int = 0) -> None:
        self.model = model.eval().to(device)
        self.faint_neighbours = int(faint_neighbours)  # > 1: faint Gaussians blend with their neighbours (faint_blend)
        self.prompt_templates = tuple(prompt_templates)  # non-empty: a prompt ensemble (prompt_ensemble.py)
        self.trained_names: frozenset[str] = frozenset(trained_names)  # the classes the run was trained on
        self.text_config = text_config
        self.checkpoint = checkpoint
        self.text_cache = text_cache
        self.device = device
        self._embeddings: dict[tuple[str, ...], object] = {}
        self._class_names = read_class_names()

    # --- per-Gaussian vectors ------------------------------------------------------------------
    def encode_gaussians(self, gaussians) -> np.ndarray:
        """``[N, S]`` float32 semantic vectors of a ``Gaussians`` (one scene, no augmentation); with
        ``faint_neighbours`` > 1, each blended with its nearest Gaussians' by its opacity (``faint_blend``)."""
        n = len(gaussians)
        if n == 0:
            return np.zeros((0, self.model.config.semantic_width), np.float32)
        means64 = gaussians.means.astype(np.float64)
        if not np.isfinite(means64).all():
            raise ValueError("Gaussians.means holds NaN/Inf")
        centre = 0.5 * (means64.min(axis=0) + means64.max(axis=0))  # as ovgaussian.data.training_data.prepare_scene
        placed = means64  # the positions the network voxelizes: on the splat's surface when the run says so
        if self.model.config.surface_radius > 0:
            placed = surface_positions(means64, gaussians.opacities(), self.model.config.surface_radius)
        lattice = self.model.grid_lattice
        if lattice is not None:  # a multiple of the grid's lattice: the voxels stay where the scene's frame has them
            step = lattice * self.model.config.voxel_size
            centre = np.round(centre / step) * step
        means = torch.from_numpy((placed - centre).astype(np.float32)).to(self.device)
        attributes = gaussian_attributes(gaussians).to(self.device)
        batch_index = torch.zeros(n, dtype=torch.int64, device=self.device)
        with torch.no_grad():
            semantic = self.model(means, attributes, batch_index)
        out = semantic.detach().cpu().numpy().astype(np.float32)
        if not np.isfinite(out).all():
            raise ValueError("the network produced non-finite semantic vectors (diverged checkpoint?)")
        if self.faint_neighbours > 1:
            out = faint_blend(means64, np.asarray(gaussians.opacities(), np.float64).reshape(-1), out,
                              self.faint_neighbours)
        return out

    def encode(self, scene) -> np.ndarray:
        return self.encode_gaussians(scene.gaussians)

    # --- classification ------------------------------------------------------------------------
    def text_embeddings(self, names: Sequence[str]):
        """``[C, D]`` L2-normalized text embeddings (cached per vocabulary)."""
        key = tuple(names)
        if key not in self._embeddings:
            if self.prompt_templates:
                embeddings = ensemble_text_embeddings(list(names), self.text_config, self.text_cache,
                                                      self.prompt_templates)
            else:
                embeddings = load_or_encode_texts(list(names), self.text_config, self.text_cache)
            self._embeddings[key] = embeddings.to(self.device)
        return self._embeddings[key]

    def decode(self, vectors: np.ndarray) -> np.ndarray:
        """``[M, S]`` semantic vectors -> ``[M, D]`` L2-normalized ``phi(s)``: the space of the text embeddings."""
        with torch.no_grad():
            decoded = self.model.phi(torch.as_tensor(np.asarray(vectors), dtype=torch.float32, device=self.device))
            decoded = decoded / decoded.norm(dim=-1, keepdim=True).clamp_min(COSINE_NORM_EPS)
        return decoded.cpu().numpy()

    def score_names(self, vectors: np.ndarray, names: Sequence[str]) -> np.ndarray:
        """``[M, S]`` semantic vectors (per Gaussian or rendered per pixel) -> ``[M, C]`` cosine scores."""
        text = self.text_embeddings(names)
        with torch.no_grad():
            scores = torch.from_numpy(self.decode(vectors)).to(self.device) @ text.T
        return scores.cpu().numpy()

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        return self.score_names(vectors, [self._class_names[int(i)] for i in class_ids])


def load_model_predictor(run: Path, checkpoint: Path | None = None, device: str = "cpu",
                         prompt_templates: Sequence[str] = (), faint_neighbours: int = 0) -> ModelPredictor:
    """The model of a training run (its latest checkpoint folder unless ``checkpoint`` is given); a non-empty
    ``prompt_templates`` scores against a prompt ensemble; ``faint_neighbours``: see ``ModelPredictor``."""
    run = Path(run)
    resolve_device(device)
    trained = load_trained_model(run, checkpoint, device=device)
    text_config = config_from_dict(TextConfig, trained.run_config.get("train", {}).get("text", {}))
    return ModelPredictor(trained.net, text_config, checkpoint=trained.checkpoint, text_cache=run / "caches",
                          device=device, prompt_templates=prompt_templates,
                          trained_names=trained.run_config.get("vocabulary", {}).get("names", ()),
                          faint_neighbours=faint_neighbours)


# ---------------------------------------------------------------------------------------------
# vocabulary, colours, cameras
# ---------------------------------------------------------------------------------------------
def parse_vocabulary(text: str) -> tuple[str, ...]:
    """``"chair, table,  sofa"`` -> ``("chair", "table", "sofa")``; error on empty or duplicate names."""
    names = tuple(" ".join(part.split()) for part in text.split(","))
    names = tuple(n for n in names if n)
    if not names:
        raise ValueError("--vocab: no class names (give a comma-separated list, e.g. \"chair, table\")")
    lowered = [n.lower() for n in names]
    dupes = sorted({n for n in lowered if lowered.count(n) > 1})
    if dupes:
        raise ValueError(f"--vocab: duplicate class names {dupes}")
    return names


def class_colours(num_classes: int) -> np.ndarray:
    """``[C, 3]`` uint8 colours of vocabulary indices 0..C-1: the fixed palette of ``seggaussian.labels.palette``."""
    return palette(num_classes)


def read_cameras(path: Path) -> list[tuple[str, object]]:
    """Cameras of a JSON file: ``{"cameras": [{"name", "width", "height", "K": 3x3, "viewmat": 4x4 | "c2w": 4x4}]}``
    (or the list alone). ``viewmat`` is world-to-camera, ``c2w`` camera-to-world, OpenCV axes."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: cannot read the cameras file ({error})") from None
    entries = doc.get("cameras") if isinstance(doc, dict) else doc
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: expected a non-empty list 'cameras'")
    cameras = []
    for i, entry in enumerate(entries):
        where = f"{path}: cameras[{i}]"
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: expected an object")
        for key in ("width", "height", "K"):
            if key not in entry:
                raise ValueError(f"{where}: missing field {key!r}")
        try:
            K = np.asarray(entry["K"], dtype=np.float64)
            if "viewmat" in entry:
                camera = Camera(K, np.asarray(entry["viewmat"], dtype=np.float64), entry["width"], entry["height"])
            elif "c2w" in entry:
                camera = Camera.from_c2w(K, np.asarray(entry["c2w"], dtype=np.float64), entry["width"], entry["height"])
            else:
                raise ValueError("missing field 'viewmat' or 'c2w'")
        except (ValueError, TypeError) as error:
            raise ValueError(f"{where}: {error}") from None
        name = str(entry.get("name", f"camera{i:03d}"))
        if not name or "/" in name or name.startswith("."):
            raise ValueError(f"{where}: field 'name' {name!r} is not a plain file name")
        cameras.append((name, camera))
    return cameras


# ---------------------------------------------------------------------------------------------
# labelling and writing
# ---------------------------------------------------------------------------------------------
class PredictResult(NamedTuple):
    """A labelled scene.

    Fields:
        vocabulary: the class names; label i = vocabulary[i].
        labels: ``[N]`` int32 label of every Gaussian.
        gaussians: the input Gaussians with extras ``semantic`` (and ``red, green, blue``) and, per
            ``colour_mode``, the class colours in ``f_dc``.
        shares: ``{name: share of Gaussians}`` (sums to 1 when N > 0).
        counts: ``{name: Gaussians}``.
        label_maps: ``{camera name: [H, W] int64 labels, IGNORE_LABEL where not covered}``.
    """

    vocabulary: tuple[str, ...]
    labels: np.ndarray
    gaussians: object
    shares: dict
    counts: dict
    label_maps: dict


def argmax_labels(scores_fn, vectors: np.ndarray, chunk_rows: int) -> np.ndarray:
    """``[M]`` argmax of ``scores_fn(vectors[chunk])`` over chunks of rows."""
    out = np.empty(vectors.shape[0], dtype=np.int64)
    for start in range(0, vectors.shape[0], chunk_rows):
        scores = np.asarray(scores_fn(vectors[start:start + chunk_rows]))
        out[start:start + scores.shape[0]] = np.argmax(scores, axis=1)
    return out


def paint_gaussians(gaussians, labels: np.ndarray, colours: np.ndarray, mode: str):
    """Gaussians with the ``semantic`` extra and the class colours (``f_dc`` and/or uchar red/green/blue)."""
    rgb = colours[labels]  # [N, 3] uint8
    extras = {k: v for k, v in gaussians.extras.items() if k not in ("semantic", "red", "green", "blue")}
    extras["semantic"] = labels.astype(np.int32)
    sh = gaussians.sh
    if mode in ("f_dc", "both"):
        sh = np.zeros((len(gaussians), 1, 3), np.float32)  # f_rest dropped: a flat class colour from every side
        sh[:, 0, :] = (rgb.astype(np.float32) / 255.0 - 0.5) / SH_C0
    if mode in ("rgb", "both"):
        extras.update(red=rgb[:, 0].copy(), green=rgb[:, 1].copy(), blue=rgb[:, 2].copy())
    elif mode != "f_dc":
        raise ValueError(f"colour mode must be f_dc, rgb or both, got {mode!r}")
    return Gaussians(gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, sh, extras)


def label_gaussians(predictor: ModelPredictor, gaussians, config: PredictConfig, cameras=(),
                    functions=None, class_offsets: "dict[str, float] | None" = None) -> PredictResult:
    """Label every Gaussian against ``config.vocabulary``; render label maps for ``cameras``. ``class_offsets``
    (``{name: offset}``, ``read_class_offsets``) are added to the scores of those names."""
    names = tuple(config.vocabulary)
    if not names:
        raise ValueError("predict: empty vocabulary")
    if class_offsets and config.stacking_gamma > 0:
        raise ValueError("predict: class offsets and a stacking gamma together are not supported (the bench fits "
                         "the offsets on scores without stacking)")
    vectors = predictor.encode_gaussians(gaussians)
    trained = np.array([n in predictor.trained_names for n in names])  # seen classes: lowered by stacking's gamma
    shift = np.array([(class_offsets or {}).get(n, 0.0) for n in names], np.float32)

    def scores(v: np.ndarray) -> np.ndarray:
        return stack_scores(predictor.score_names(v, names), trained, config.stacking_gamma) + shift[None, :]

    labels = argmax_labels(scores, vectors, config.chunk_rows)
    if config.color_by == "semantic":
        painted = paint_gaussians(gaussians, labels, class_colours(len(names)), config.colour_mode)
    else:  # keep the scene's colours; only the label property is added
        painted = gaussians.with_extras(semantic=labels.astype(np.int32))
    counts = np.bincount(labels, minlength=len(names))
    total = max(int(counts.sum()), 1)
    label_maps = {}
    if cameras:
        functions = functions or default_blend_functions()
        for name, camera in cameras:  # streamed: band_rows rows of a view's blend weights at a time
            blender = functions.blend(gaussians, camera, config.blend_top_k)
            label_maps[name] = stream_view_labels(
                lambda rendered: argmax_labels(scores, rendered, config.chunk_rows),
                vectors, blender, functions, config.min_alpha, config.band_rows)
    return PredictResult(names, labels.astype(np.int32), painted,
                         {n: counts[i] / total for i, n in enumerate(names)},
                         {n: int(counts[i]) for i, n in enumerate(names)}, label_maps)


def _write_png_atomic(path: Path, image: np.ndarray) -> None:
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"{path}: could not encode the PNG")


def write_label_maps(folder: Path, label_maps: dict, num_classes: int) -> list[Path]:
    """Per camera ``<name>_labels.png`` (uint16 label, 65535 = not covered) and ``<name>_colour.png``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    colours = np.concatenate([class_colours(num_classes), np.zeros((1, 3), np.uint8)])  # last: uncovered = black
    written = []
    for name, labels in label_maps.items():
        label_path, colour_path = folder / f"{name}_labels.png", folder / f"{name}_colour.png"
        _write_png_atomic(label_path, labels.astype(np.uint16))
        index = np.where(labels == IGNORE_LABEL, num_classes, labels)
        _write_png_atomic(colour_path, colours[index][..., ::-1].copy())  # RGB -> BGR for OpenCV
        written += [label_path, colour_path]
    return written


def load_predictor(config: PredictConfig):
    """The run's model (``config.checkpoint`` or its latest), or the ensemble of it and ``config.ensemble_runs``."""
    templates = PROMPT_TEMPLATES if config.prompt_ensemble else ()
    predictor = load_model_predictor(config.run, config.checkpoint, device=config.device, prompt_templates=templates,
                                     faint_neighbours=config.faint_neighbours)
    if not config.ensemble_runs:
        return predictor
    if config.stacking_gamma > 0:
        raise ValueError("predict: --ensemble-run with --stacking-gamma is not supported (bench chooses gamma for "
                         "one run)")
    return load_ensemble(predictor, config.ensemble_runs, config.device, templates)


def load_ensemble(first: ModelPredictor, runs: Sequence[Path], device: str = "cpu",
                  prompt_templates: Sequence[str] = ()) -> EnsemblePredictor:
    """``first`` and the latest checkpoint of each of ``runs`` (same device, prompts and faint blend) as one
    ensemble."""
    members = [first] + [load_model_predictor(run, None, device=device, prompt_templates=prompt_templates,
                                              faint_neighbours=first.faint_neighbours) for run in runs]
    return EnsemblePredictor(members, [m.model.config.semantic_width for m in members])


def check_offsets_source(report: Path, predictor) -> None:
    """Refuse class offsets fitted on other scores than the predictor gives: on other weights than the predictor's
    (its members' for an ensemble; compared by the sha256 of each checkpoint's ``model.safetensors`` that the bench
    report records, not checked when it records none), or with another ``--faint-neighbours`` blend of the vectors
    (a report without the field was scored without the blend)."""
    members = getattr(predictor, "members", (predictor,))
    recorded = offsets_checkpoints(report)
    given = [weights_sha256(getattr(m, "checkpoint", None)) for m in members]
    if recorded and None not in given and sorted(given) != sorted(recorded):
        raise ValueError(f"{report}: its class offsets were fitted on the scores of {len(recorded)} checkpoint(s) "
                         f"(sha256 {', '.join(d[:12] for d in recorded)}), not on the {len(given)} given with --run"
                         f"{' and --ensemble-run' if len(given) > 1 else ''} (sha256 "
                         f"{', '.join(d[:12] for d in given)}); give the runs that bench scored")
    fitted_with = offsets_faint_neighbours(report)
    blend = max(getattr(m, "faint_neighbours", 0) for m in members)
    if fitted_with != (blend if blend > 1 else 0):
        raise ValueError(f"{report}: its class offsets were fitted on scores with --faint-neighbours {fitted_with}, "
                         f"not {blend}; give the value that bench scored with")


class PredictReport(NamedTuple):
    """What ``ovgaussian predict`` wrote: the labelled scene (``ply``: its path, in ``format``), PNGs, the
    legend files (empty without colouring), and the JSON summary."""

    result: PredictResult
    ply: Path
    pngs: list
    summary: dict
    legend: tuple = ()
    format: str = "ply"


def run_predict(scene_path: Path, out: Path, config: PredictConfig, *, cameras_path: Path | None = None,
                views_dir: Path | None = None, predictor: ModelPredictor | None = None) -> PredictReport:
    """Read ``scene_path`` (any splat format), label it with the run's model, write ``out`` (PLY unless
    ``config.output_format`` or the name asks for another format), the legend and optional label-map PNGs."""
    scene_path, out = Path(scene_path), Path(out)
    resolve_device(config.device)  # before the scene is read
    if scene_path.resolve() == out.resolve():
        raise ValueError(f"{out}: refusing to overwrite the input scene")
    ensure_writable_dir(out.parent)  # fail before the model runs, not after it
    cameras = read_cameras(cameras_path) if cameras_path is not None else []
    out_format = format_for_output(out, config.output_format)
    if out_format != "ply" and config.color_by == "semantic" and config.colour_mode == "rgb":
        raise ValueError(f"{out}: --colours rgb puts the class colours in PLY properties, which a {out_format} "
                         "file cannot hold; use --colours f_dc or both, or a .ply output")
    offsets = read_class_offsets(config.class_offsets) if config.class_offsets is not None else None
    gaussians, report, in_format = read_gaussians(scene_path, on_invalid=config.on_invalid)
    if predictor is None:
        predictor = load_predictor(config)
    if offsets is not None:
        check_offsets_source(config.class_offsets, predictor)
    result = label_gaussians(predictor, gaussians, config, cameras, class_offsets=offsets)
    # the vocabulary goes into the header so the file explains its own labels
    comments = tuple(f"ovgaussian semantic {i} = {name}" for i, name in enumerate(result.vocabulary))
    # and a glTF file's extras: the names and colours of the ids of its _SEMANTIC attribute
    legend = {"semantic": {"names": list(result.vocabulary),
                           "rgb": class_colours(len(result.vocabulary)).tolist()}}
    write_gaussians(out, result.gaussians, out_format, spz_version=config.spz_version,
                    ply_comments=comments, legend=legend)
    legend_files: tuple = ()
    if config.color_by == "semantic":
        legend_files = write_legend(out, build_legend(result.labels, "semantic", result.vocabulary))
    pngs = []
    if cameras:
        views_dir = views_dir or out.with_name(out.stem + "_views")
        pngs = write_label_maps(views_dir, result.label_maps, len(result.vocabulary))
    summary = {
        "scene": str(scene_path),
        "scene_format": in_format,
        "out": str(out),
        "out_format": out_format,
        "legend": [str(p) for p in legend_files],
        "run": str(config.run),
        "checkpoint": None if predictor.checkpoint is None else str(predictor.checkpoint),
        "ensemble": [{"run": str(run), "checkpoint": str(member.checkpoint)}
                     for run, member in zip(config.ensemble_runs, getattr(predictor, "members", ())[1:])],
        "num_gaussians": int(len(gaussians)),
        "validation": getattr(report, "_asdict", lambda: str(report))() if report is not None else None,
        "vocabulary": list(result.vocabulary),
        "class_offsets": None if offsets is None else {"report": str(config.class_offsets),
                                                       "applied": {n: offsets[n] for n in result.vocabulary
                                                                   if n in offsets}},
        "counts": result.counts,
        "shares": result.shares,
        "colours": {n: class_colours(len(result.vocabulary))[i].tolist() for i, n in enumerate(result.vocabulary)},
        "label_maps": [str(p) for p in pngs],
    }
    return PredictReport(result, out, pngs, summary, legend_files, out_format)
