"""``--transform`` / ``--from-frame``: the text a user gives, read into a ``FrameTransform`` (``world_from_splat``).

Accepted ``spec`` strings (see the package docstring for which tool exports in which frame):

- ``frame:CODE``: an axis-letter frame (``frame:RUB``): ``world_from_splat = axes_to_rdf(CODE)``.
- ``gsplat:COLMAP_DIR``: gsplat ``simple_trainer``'s default normalization recomputed from that COLMAP model
  (a model folder, or a dataset folder with ``sparse/0``), inverted. ``gsplat-legacy:COLMAP_DIR``: the same for
  gsplat 1.0 .. 1.5.1 (no upside-down flip).
- a path to a JSON file holding one of:
  - ``{"world_from_splat": 4x4}`` or a bare 4x4 list: splat coordinates -> scene coordinates, row-major;
  - nerfstudio's ``dataparser_transforms.json`` (``{"transform": 3x4, "scale": s}``): nerfstudio maps its input
    data's world to the trained model's frame by ``x = s * (transform @ [p; 1])``
    (``DataparserOutputs.save_dataparser_transform``, ``Nerfstudio._load_3D_points``); inverted here;
  - ``{"chain": [spec, ...]}``: specs composed from the splat outward (the first is applied first); relative
    paths inside are resolved against the JSON file's folder.

Relative paths of the top-level ``spec`` resolve against ``base_dir`` (the current folder when None).
Every refusal is a one-line ``TransformSpecError`` (a ``ValueError``) naming the file (or the spec) and the field.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from seggaussian.frames.axes import axes_to_rdf, parse_axes_code
from seggaussian.frames.colmap_model import ColmapModelError, read_colmap_model
from seggaussian.frames.gsplat_normalization import GSPLAT_FLIP_VERSION, GsplatNormalizationError, gsplat_normalization
from seggaussian.frames.similarity import Similarity, similarity_problem

FRAME_PREFIX = "frame:"
GSPLAT_PREFIX = "gsplat:"
GSPLAT_LEGACY_PREFIX = "gsplat-legacy:"
#: A chain may name chains; deeper nesting than this is refused (it is almost surely a chain naming itself).
MAX_CHAIN_DEPTH = 16


class TransformSpecError(ValueError):
    """A ``--transform`` / ``--from-frame`` that cannot be used; one line naming the file (or spec) and field."""

    def __init__(self, where: Path | str, field_name: str | None, problem: str):
        location = f"{where}" + (f" [{field_name}]" if field_name else "")
        super().__init__(f"{location}: {problem}")


@dataclass(frozen=True, eq=False)
class FrameTransform:
    """Where a splat's coordinates go: ``world_from_splat`` maps splat coordinates to the scene's (mesh) frame.

    Fields:
        world_from_splat: the similarity.
        description: one line saying what it is (for logs and records).
        details: JSON-safe facts for reports (kind, source file, the steps' values).
    """

    world_from_splat: Similarity
    description: str
    details: dict = field(default_factory=dict)


def _similarity_details(sim: Similarity) -> dict:
    return {"world_from_splat": sim.matrix.tolist(), "scale": float(sim.scale), "reflection": sim.is_reflection}


def _frame_transform(code: str, where: str) -> FrameTransform:
    try:
        letters = parse_axes_code(code)
    except ValueError as exc:
        raise TransformSpecError(where, None, str(exc)) from None
    sim = Similarity(axes_to_rdf(letters), np.zeros(3), 1.0)
    return FrameTransform(sim, f"frame:{letters} (axes {letters} -> RDF)",
                          {"kind": "axes", "axes": letters, **_similarity_details(sim)})


def _gsplat_transform(folder: Path, spec: str, upside_down_fix: bool) -> FrameTransform:
    try:
        model = read_colmap_model(folder)
    except ColmapModelError as exc:
        raise TransformSpecError(spec, None, str(exc)) from None
    order = np.argsort(model.image_names, kind="stable")  # gsplat sorts the images by name
    camtoworlds = np.linalg.inv(model.world_to_camera[order])
    try:
        norm = gsplat_normalization(camtoworlds, model.points, upside_down_fix=upside_down_fix)
    except GsplatNormalizationError as exc:
        raise TransformSpecError(model.folder, None, f"gsplat normalization: {exc}") from None
    normalized_from_colmap = Similarity.from_matrix(norm.transform, source=f"{model.folder} [gsplat normalization]")
    sim = normalized_from_colmap.inverse()
    version = f">= {GSPLAT_FLIP_VERSION}" if upside_down_fix else f"1.0 .. < {GSPLAT_FLIP_VERSION}"
    details = {
        "kind": "gsplat", "gsplat_version": version, "colmap_model": str(model.folder),
        "colmap_format": "binary" if model.binary else "text", "num_images": len(model.image_names),
        "num_points": int(len(model.points)), "normalization": norm.transform.tolist(), "t1": norm.t1.tolist(),
        "t2": norm.t2.tolist(), "upside_down_flip": norm.flipped, "normalization_scale": norm.scale,
        **_similarity_details(sim),
    }
    return FrameTransform(sim, f"gsplat normalization of {model.folder} (gsplat {version}), inverted", details)


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise TransformSpecError(path, None, f"cannot read ({type(exc).__name__}: {exc})") from None
    except json.JSONDecodeError as exc:
        raise TransformSpecError(path, None, f"not valid JSON ({exc})") from None


def _matrix(value, path: Path, name: str, shape: tuple[int, int]) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TransformSpecError(path, name, f"expected a {shape[0]}x{shape[1]} matrix of numbers") from None
    if m.shape != shape:
        raise TransformSpecError(path, name, f"expected a {shape[0]}x{shape[1]} matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise TransformSpecError(path, name, "holds NaN/Inf")
    return m


def _explicit_transform(value, path: Path, name: str) -> FrameTransform:
    m = _matrix(value, path, name, (4, 4))
    problem = similarity_problem(m)
    if problem is not None:
        raise TransformSpecError(path, name, problem)
    sim = Similarity.from_matrix(m)
    return FrameTransform(sim, f"world_from_splat from {path}", {"kind": "matrix", "file": str(path),
                                                                 **_similarity_details(sim)})


def _nerfstudio_transform(data: dict, path: Path) -> FrameTransform:
    transform = _matrix(data["transform"], path, "transform", (3, 4))
    scale = data["scale"]
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (np.isfinite(scale) and scale > 0):
        raise TransformSpecError(path, "scale", f"expected a positive number, got {scale!r}")
    splat_from_data = np.eye(4)
    splat_from_data[:3] = float(scale) * transform
    problem = similarity_problem(splat_from_data)
    if problem is not None:
        raise TransformSpecError(path, "transform", problem)
    sim = Similarity.from_matrix(splat_from_data).inverse()
    return FrameTransform(sim, f"nerfstudio dataparser frame of {path}, inverted",
                          {"kind": "nerfstudio_dataparser", "file": str(path), "dataparser_scale": float(scale),
                           "dataparser_transform": transform.tolist(), **_similarity_details(sim)})


def _chain_transform(items, path: Path, depth: int) -> FrameTransform:
    if not isinstance(items, list) or not items:
        raise TransformSpecError(path, "chain", "expected a non-empty list of specs")
    sim = Similarity.identity()
    steps = []
    for index, item in enumerate(items):
        if not isinstance(item, str):
            raise TransformSpecError(path, f"chain[{index}]", f"expected a spec string, got {type(item).__name__}")
        step = _load(item, path.parent, depth + 1, f"{path} [chain[{index}]]")
        sim = step.world_from_splat.compose(sim)
        steps.append({"spec": item, "description": step.description, "details": step.details})
    descriptions = " then ".join(step["description"] for step in steps)
    return FrameTransform(sim, f"chain of {path}: {descriptions}",
                          {"kind": "chain", "file": str(path), "steps": steps, **_similarity_details(sim)})


def _json_transform(path: Path, depth: int) -> FrameTransform:
    data = _read_json(path)
    if isinstance(data, list):
        return _explicit_transform(data, path, "matrix")
    if not isinstance(data, dict):
        raise TransformSpecError(path, None, f"expected a JSON object or a 4x4 list, got {type(data).__name__}")
    kinds = [key for key in ("world_from_splat", "chain", "transform") if key in data]
    if len(kinds) != 1:
        raise TransformSpecError(path, None, "expected exactly one of 'world_from_splat' (4x4), 'chain' (list of "
                                             "specs) or nerfstudio's 'transform' + 'scale'"
                                 + (f", found {kinds}" if kinds else f", found keys {sorted(data)[:8]}"))
    kind = kinds[0]
    if kind == "world_from_splat":
        return _explicit_transform(data["world_from_splat"], path, "world_from_splat")
    if kind == "chain":
        return _chain_transform(data["chain"], path, depth)
    if "scale" not in data:
        raise TransformSpecError(path, "scale", "missing (a nerfstudio dataparser_transforms.json has "
                                                "'transform' and 'scale')")
    return _nerfstudio_transform(data, path)


def _resolve_path(text: str, base_dir: Path | None) -> Path:
    path = Path(text).expanduser()
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    return path


def _load(spec: str, base_dir: Path | None, depth: int, where: str) -> FrameTransform:
    if depth > MAX_CHAIN_DEPTH:
        raise TransformSpecError(where, None, f"chains nested deeper than {MAX_CHAIN_DEPTH} (a chain naming itself?)")
    if not isinstance(spec, str) or not spec.strip():
        raise TransformSpecError(where, None, f"expected a non-empty spec string, got {spec!r}")
    spec = spec.strip()
    if spec.startswith(FRAME_PREFIX):
        return _frame_transform(spec[len(FRAME_PREFIX):], where)
    for prefix, fix in ((GSPLAT_PREFIX, True), (GSPLAT_LEGACY_PREFIX, False)):
        if spec.startswith(prefix):
            folder = spec[len(prefix):]
            if not folder:
                raise TransformSpecError(where, None, f"{prefix} needs a COLMAP folder ({prefix}PATH)")
            return _gsplat_transform(_resolve_path(folder, base_dir), where, fix)
    path = _resolve_path(spec, base_dir)
    if not path.is_file():
        raise TransformSpecError(where, None, f"no such file {path} (expected a JSON file, frame:AXES, "
                                              "gsplat:COLMAP_DIR or gsplat-legacy:COLMAP_DIR)")
    return _json_transform(path, depth)


def load_transform(spec: str, *, base_dir: Path | None = None) -> FrameTransform:
    """The ``FrameTransform`` a ``--transform`` spec names (see the module docstring)."""
    return _load(spec, base_dir, 0, f"--transform {spec!r}")


def resolve_transform(transform: str | None, from_frame: str | None, base_dir: Path | None = None
                      ) -> FrameTransform | None:
    """``--from-frame`` (axes of the splat's raw coordinates, applied first) then ``--transform``; None for neither.

    ``from_frame`` is an axes code (``RUB``) or ``frame:RUB``."""
    steps = []
    if from_frame is not None:
        code = from_frame.strip()
        code = code[len(FRAME_PREFIX):] if code.startswith(FRAME_PREFIX) else code
        steps.append(_frame_transform(code, f"--from-frame {from_frame!r}"))
    if transform is not None:
        steps.append(load_transform(transform, base_dir=base_dir))
    if not steps:
        return None
    if len(steps) == 1:
        return steps[0]
    first, second = steps
    sim = second.world_from_splat.compose(first.world_from_splat)
    return FrameTransform(sim, f"{first.description} then {second.description}",
                          {"kind": "from_frame_then_transform", "from_frame": first.details,
                           "transform": second.details, **_similarity_details(sim)})
