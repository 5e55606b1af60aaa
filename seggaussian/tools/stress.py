"""Numerical-stability stress suite: seeded generators of malformed and extreme inputs, run through the
real stages (PLY reading and validation, rasterization forward and backward, blend weights and label maps,
label transfer), with every outcome classified. The model package adds its own families through the same
``StressFamily`` type (``ovgaussian.train.stress_losses``: training losses); ``seggaussian stress`` runs both, this
package never imports the model package.

An outcome is one of:
- ``ok``: the stage ran and every output (and gradient) is finite;
- ``clean_error``: the stage refused the input with a ValueError/TypeError raised by this toolkit's own
  code (the message names the file or field), never from inside numpy, plyfile or torch;
- ``repaired``: validation changed the input as asked (``on_invalid=repair``) and counted what it did;
- ``nan_inf``: an output held NaN/Inf (a failure);
- ``crash``: any other exception, or a refusal raised from inside a dependency (a failure).

``run_stress(StressConfig(cases=N, seed=S), families)`` runs N cases per family; the same generators run in the
tests with a small N. ``seggaussian stress`` is the command-line face.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from seggaussian.core.cameras import Camera, intrinsics, look_at
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.header import PlyFormatError
from seggaussian.io.ply.reader import read_gaussians_ply
from seggaussian.io.ply.writer import write_gaussians_ply
from seggaussian.render import compute_blend_weights, rasterize, render_features, render_gaussians, render_label_maps
from seggaussian.tools.own_code import raised_by_own_code
from seggaussian.labels.transfer import transfer_labels

#: Image size used for stress renders (small: the suite checks values, not speed).
STRESS_IMAGE_SIZE = (48, 36)
#: Offset (metres) applied to a scene and its camera in the float32 precision check.
FAR_OFFSET = 1e5
#: Largest per-pixel difference allowed between a scene rendered at the origin and at FAR_OFFSET.
FAR_OFFSET_TOLERANCE = 1e-3
#: Outcomes that count as failures.
FAILURES = ("nan_inf", "crash")


@dataclass(frozen=True)
class StressConfig:
    """Settings of ``seggaussian stress``."""

    #: Cases generated per family (ply, broken_file, camera, transfer; loss from the model package).
    cases: int = 20
    #: Seed of the case generators (the whole run is deterministic for a seed).
    seed: int = 0
    #: Rasterizer backend exercised (``fast``, ``reference`` or ``auto``).
    backend: str = "auto"


class CaseResult(NamedTuple):
    """One stress case: ``family`` (stage family), ``name`` (what was generated), ``outcome`` (see module
    docstring) and ``detail`` (the error message, repair summary or failing output)."""

    family: str
    name: str
    outcome: str
    detail: str


class StressReport(NamedTuple):
    """Counts over all cases, plus the cases that failed (``nan_inf`` or ``crash``)."""

    cases_tried: int
    ok: int
    clean_errors: int
    repairs: int
    nan_inf_found: int
    crashes: int
    by_family: dict
    failures: list

    @property
    def passed(self) -> bool:
        return self.nan_inf_found == 0 and self.crashes == 0

    def to_dict(self) -> dict:
        out = self._asdict()
        out["failures"] = [c._asdict() for c in self.failures]
        out["passed"] = self.passed
        return out


class NonFiniteOutput(Exception):
    """An output or gradient of a stage held NaN/Inf."""


# --- classification ------------------------------------------------------------------------------
def classify(family: str, name: str, run: Callable[[], str | None]) -> CaseResult:
    """Run one case; ``run`` returns None (ok) or a repair summary, or raises."""
    try:
        repaired = run()
    except NonFiniteOutput as exc:
        return CaseResult(family, name, "nan_inf", str(exc))
    except (ValueError, TypeError) as exc:
        if raised_by_own_code(exc):
            return CaseResult(family, name, "clean_error", str(exc))
        return CaseResult(family, name, "crash", f"{type(exc).__name__} from a dependency: {exc}")
    except Exception as exc:  # noqa: BLE001 - the suite's job is to catch everything else
        return CaseResult(family, name, "crash", f"{type(exc).__name__}: {exc}")
    if repaired:
        return CaseResult(family, name, "repaired", repaired)
    return CaseResult(family, name, "ok", "")


def require_finite(label: str, *arrays) -> None:
    """Raise NonFiniteOutput naming ``label`` when any array (numpy or torch) holds NaN/Inf."""
    for i, a in enumerate(arrays):
        if a is None:
            continue
        values = a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a)
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            raise NonFiniteOutput(f"{label}: output {i} holds {int((~np.isfinite(values)).sum())} NaN/Inf values")


# --- generators ----------------------------------------------------------------------------------
def random_gaussians(rng: np.random.Generator, n: int, sh_degree: int = 1, center=(0.0, 0.0, 0.0),
                     spread: float = 0.5) -> Gaussians:
    """Well-formed Gaussians around ``center`` (the base every corruption starts from)."""
    k = (sh_degree + 1) ** 2
    return Gaussians.from_arrays(
        np.asarray(center) + rng.normal(scale=spread, size=(n, 3)),
        rng.normal(size=(n, 4)),
        rng.uniform(-4.5, -2.0, size=(n, 3)),
        rng.normal(size=n),
        rng.normal(scale=0.3, size=(n, k, 3)),
    )


def corrupt(g: Gaussians, kind: str, rng: np.random.Generator) -> Gaussians:
    """A copy of ``g`` with one kind of extreme or malformed values in a random subset of rows."""
    means, quats, log_scales = g.means.copy(), g.quats.copy(), g.log_scales.copy()
    opacity_logits, sh = g.opacity_logits.copy(), g.sh.copy()
    rows = rng.random(len(g)) < 0.3
    if kind == "nan_means":
        means[rows, rng.integers(0, 3)] = np.nan
    elif kind == "inf_sh":
        sh[rows, 0, rng.integers(0, 3)] = np.inf
    elif kind == "zero_scales":  # stored as logs: zero scale is -inf
        log_scales[rows] = -np.inf
    elif kind == "denormal_scales":
        log_scales[rows] = -100.0  # exp(-100) ~ 3.7e-44: a float32 denormal
    elif kind == "huge_log_scales":
        log_scales[rows] = rng.uniform(20.0, 120.0)
    elif kind == "non_unit_quats":
        quats *= rng.uniform(1e-6, 1e6, size=(len(g), 1)).astype(np.float32)
    elif kind == "zero_quats":
        quats[rows] = 0.0
    elif kind == "saturated_opacity":
        opacity_logits[rows] = rng.choice([-100.0, 100.0], size=int(rows.sum()))
    elif kind == "duplicate_positions":
        means[:] = means[0]
    elif kind == "far_offset":
        means += FAR_OFFSET
    else:
        raise ValueError(f"unknown corruption {kind!r}")
    return Gaussians(means, quats, log_scales, opacity_logits, sh, g.extras)


CORRUPTIONS = (
    "nan_means", "inf_sh", "zero_scales", "denormal_scales", "huge_log_scales", "non_unit_quats",
    "zero_quats", "saturated_opacity", "duplicate_positions", "far_offset",
)
#: Broken files: each must end in a clean PlyFormatError.
BROKEN_FILES = ("truncated", "count_too_large", "empty", "not_ply", "missing_opacity", "f_rest_7")


def camera_facing(center: np.ndarray, distance: float = 3.0) -> Camera:
    """A small camera looking at ``center`` from ``distance`` metres away."""
    w, h = STRESS_IMAGE_SIZE
    eye = np.asarray(center, dtype=np.float64) + np.array([0.0, -distance, 0.3 * distance])
    return Camera(intrinsics(0.8 * w, 0.8 * w, w / 2, h / 2), look_at(eye, center), w, h)


# --- stage runners -------------------------------------------------------------------------------
def render_and_check(g: Gaussians, camera: Camera, backend: str, label: str) -> None:
    """Forward and backward through the rasterizer, blend weights and label maps; all must be finite."""
    import torch

    t = {k: v.clone().requires_grad_(True) for k, v in g.to_torch().items()}
    viewmat = torch.as_tensor(camera.viewmat)
    K = torch.as_tensor(camera.K)
    out = rasterize(t["means"], t["quats"], t["log_scales"], t["opacity_logits"], viewmat, K, camera.width,
                    camera.height, sh=t["sh"], backend=backend)
    require_finite(f"{label}: rasterize forward", out.image, out.alpha, out.depth)
    (out.image.sum() + out.depth.sum() + out.alpha.sum()).backward()
    require_finite(f"{label}: rasterize backward", *(v.grad for v in t.values()))
    blend = compute_blend_weights(t["means"].detach(), t["quats"].detach(), t["log_scales"].detach(),
                                  t["opacity_logits"].detach(), viewmat, K, camera.width, camera.height)
    require_finite(f"{label}: blend weights", blend.weights, blend.residual_alpha)
    features = torch.ones(len(g), 2, requires_grad=True)
    rendered = render_features(blend, features)
    rendered.sum().backward()
    require_finite(f"{label}: render_features", rendered, features.grad)
    labels = np.arange(len(g), dtype=np.int32) % 3
    maps = render_label_maps(blend, torch.as_tensor(labels), torch.as_tensor(labels), 3)
    require_finite(f"{label}: label maps", maps.soft)


def run_ply_case(rng: np.random.Generator, kind: str, workdir: Path, backend: str) -> str | None:
    """Write a corrupted PLY; reading with ``error`` must refuse it cleanly (or accept a valid file),
    reading with ``repair`` must count its repairs, and the repaired scene must render finitely."""
    g = corrupt(random_gaussians(rng, int(rng.integers(1, 200)), int(rng.integers(0, 4))), kind, rng)
    path = workdir / f"{kind}.ply"
    write_gaussians_ply(path, g)
    try:
        read_gaussians_ply(path, on_invalid="error")
    except PlyFormatError:
        pass
    repaired, report = read_gaussians_ply(path, on_invalid="repair")
    require_finite(f"{kind}: repaired Gaussians", repaired.means, repaired.quats, repaired.sh,
                   repaired.opacity_logits, repaired.log_scales)
    if len(repaired):
        center = np.median(repaired.means, axis=0)
        render_and_check(repaired, camera_facing(center), backend, kind)
    return report.describe_actions() if report.actions else None


def write_broken_file(kind: str, workdir: Path, rng: np.random.Generator) -> Path:
    """A PLY that no reader should accept, of the given kind."""
    path = workdir / f"broken_{kind}.ply"
    if kind == "empty":
        path.write_bytes(b"")
        return path
    if kind == "not_ply":
        path.write_bytes(rng.bytes(64))
        return path
    g = random_gaussians(rng, 10)
    write_gaussians_ply(path, g)
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    if kind == "truncated":
        data = head + b"end_header\n" + body[: len(body) // 2 + 1]
    elif kind == "count_too_large":
        data = head.replace(b"element vertex 10", b"element vertex 11") + b"end_header\n" + body
    elif kind == "missing_opacity":
        data = head.replace(b"property float opacity", b"property float opacityx") + b"end_header\n" + body
    elif kind == "f_rest_7":  # degree-1 file (9 f_rest) relabelled so 7 f_rest remain
        data = (head.replace(b"property float f_rest_7", b"property float g_rest_7")
                .replace(b"property float f_rest_8", b"property float g_rest_8") + b"end_header\n" + body)
    path.write_bytes(data)
    return path


def run_broken_file_case(rng: np.random.Generator, kind: str, workdir: Path) -> str | None:
    read_gaussians_ply(write_broken_file(kind, workdir, rng), on_invalid="repair")
    raise RuntimeError(f"broken file ({kind}) was accepted")


def run_camera_case(rng: np.random.Generator, kind: str, backend: str) -> None:
    """Degenerate geometry relative to the camera: on the camera plane, behind it, nothing in view,
    everything at one point, and the 1e5 m offset invariance of the image."""
    g = random_gaussians(rng, int(rng.integers(1, 100)))
    camera = camera_facing(np.zeros(3))
    if kind == "on_camera_plane":  # camera-frame z = 0 exactly
        c2w = camera.c2w
        local = np.c_[rng.normal(size=(len(g), 2)), np.zeros(len(g))]
        means = (local @ c2w[:3, :3].T + c2w[:3, 3]).astype(np.float32)
        g = Gaussians(means, g.quats, g.log_scales, g.opacity_logits, g.sh)
    elif kind == "behind_camera":
        behind = 2 * camera.center - g.means  # mirrored through the camera centre
        g = Gaussians(behind.astype(np.float32), g.quats, g.log_scales, g.opacity_logits, g.sh)
    elif kind == "sees_nothing":
        camera = Camera(camera.K, look_at(camera.center, camera.center * 2), camera.width, camera.height)
    elif kind == "one_point":
        g = Gaussians(np.zeros_like(g.means), g.quats, g.log_scales, g.opacity_logits, g.sh)
    elif kind == "far_offset":
        return check_far_offset(g, camera, backend)
    render_and_check(g, camera, backend, kind)
    return None


def check_far_offset(g: Gaussians, camera: Camera, backend: str) -> None:
    """The image of a scene and its camera shifted by FAR_OFFSET equals the unshifted one."""
    near = render_gaussians(g, camera, backend=backend).image
    offset = np.full(3, FAR_OFFSET)
    far_g = Gaussians((g.means.astype(np.float64) + offset).astype(np.float32), g.quats, g.log_scales,
                      g.opacity_logits, g.sh)
    far = render_gaussians(far_g, camera.translated(offset), backend=backend).image
    require_finite("far_offset", near, far)
    # the float32 storage of the shifted means rounds them by up to ~4 mm at 1e5 m; compare against
    # the unshifted scene holding exactly those rounded positions
    rounded = Gaussians((far_g.means.astype(np.float64) - offset).astype(np.float32), g.quats, g.log_scales,
                        g.opacity_logits, g.sh)
    expected = render_gaussians(rounded, camera, backend=backend).image
    diff = float((far - expected).abs().max()) if far.numel() else 0.0
    if diff > FAR_OFFSET_TOLERANCE:
        raise NonFiniteOutput(f"far_offset: image changed by {diff:.2e} (> {FAR_OFFSET_TOLERANCE}) at 1e5 m")


def run_transfer_case(rng: np.random.Generator, kind: str) -> None:
    """Label transfer with ties, empty point sets, no Gaussians, far offsets."""
    n, p = int(rng.integers(0, 50)), int(rng.integers(1, 50))
    means = rng.normal(size=(n, 3))
    points = rng.normal(size=(p, 3))
    semantic = rng.integers(0, 5, size=p).astype(np.int32)
    if kind == "ties":  # every point duplicated with another label: equidistant candidates
        points = np.r_[points, points]
        semantic = np.r_[semantic, (semantic + 1) % 5].astype(np.int32)
    elif kind == "empty_points":
        points, semantic = np.zeros((0, 3)), np.zeros(0, np.int32)
    elif kind == "no_gaussians":
        means = np.zeros((0, 3))
    elif kind == "far_offset":
        means, points = means + FAR_OFFSET, points + FAR_OFFSET
    result = transfer_labels(means, points, semantic, semantic.copy())
    require_finite(f"transfer {kind}", result.distances)
    if kind == "ties" and len(means):  # a tie must resolve to one of the tied labels, deterministically
        again = transfer_labels(means, points, semantic, semantic.copy())
        if not np.array_equal(again.semantic, result.semantic):
            raise NonFiniteOutput("transfer ties: labels differ between two identical runs")
    return None


TRANSFER_KINDS = ("ties", "empty_points", "no_gaussians", "far_offset", "plain")
CAMERA_KINDS = ("on_camera_plane", "behind_camera", "sees_nothing", "one_point", "far_offset")


class StressContext(NamedTuple):
    """What a case may use besides its generator: ``workdir`` (scratch folder of the run, removed at its
    end) and ``backend`` (rasterizer backend exercised)."""

    workdir: Path
    backend: str


class StressFamily(NamedTuple):
    """A family of stress cases: ``name`` (reported), ``kinds`` (case ``i`` generates ``kinds[i % len]``) and
    ``run(rng, kind, context)``, which returns None (ok) or a repair summary, or raises (see ``classify``)."""

    name: str
    kinds: tuple
    run: Callable[[np.random.Generator, str, StressContext], "str | None"]


def _ply_family(rng: np.random.Generator, kind: str, context: StressContext) -> str | None:
    return run_ply_case(rng, kind, context.workdir, context.backend)


def _broken_file_family(rng: np.random.Generator, kind: str, context: StressContext) -> str | None:
    return run_broken_file_case(rng, kind, context.workdir)


def _camera_family(rng: np.random.Generator, kind: str, context: StressContext) -> None:
    return run_camera_case(rng, kind, context.backend)


def _transfer_family(rng: np.random.Generator, kind: str, context: StressContext) -> None:
    return run_transfer_case(rng, kind)


#: The dataset package's families, in the order they run (the seeds of later families depend on it).
DATASET_FAMILIES = (
    StressFamily("ply", CORRUPTIONS, _ply_family),
    StressFamily("broken_file", BROKEN_FILES, _broken_file_family),
    StressFamily("camera", CAMERA_KINDS, _camera_family),
    StressFamily("transfer", TRANSFER_KINDS, _transfer_family),
)


def run_stress(config: StressConfig, progress: Callable[[CaseResult], None] | None = None,
               families: Sequence[StressFamily] = DATASET_FAMILIES) -> StressReport:
    """Run ``config.cases`` cases of every family (in order, one seeded generator for the whole run) and
    count the outcomes."""
    rng = np.random.default_rng(config.seed)
    results: list[CaseResult] = []
    with tempfile.TemporaryDirectory(prefix="seggaussian-stress-") as tmp:
        context = StressContext(Path(tmp), config.backend)
        for family in families:
            for i in range(config.cases):
                kind = family.kinds[i % len(family.kinds)]
                case_rng = np.random.default_rng(rng.integers(2**63))
                result = classify(family.name, f"{kind}#{i}", lambda: family.run(case_rng, kind, context))
                results.append(result)
                if progress:
                    progress(result)
    counts = {o: sum(r.outcome == o for r in results) for o in ("ok", "clean_error", "repaired", "nan_inf", "crash")}
    by_family: dict[str, dict[str, int]] = {}
    for r in results:
        by_family.setdefault(r.family, {}).setdefault(r.outcome, 0)
        by_family[r.family][r.outcome] += 1
    return StressReport(
        cases_tried=len(results), ok=counts["ok"], clean_errors=counts["clean_error"], repairs=counts["repaired"],
        nan_inf_found=counts["nan_inf"], crashes=counts["crash"], by_family=by_family,
        failures=[r for r in results if r.outcome in FAILURES],
    )
