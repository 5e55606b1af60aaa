"""``seggaussian build``: raw scenes -> labelled Gaussians -> per-view label maps -> split-named Parquet shards.

Orchestration only; every stage is a call into its own module:

    discover   sources.{scannetpp,replica}.list_scenes + a stat fingerprint of each scene's raw files
    gaussians  fit.fit_scene | io.formats.read_gaussians (trained splat) | sample_oracle_gaussians (--gaussians oracle)
    transfer   transfer.transfer_labels  -> per-scene ``gaussians`` table
    views      render.compute_blend_weights + render_label_maps -> per-scene ``views`` table
    assemble   split.assign_splits + shards.write_dataset (shards, manifest, dataset card, splits.json)

Cache (``DATASET/.build/scenes/<scene>/``): each stage writes its outputs atomically, then a record
``<stage>.json`` holding the stage key = sha256 of (input fingerprint, upstream keys, the stage's config,
the stage's code). A stage runs only when its key changed or an output is missing, so an unchanged rerun
reads no raw scene and writes no file; a changed setting reruns the stages downstream of it; a killed build
resumes at the first stage without a record. Outputs are byte-deterministic for the same inputs and config.

``--source synthetic``: ``ROOT/scannetpp`` (ScanNet++ layout) and ``ROOT/replica`` (Replica layout), as
written by ``seggaussian synth``; a root holding only one layout is read as that layout. When ``ROOT``
does not exist, the default synthetic set is synthesized into it first (``BuildConfig.synthesize_missing``).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import time
import traceback
from dataclasses import asdict, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

import seggaussian
from seggaussian.atomic import ensure_writable_dir, sweep_temps
from seggaussian.build_config import BuildConfig, OracleConfig, ViewConfig, config_dict
from seggaussian.constants import IGNORE_LABEL, SH_C0, read_class_names
from seggaussian.gaussians import Gaussians

STAGES = ("gaussians", "transfer", "views")
CACHE_DIR = ".build"
#: Bumped when the oracle sampler's output changes.
ORACLE_VERSION = 1
#: Bumped when ``run_views`` (code outside the hashed render package) changes the stored views;
#: 2 = anonymization masks make their pixels ignore in the label maps.
VIEWS_VERSION = 2
#: Triangles with an area below this (m^2) get no oracle samples (their normal is undefined).
MIN_TRIANGLE_AREA = 1e-12
#: A unit normal within this of -z (1 + n.z below it) is rotated by 180 degrees about x: the half-way
#: quaternion is undefined there.
ANTIPODAL_EPS = 1e-9
#: Floor (metres) of each side of a point cloud's bounding box when deriving oracle scales (flat clouds).
MIN_EXTENT = 1e-3
#: Smallest oracle Gaussian standard deviation (metres): keeps log-scales finite for zero-size samples.
MIN_ORACLE_SCALE = 1e-5
#: Oracle opacities are clipped into [eps, 1 - eps] before the logit (keeps it finite).
OPACITY_EPS = 1e-6
SEGGAUSSIAN_DIR = Path(seggaussian.__file__).resolve().parent


class SceneTask(NamedTuple):
    """One scene to build (picklable; sent to workers).

    Fields:
        scene_id: the source's scene id.
        domain: reader used: ``scannetpp`` or ``replica``.
        root: the layout root passed to the reader.
        fingerprint: sha256 of the scene's raw files (relative path, size, mtime) and the reader code.
        trained_ply: a trained 3DGS PLY for this scene, or None.
        official_split: ``train`` / ``val`` from the official lists, or None.
    """

    scene_id: str
    domain: str
    root: Path
    fingerprint: str
    trained_ply: Path | None
    official_split: str | None


class SceneOutcome(NamedTuple):
    """What building one scene did.

    Fields:
        scene_id, domain, official_split: as in the task.
        status: ``built`` (a stage ran), ``skipped`` (every stage cached) or ``failed``.
        stages_run: names of the stages that ran.
        reason: the error (type and message) for a failed scene.
        info: JSON-ready facts copied into the manifest (counts, transfer statistics, accuracy).
        fragments: {table: cached per-scene Parquet path}.
        keys: {stage: key}.
        seconds: wall time.
    """

    scene_id: str
    domain: str
    official_split: str | None
    status: str
    stages_run: tuple
    reason: str | None
    info: dict
    fragments: dict
    keys: dict
    seconds: float


class BuildReport(NamedTuple):
    """Result of ``build_dataset``: per-scene outcomes, split counts, files, whether shards were rewritten."""

    dataset: Path
    outcomes: list
    split_counts: dict
    files: int
    bytes: int
    assembled: bool
    synthesized: list
    seconds: float
    #: Failed scenes whose last good copy stays in the shards (see ``_write_build_record``).
    kept: tuple = ()
    #: Temporaries of killed earlier runs removed from the dataset folder at the start.
    swept: int = 0

    @property
    def counts(self) -> dict:
        return {s: sum(1 for o in self.outcomes if o.status == s) for s in ("built", "skipped", "failed")}


# --- hashing helpers ----------------------------------------------------------------------------------
def sha256_json(payload) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def code_hash(*relative: str) -> str:
    """sha256 of the named source files / folders (``*.py``) of the seggaussian package (missing ones count)."""
    h = hashlib.sha256(seggaussian.__version__.encode())
    for rel in relative:
        path = SEGGAUSSIAN_DIR / rel
        files = sorted(path.rglob("*.py")) if path.is_dir() else [path]
        for f in files:
            h.update(str(f.relative_to(SEGGAUSSIAN_DIR)).encode())
            h.update(f.read_bytes() if f.is_file() else b"<missing>")
    return h.hexdigest()


#: The suffixes of data_specs/ files that code reads (prose, the package marker and bytecode stay out of the key).
DATA_SUFFIXES = (".txt", ".json", ".csv")


def data_specs_hash() -> str:
    """sha256 of the data files readers use (class lists, mappings) in ``data_specs/`` (prose and code excluded)."""
    from seggaussian.constants import DATA_SPECS_DIR

    h = hashlib.sha256()
    if DATA_SPECS_DIR.is_dir():
        for f in sorted(p for p in DATA_SPECS_DIR.rglob("*") if p.is_file() and p.suffix in DATA_SUFFIXES):
            h.update(str(f.relative_to(DATA_SPECS_DIR)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def content_config_hash(config: BuildConfig) -> str:
    """Hash of every setting that changes dataset bytes (no paths, job counts or executors)."""
    d = config_dict(config)
    for k in ("root", "out", "scenes", "jobs", "executor", "address", "progress", "ply_dir",
              "synthesize_missing", "synthetic_counts", "split"):
        d.pop(k, None)
    return sha256_json(d)[:16]


# --- discovery ------------------------------------------------------------------------------------
def layout_roots(config: BuildConfig) -> list[tuple[str, Path]]:
    """(domain, layout root) pairs the build reads."""
    root = Path(config.root)
    if config.source in ("scannetpp", "replica"):
        return [(config.source, root)]
    if config.source == "ply":
        return [(detect_layout(root), root)]
    if config.source == "synthetic":
        pairs = [(d, root / d) for d in ("scannetpp", "replica") if (root / d).is_dir()]
        return pairs or [(detect_layout(root), root)]
    raise ValueError(f"build: --source must be synthetic, scannetpp, replica or ply, got {config.source!r}")


def detect_layout(root: Path) -> str:
    """``scannetpp`` when ``root/data`` exists (ScanNet++ layout), else ``replica``."""
    if not Path(root).is_dir():
        raise FileNotFoundError(f"{root}: raw tree does not exist")
    return "scannetpp" if (Path(root) / "data").is_dir() else "replica"


def reader(domain: str):
    """The source module of a domain (imported lazily)."""
    if domain == "scannetpp":
        from seggaussian.sources import scannetpp as module
    elif domain == "replica":
        from seggaussian.sources import replica as module
    else:
        raise ValueError(f"unknown source domain {domain!r}")
    return module


def synthesize_default(config: BuildConfig) -> list[str]:
    """Write the default synthetic set (ScanNet++ and Replica layouts) into ``config.root``."""
    from seggaussian.sources import synthetic

    root = Path(config.root)
    made: list[str] = []
    for layout, count in zip(("scannetpp", "replica"), config.synthetic_counts):
        if count > 0:
            made += list(synthetic.synthesize(root / layout, count, config.seed, layout=layout))
    return made


def fingerprint_tree(root: Path, scene_ids: list[str]) -> dict[str, str]:
    """Per scene, sha256 over (relative path, size, mtime_ns) of its raw files plus the shared files.

    A file belongs to a scene when a component of its path relative to ``root`` equals the scene id, or
    starts with the scene id followed by ``_``, ``.`` or ``-``; files that belong to no scene (metadata,
    class lists, split lists) are shared and enter every scene's fingerprint (conservative).
    """
    root = Path(root)
    ids = set(scene_ids)
    per_scene: dict[str, list] = {s: [] for s in scene_ids}
    shared: list = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        rel_dir = Path(dirpath).relative_to(root)
        for name in sorted(filenames):
            rel = rel_dir / name
            st = os.stat(Path(dirpath) / name)
            entry = (str(rel), st.st_size, st.st_mtime_ns)
            owner = _owner(rel.parts, ids)
            (per_scene[owner] if owner is not None else shared).append(entry)
    shared_hash = sha256_json(shared)
    return {s: sha256_json([shared_hash, per_scene[s]]) for s in scene_ids}


def _owner(parts: tuple, ids: set) -> str | None:
    for part in parts:
        if part in ids:
            return part
    for part in parts:
        for sep in ("_", ".", "-"):
            head = part.split(sep, 1)[0]
            if head in ids and head != part:
                return head
    return None


def find_trained_ply(ply_dir: Path | None, scene_id: str) -> Path | None:
    """``ply_dir/<scene>.ply`` (or ``.compressed.ply``, ``.splat``, ``.spz``: any format ``io.formats``
    reads, detected by content) or the highest ``ply_dir/<scene>/point_cloud/iteration_*/point_cloud.ply``."""
    if ply_dir is None:
        return None
    for suffix in (".ply", ".compressed.ply", ".splat", ".spz"):
        flat = Path(ply_dir) / f"{scene_id}{suffix}"
        if flat.is_file():
            return flat
    runs = sorted((Path(ply_dir) / scene_id / "point_cloud").glob("iteration_*/point_cloud.ply"),
                  key=lambda p: int(p.parent.name.split("_")[-1]) if p.parent.name.split("_")[-1].isdigit() else -1)
    return runs[-1] if runs else None


def discover(config: BuildConfig) -> tuple[list[SceneTask], list[SceneOutcome]]:
    """Scene tasks of the build, and failures found while listing (a bad layout fails its scenes only)."""
    from seggaussian.split import read_official_lists

    tasks: list[SceneTask] = []
    failures: list[SceneOutcome] = []
    wanted = set(config.scenes) if config.scenes else None
    for domain, root in layout_roots(config):
        read_code = code_hash(f"sources/{domain}.py", "sources/_common.py", "sources/replica_classes.py",
                              "sources/raycast.py", "classes.py", "scene.py", "cameras.py", "constants.py")
        read_code = sha256_json([read_code, data_specs_hash()])
        ids = sorted(reader(domain).list_scenes(root))
        if wanted is not None:
            ids = [s for s in ids if s in wanted]
        official = read_official_lists(root) if domain == "scannetpp" else {}
        prints = fingerprint_tree(root, ids)
        for scene_id in ids:
            ply = find_trained_ply(config.ply_dir, scene_id)
            tasks.append(SceneTask(scene_id, domain, root, sha256_json([prints[scene_id], read_code, domain]),
                                   ply, official.get(scene_id)))
    seen: dict[str, SceneTask] = {}
    for t in tasks:
        if t.scene_id in seen:
            failures.append(_failed(t, f"duplicate scene id (also in {seen[t.scene_id].root})", 0.0))
        seen[t.scene_id] = t
    if wanted:
        for missing in sorted(wanted - set(seen)):
            failures.append(SceneOutcome(missing, "?", None, "failed", (), "scene not found in the raw tree",
                                         {}, {}, {}, 0.0))
    dup = {f.scene_id for f in failures}
    return [t for t in seen.values() if t.scene_id not in dup], failures


# --- oracle Gaussians ----------------------------------------------------------------------------------
def scene_seed(seed: int, scene_id: str) -> int:
    """A per-scene seed: the run seed mixed with a stable hash of the scene id."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{scene_id}".encode()).digest()[:8], "little")


def sample_oracle_gaussians(
    points: np.ndarray,  # [P, 3]
    colors: np.ndarray,  # [P, 3] uint8
    semantic: np.ndarray,  # [P]
    faces: np.ndarray | None,  # [F, 3]
    config: OracleConfig,
    rng: np.random.Generator,
    cameras: tuple = (),
) -> tuple[Gaussians, np.ndarray]:
    """Gaussians sampled on the labelled mesh, flat along the face normal, and their ground-truth class
    ``[N]`` = the label of the sampled triangle's corner with the largest barycentric weight.

    With ``config.visible_only`` and cameras, samples are the first hits of rays through random pixels of
    the views (what a fitted 3DGS can reconstruct; no hidden contact faces such as a shelf's back against
    a wall); otherwise area-weighted over all triangles; on the points themselves for point clouds.
    """
    points = np.asarray(points, np.float64)
    n = int(config.num_gaussians)
    if n <= 0 or not len(points):
        return Gaussians.empty(), np.zeros(0, np.int32)
    faces = None if faces is None or not len(faces) else np.asarray(faces, np.int64)
    areas = cross = None
    if faces is not None:
        a, b, c = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
        cross = np.cross(b - a, c - a)
        areas = 0.5 * np.linalg.norm(cross, axis=1)
        areas[~(areas > MIN_TRIANGLE_AREA)] = 0.0
        if areas.sum() <= 0:
            faces = None
    if faces is None:
        idx = np.sort(rng.integers(0, len(points), n))
        extent = np.prod(np.maximum(points.max(0) - points.min(0), MIN_EXTENT)) ** (1 / 3)
        sigma = config.scale_factor * extent / max(1.0, n ** (1 / 3))
        return _oracle_gaussians(points[idx], np.asarray(colors, np.float64)[idx] / 255.0,
                                 np.tile([1.0, 0.0, 0.0, 0.0], (len(idx), 1)),
                                 np.full((len(idx), 3), sigma), config), np.asarray(semantic, np.int32)[idx]
    if config.visible_only and len(cameras):
        tri, bary, sigma = _sample_visible(points, faces, cameras, n, rng, config)
    else:
        cdf = np.cumsum(areas)
        tri = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(faces) - 1)
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # [n, 3]
        sigma = np.full(n, config.scale_factor * np.sqrt(areas.sum() / n))
    corners = faces[tri]  # [m, 3]
    means = np.einsum("nk,nkd->nd", bary, points[corners])
    rgb = np.einsum("nk,nkd->nd", bary, np.asarray(colors, np.float64)[corners]) / 255.0
    truth = np.asarray(semantic, np.int32)[corners[np.arange(len(tri)), np.argmax(bary, axis=1)]]
    normals = cross[tri] / np.maximum(2.0 * areas[tri], MIN_TRIANGLE_AREA)[:, None]
    scales = np.stack([sigma, sigma, sigma * config.thickness_ratio], axis=1)
    return _oracle_gaussians(means, rgb, quats_from_z_axis(normals), scales, config), truth


def _oracle_gaussians(means, rgb, quats, scales, config: OracleConfig) -> Gaussians:
    p = np.clip(config.opacity, OPACITY_EPS, 1 - OPACITY_EPS)
    return Gaussians.from_arrays(means, quats, np.log(np.maximum(scales, MIN_ORACLE_SCALE)),
                                 np.full(len(means), np.log(p / (1 - p))), (rgb - 0.5) / SH_C0)


def _sample_visible(points, faces, cameras, n, rng, config: OracleConfig):
    """First hits of ``n`` rays through uniformly random pixels of the cameras (open3d raycasting).

    Returns (triangle ids [m], barycentric weights [m, 3], in-plane sigma [m]); m <= n (misses dropped)."""
    import open3d as o3d

    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(points.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(faces.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    per_view = np.diff(np.linspace(0, n, len(cameras) + 1).round().astype(np.int64))
    rays, footprint = [], []
    for cam, m in zip(cameras, per_view):
        uv = rng.random((m, 2)) * [cam.width, cam.height]
        d_cam = np.concatenate([uv, np.ones((m, 1))], axis=1) @ np.linalg.inv(cam.K).T
        c2w = cam.c2w
        d_world = d_cam @ c2w[:3, :3].T
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        rays.append(np.concatenate([np.broadcast_to(c2w[:3, 3], (m, 3)), d_world], axis=1))
        # sample spacing on a fronto-parallel surface at unit depth
        footprint.append(np.full(m, np.sqrt(cam.width * cam.height / max(m, 1)) / cam.K[0, 0]))
    rays = np.concatenate(rays) if rays else np.zeros((0, 6))
    footprint = np.concatenate(footprint) if footprint else np.zeros(0)
    ans = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    hit = np.isfinite(t_hit) & (tri >= 0) & (tri < len(faces))
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    # In-plane size from the realized sample density: every view's samples land on the same surfaces, so a
    # per-view pixel footprint would overestimate the spacing by about sqrt(number of views).
    hit_points = rays[hit, :3] + rays[hit, 3:] * t_hit[hit, None]
    sigma = config.scale_factor * _mean_neighbour_distance(hit_points, fallback=t_hit[hit] * footprint[hit])
    return tri[hit], np.clip(bary[hit], 0.0, 1.0), sigma


#: Neighbours averaged for the in-plane spacing of sampled oracle Gaussians.
SPACING_NEIGHBOURS = 3


def _mean_neighbour_distance(points: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``[m]`` mean distance of each point to its SPACING_NEIGHBOURS nearest others (``fallback`` when too few)."""
    if len(points) <= SPACING_NEIGHBOURS:
        return fallback
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=SPACING_NEIGHBOURS + 1, workers=-1)
    spacing = d[:, 1:].mean(axis=1)
    return np.where(spacing > 0, spacing, fallback)


def quats_from_z_axis(normals: np.ndarray) -> np.ndarray:
    """``[N, 4]`` unit quaternions (w, x, y, z) rotating +z onto the (unit) ``normals`` [N, 3]."""
    z = np.array([0.0, 0.0, 1.0])
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), ANTIPODAL_EPS)
    axis = np.cross(np.broadcast_to(z, n.shape), n)
    w = 1.0 + n @ z
    q = np.concatenate([w[:, None], axis], axis=1)
    flip = w < ANTIPODAL_EPS  # normal = -z: rotate 180 degrees about x
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# --- stages -------------------------------------------------------------------------------------------
class _Stage:
    """Cache record of one stage of one scene (``<scene dir>/<stage>.json``)."""

    def __init__(self, scene_dir: Path, name: str):
        self.path = scene_dir / f"{name}.json"
        self.dir = scene_dir

    def cached(self, key: str, outputs: list[str]) -> dict | None:
        if not self.path.is_file():
            return None
        try:
            record = json.loads(self.path.read_text())
        except json.JSONDecodeError:
            return None
        if record.get("key") != key or not all((self.dir / o).is_file() for o in outputs):
            return None
        return record

    def save(self, key: str, info: dict, parts=None) -> None:
        """Record the stage as done; ``parts`` (what the key was made of) only helps explain cache misses."""
        from seggaussian.shards import write_json_atomic

        write_json_atomic(self.path, {"key": key, "info": info, "key_parts": json.loads(json.dumps(parts, default=str))})


def _save_npz(path: Path, **arrays) -> None:
    from seggaussian.atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def _load_gaussians_npz(path: Path) -> tuple[Gaussians, np.ndarray | None]:
    with np.load(path) as z:
        g = Gaussians(z["means"], z["quats"], z["log_scales"], z["opacity_logits"], z["sh"])
        truth = z["truth"] if "truth" in z.files and z["truth"].shape == (len(g),) else None
    return g, truth


def gaussians_stage_config(config: BuildConfig, task: SceneTask) -> dict:
    """What the gaussians stage depends on: mode, the fitting/oracle settings, the trained PLY's stat."""
    from seggaussian.fit import needs_fit

    if config.gaussians == "oracle":
        return {"mode": "oracle", "oracle": asdict(config.oracle), "seed": config.seed,
                "code": code_hash("gaussians.py") + str(ORACLE_VERSION)}
    if config.source == "ply" and task.trained_ply is None:
        raise FileNotFoundError(f"--source ply: no trained PLY for scene {task.scene_id} in {config.ply_dir}")
    if needs_fit(config.fit, task.trained_ply):
        fit_cfg = config.fit_config
        return {"mode": "fit", "fit": asdict(fit_cfg), "seed": config.seed,
                "code": code_hash("fit.py", "fit_config.py", "losses.py", "render", "gaussians.py")}
    if task.trained_ply is None:
        raise FileNotFoundError(f"--fit never: no trained PLY for scene {task.scene_id}")
    st = task.trained_ply.stat()
    return {"mode": "import", "ply": [str(task.trained_ply), st.st_size, st.st_mtime_ns],
            "code": code_hash("io", "gaussians.py")}


def run_gaussians(scene, config: BuildConfig, stage_cfg: dict, task: SceneTask) -> tuple[Gaussians, np.ndarray | None, dict]:
    """Gaussians of a scene by the stage's mode; returns (Gaussians, oracle truth or None, facts)."""
    mode = stage_cfg["mode"]
    if mode == "oracle":
        rng = np.random.default_rng(scene_seed(config.oracle.seed + config.seed, scene.scene_id))
        g, truth = sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces, config.oracle, rng,
                                           tuple(v.camera for v in scene.views))
        return g, truth, {"mode": "oracle"}
    if mode == "fit":
        from seggaussian.fit import fit_scene
        result = fit_scene(scene, config.fit_config, seed=scene_seed(config.seed, scene.scene_id) % 2**31,
                           progress=config.progress and config.jobs == 1)
        metrics = {k: v for k, v in result.metrics.items()
                   if k in ("novel_psnr", "novel_ssim", "novel_l1", "iterations", "early_stop_reason")}
        return result.gaussians, None, {"mode": "fit", "fit_metrics": metrics}
    from seggaussian.io.formats import read_gaussians

    g, report, _format = read_gaussians(task.trained_ply)
    g = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)  # labels come from the transfer
    return g, None, {"mode": "import", "ply": str(task.trained_ply)}


def run_transfer(scene, gaussians: Gaussians, truth: np.ndarray | None, config: BuildConfig) -> tuple[Gaussians, dict]:
    """Labels of the Gaussians (transfer + per-scene statistics and accuracy)."""
    from seggaussian.transfer import densify_labelled_mesh, label_accuracy, surface_labels, transfer_labels

    points, semantic, instance = scene.points, scene.semantic, scene.instance
    multilabel = scene.multilabel
    extra = 0
    if scene.faces is not None and len(scene.faces) and config.transfer.mesh_sample_spacing > 0:
        if multilabel is None:
            multilabel = np.full((len(points), 3), IGNORE_LABEL, np.int32)
            multilabel[:, 0] = semantic
        samples, (s_sem, s_inst, s_multi) = densify_labelled_mesh(
            points, scene.faces, config.transfer.mesh_sample_spacing, semantic, instance, multilabel)
        extra = len(samples)
        points = np.concatenate([points, samples])
        semantic, instance = np.concatenate([semantic, s_sem]), np.concatenate([instance, s_inst])
        multilabel = np.concatenate([multilabel, s_multi])
    result = transfer_labels(gaussians.means, points, semantic, instance, multilabel, config.transfer)
    if truth is None and len(gaussians):
        truth = surface_labels(gaussians.means, scene.points, scene.faces, scene.semantic)
    accuracy = label_accuracy(result.semantic, truth) if truth is not None else {"scored": 0, "correct": 0,
                                                                                   "accuracy": None}
    inst = result.instance
    if len(inst) and int(inst[inst != IGNORE_LABEL].max(initial=0)) >= IGNORE_LABEL:
        raise ValueError(f"scene {scene.scene_id}: instance ids >= {IGNORE_LABEL} do not fit a 16-bit label map")
    labelled = gaussians.with_extras(semantic=result.semantic, instance=result.instance,
                                     multilabel=result.multilabel, transfer_distance=result.distances)
    stats = result.stats.to_dict()
    stats["mesh_samples"] = extra
    return labelled, {"transfer": stats, "label_accuracy": accuracy}


def select_views(views, stride: int) -> list:
    """Every ``stride``-th train view plus every novel view, in source order."""
    out, k = [], 0
    for v in views:
        if v.role == "novel":
            out.append(v)
        else:
            if k % max(1, stride) == 0:
                out.append(v)
            k += 1
    return out


def view_scale(width: int, height: int, config: ViewConfig) -> float:
    scale = float(config.image_scale)
    if config.max_image_side and max(width, height) * scale > config.max_image_side:
        scale = config.max_image_side / max(width, height)
    return scale


def run_views(scene, gaussians: Gaussians, config: BuildConfig, num_classes: int) -> tuple[list, dict]:
    """One ViewRow per selected view: camera, RGB bytes, label maps rendered through the blend weights."""
    import cv2
    import torch

    from seggaussian.render import compute_blend_weights, render_label_maps
    from seggaussian.render.rasterize import camera_tensors
    from seggaussian.shards import ViewRow, encode_label_map, encode_rgb, image_format
    from seggaussian.sources._common import read_valid_mask

    t = gaussians.to_torch()
    semantic = torch.from_numpy(gaussians.extras["semantic"].astype(np.int64))
    instance = torch.from_numpy(gaussians.extras["instance"].astype(np.int64))
    rows = []
    for view in select_views(scene.views, config.views.view_stride):
        cam = view.camera
        scale = view_scale(cam.width, cam.height, config.views)
        if scale != 1.0:
            cam = cam.scaled(scale)
        what = f"scene {scene.scene_id} view {view.name}"
        if view.image_path is not None:
            data = Path(view.image_path).read_bytes()
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            if image is None:
                raise ValueError(f"{view.image_path}: image does not decode ({what})")
            if scale == 1.0 and image.shape[:2] == (cam.height, cam.width) and _is_png_or_jpeg(data):
                rgb_bytes = data  # stored as is (exact, no re-encoding)
            else:
                resized = cv2.resize(image, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
                rgb_bytes = encode_rgb(np.ascontiguousarray(resized[:, :, ::-1]))
        else:
            from seggaussian.render import render_gaussians

            out = render_gaussians(gaussians, cam)
            rgb = (out.image.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
            rgb_bytes = encode_rgb(rgb)
        image_format(rgb_bytes)
        if len(gaussians):
            viewmat, K = camera_tensors(cam)
            blend = compute_blend_weights(t["means"], t["quats"], t["log_scales"], t["opacity_logits"], viewmat, K,
                                          cam.width, cam.height, top_k=config.views.top_k)
            maps = render_label_maps(blend, semantic, instance, num_classes, min_alpha=config.views.min_alpha)
            sem_map = maps.semantic.numpy()
            inst_map = maps.instance.numpy()
        else:
            sem_map = np.full((cam.height, cam.width), IGNORE_LABEL, np.int64)
            inst_map = sem_map.copy()
        if view.mask_path is not None:  # anonymized pixels carry no label
            valid = read_valid_mask(view.mask_path, cam.width, cam.height)
            sem_map[~valid] = IGNORE_LABEL
            inst_map[~valid] = IGNORE_LABEL
        rows.append(ViewRow(view.name, view.role, cam, rgb_bytes, encode_label_map(sem_map), encode_label_map(inst_map),
                            float((sem_map != IGNORE_LABEL).mean())))
    coverage = [r.label_coverage for r in rows]
    return rows, {"num_views": len(rows), "novel_views": sum(r.role == "novel" for r in rows),
                  "label_coverage_mean": float(np.mean(coverage)) if coverage else 0.0}


def _is_png_or_jpeg(data: bytes) -> bool:
    return data[:8] == b"\x89PNG\r\n\x1a\n" or data[:3] == b"\xff\xd8\xff"


# --- one scene ----------------------------------------------------------------------------------------
def build_scene(task: SceneTask, config: BuildConfig, cache_root: Path) -> SceneOutcome:
    """Run the scene's stages that are not cached. Never raises: a failure is returned with its reason."""
    start = time.perf_counter()
    try:
        return _build_scene(task, config, cache_root, start)
    except Exception as exc:  # noqa: BLE001 -- one bad scene must not stop the others
        return _failed(task, f"{type(exc).__name__}: {exc}", time.perf_counter() - start,
                       trace=traceback.format_exc() if os.environ.get("SEGGAUSSIAN_DEBUG") else None)


def _failed(task: SceneTask, reason: str, seconds: float, trace: str | None = None) -> SceneOutcome:
    return SceneOutcome(task.scene_id, task.domain, task.official_split, "failed", (),
                        reason + (f"\n{trace}" if trace else ""), {}, {}, {}, seconds)


def _build_scene(task: SceneTask, config: BuildConfig, cache_root: Path, start: float) -> SceneOutcome:
    from seggaussian.shards import gaussians_table, views_table, write_parquet_atomic

    scene_dir = cache_root / "scenes" / task.scene_id
    scene_dir.mkdir(parents=True, exist_ok=True)
    class_names = read_class_names()
    g_cfg = gaussians_stage_config(config, task)
    parts = {
        "gaussians": [task.fingerprint, g_cfg],
        "transfer": [task.fingerprint, asdict(config.transfer), code_hash("transfer.py", "shards.py", "shard_schema.py")],
        "views": [asdict(config.views), len(class_names), code_hash("render", "shards.py", "shard_schema.py"),
                  VIEWS_VERSION],
    }
    keys = {"gaussians": sha256_json(parts["gaussians"])}
    keys["transfer"] = sha256_json([keys["gaussians"], *parts["transfer"]])
    keys["views"] = sha256_json([keys["transfer"], *parts["views"]])
    outputs = {"gaussians": ["gaussians.npz"], "transfer": ["gaussians.parquet"], "views": ["views.parquet"]}
    stages = {name: _Stage(scene_dir, name) for name in STAGES}
    records = {name: stages[name].cached(keys[name], outputs[name]) for name in STAGES}
    ran: list[str] = []
    scene = None
    gaussians = truth = labelled = None

    def get_scene():
        nonlocal scene
        if scene is None:
            if task.domain == "replica":  # rooms without pre-rendered views are rendered into the cache
                scene = reader("replica").read_scene(task.root, task.scene_id, cache_dir=cache_root / "replica_views")
            else:
                scene = reader(task.domain).read_scene(task.root, task.scene_id)
        return scene

    if records["gaussians"] is None:
        gaussians, truth, facts = run_gaussians(get_scene(), config, g_cfg, task)
        arrays = dict(means=gaussians.means, quats=gaussians.quats, log_scales=gaussians.log_scales,
                      opacity_logits=gaussians.opacity_logits, sh=gaussians.sh)
        if truth is not None:
            arrays["truth"] = truth
        _save_npz(scene_dir / "gaussians.npz", **arrays)
        facts["num_gaussians"] = len(gaussians)
        stages["gaussians"].save(keys["gaussians"], facts, parts["gaussians"])
        records["gaussians"] = {"info": facts}
        ran.append("gaussians")
    if records["transfer"] is None:
        if gaussians is None:
            gaussians, truth = _load_gaussians_npz(scene_dir / "gaussians.npz")
        labelled, facts = run_transfer(get_scene(), gaussians, truth, config)
        write_parquet_atomic(scene_dir / "gaussians.parquet", "gaussians", [gaussians_table(task.scene_id, labelled)],
                             config.shards)
        _save_npz(scene_dir / "labels.npz", semantic=labelled.extras["semantic"], instance=labelled.extras["instance"])
        stages["transfer"].save(keys["transfer"], facts, parts["transfer"])
        records["transfer"] = {"info": facts}
        ran.append("transfer")
    if records["views"] is None:
        if labelled is None:
            if gaussians is None:
                gaussians, _ = _load_gaussians_npz(scene_dir / "gaussians.npz")
            with np.load(scene_dir / "labels.npz") as z:
                labelled = gaussians.with_extras(semantic=z["semantic"], instance=z["instance"])
        rows, facts = run_views(get_scene(), labelled, config, len(class_names))
        write_parquet_atomic(scene_dir / "views.parquet", "views", [views_table(task.scene_id, rows)], config.shards)
        stages["views"].save(keys["views"], facts, parts["views"])
        records["views"] = {"info": facts}
        ran.append("views")
    info = {"source": task.domain}
    for name in STAGES:
        info.update(records[name]["info"])
    if "fit_metrics" in info:  # JSON-safe: drop non-finite numbers
        info["fit_metrics"] = {k: v for k, v in info["fit_metrics"].items()
                               if not isinstance(v, float) or np.isfinite(v)}
    info["num_gaussians"] = info.get("transfer", {}).get("num_gaussians", info.get("num_gaussians", 0))
    fragments = {"gaussians": scene_dir / "gaussians.parquet", "views": scene_dir / "views.parquet"}
    return SceneOutcome(task.scene_id, task.domain, task.official_split, "built" if ran else "skipped", tuple(ran),
                        None, info, fragments, keys, time.perf_counter() - start)


def _worker(task: SceneTask, config: BuildConfig, cache_root: Path, threads: int) -> SceneOutcome:
    """Process-pool / Ray entry point: cap torch threads, then build one scene."""
    try:
        import torch

        torch.set_num_threads(max(1, threads))
    except ImportError:
        pass
    return build_scene(task, config, cache_root)


# --- executors ----------------------------------------------------------------------------------------
def run_tasks(tasks: list[SceneTask], config: BuildConfig, cache_root: Path, on_done) -> list[SceneOutcome]:
    """Build every task with the configured executor; ``on_done(outcome)`` is called as scenes finish."""
    outcomes: list[SceneOutcome] = []
    jobs = max(1, int(config.jobs))
    threads = max(1, (os.cpu_count() or 1) // jobs)
    if config.executor == "ray":
        try:
            import ray
        except ImportError:
            raise RuntimeError("--executor ray needs Ray: pip install 'seggaussian[ray]' (or ray>=2.9)") from None
        if not ray.is_initialized():
            ray.init(address=config.address, include_dashboard=False, log_to_driver=False)
        remote = ray.remote(_worker)
        pending = [remote.remote(t, config, cache_root, threads) for t in tasks]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            outcome = ray.get(done[0])
            outcomes.append(outcome)
            on_done(outcome)
        return outcomes
    if config.executor != "local":
        raise ValueError(f"build: --executor must be local or ray, got {config.executor!r}")
    if jobs == 1 or len(tasks) <= 1:
        for t in tasks:
            outcome = build_scene(t, config, cache_root)
            outcomes.append(outcome)
            on_done(outcome)
        return outcomes
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    # spawn: numba's OpenMP layer and torch threads do not survive fork
    with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(_worker, t, config, cache_root, threads): t for t in tasks}
        for future in as_completed(futures):
            try:
                outcome = future.result()
            except Exception as exc:  # noqa: BLE001 -- a crashed worker fails its scene only
                outcome = _failed(futures[future], f"worker crashed: {type(exc).__name__}: {exc}", 0.0)
            outcomes.append(outcome)
            on_done(outcome)
    return outcomes


# --- the build ------------------------------------------------------------------------------------------
def build_dataset(config: BuildConfig) -> BuildReport:
    """Build (or update) the dataset in ``config.out``; see the module docstring."""
    start = time.perf_counter()
    out = Path(config.out)
    cache_root = out / CACHE_DIR
    synthesized: list[str] = []
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "the output is not a folder", str(out))
    ensure_writable_dir(out)  # fail before building scenes, not after
    if config.source == "synthetic" and not Path(config.root).exists():
        if not config.synthesize_missing:
            raise FileNotFoundError(f"{config.root}: no synthetic tree (write one with `seggaussian synth`)")
        synthesized = synthesize_default(config)
    if config.source == "ply" and config.ply_dir is None:
        raise ValueError("build: --source ply needs --ply-dir (trained PLYs)")
    swept = sweep_temps(out, recursive=True)  # leftovers of a killed earlier build
    tasks, failures = discover(config)
    if not tasks and not failures:
        raise ValueError(f"{config.root}: no scenes found in the raw tree (an empty source root is an error)")
    bars = _progress_bars(len(tasks), config.progress)
    outcomes = list(failures)

    def on_done(outcome: SceneOutcome) -> None:
        for name, bar in bars.items():
            if bar is not None:
                bar.update(1)
                if name in outcome.stages_run:
                    bar.set_postfix_str(f"last ran: {outcome.scene_id}", refresh=False)

    try:
        outcomes += run_tasks(tasks, config, cache_root, on_done)
    finally:
        for bar in bars.values():
            if bar is not None:
                bar.close()
    outcomes.sort(key=lambda o: o.scene_id)
    kept = _write_build_record(cache_root, config, outcomes)
    split_counts, files, nbytes, assembled = assemble(out, config)
    return BuildReport(out, outcomes, split_counts, files, nbytes, assembled, synthesized,
                       time.perf_counter() - start, tuple(kept), swept)


def _progress_bars(total: int, enabled: bool) -> dict:
    if not enabled or total == 0:
        return {name: None for name in STAGES}
    from tqdm import tqdm

    return {name: tqdm(total=total, desc=f"{name:9s}", unit="scene", position=i, leave=True)
            for i, name in enumerate(STAGES)}


def _write_build_record(cache_root: Path, config: BuildConfig, outcomes: list[SceneOutcome]) -> list[str]:
    """``.build/build.json``: every scene the shards publish (merged with earlier builds of other scenes).

    Policy for a scene that fails now but was built before: its last good copy stays published (its
    entry is kept) as long as its cached fragments are byte-identical to that copy (sha256 recorded per
    fragment); the caller warns and exits non-zero unless ``--keep-going``. Returns those scene ids.
    A failed scene with no intact earlier copy is left out.
    """
    from seggaussian.shards import sha256_file, write_json_atomic

    root = cache_root.parent
    path = cache_root / "build.json"
    previous = json.loads(path.read_text()) if path.is_file() else {}
    scenes = dict(previous.get("scenes", {}))
    if config.scenes is None:  # a full build: scenes no longer in the raw tree leave the dataset
        listed = {o.scene_id for o in outcomes}
        scenes = {s: v for s, v in scenes.items() if s in listed}
    kept = []
    for o in outcomes:
        if o.status == "failed":
            entry = scenes.get(o.scene_id)
            if entry is not None and _fragments_intact(root, entry):
                kept.append(o.scene_id)
            else:
                scenes.pop(o.scene_id, None)
            continue
        fragments = {k: str(Path(v).relative_to(root)) for k, v in o.fragments.items()}
        old = scenes.get(o.scene_id, {})
        digests = {k: (old["fragment_sha256"][k] if not o.stages_run and old.get("fragments", {}).get(k) == f
                       and k in old.get("fragment_sha256", {}) else sha256_file(root / f))
                   for k, f in fragments.items()}
        scenes[o.scene_id] = {"domain": o.domain, "official_split": o.official_split, "info": o.info,
                              "keys": o.keys, "fragments": fragments, "fragment_sha256": digests}
    # a scene whose cached fragments vanished is dropped rather than shipped broken
    scenes = {s: v for s, v in scenes.items() if all((root / f).is_file() for f in v["fragments"].values())}
    record = {"config_hash": content_config_hash(config), "config": _content_config(config),
              "scenes": dict(sorted(scenes.items()))}
    write_json_atomic(path, record)
    return kept


def _fragments_intact(root: Path, entry: dict) -> bool:
    """True when every cached fragment of a build-record entry still holds the bytes it recorded."""
    from seggaussian.shards import sha256_file

    digests = entry.get("fragment_sha256", {})
    return all(k in digests and (root / f).is_file() and sha256_file(root / f) == digests[k]
               for k, f in entry["fragments"].items())


def _content_config(config: BuildConfig) -> dict:
    d = config_dict(config)
    return {k: d[k] for k in ("source", "fit", "gaussians", "seed", "transfer", "oracle", "views", "shards")}


def assemble(out: Path, config: BuildConfig | None = None, split_config=None) -> tuple[dict, int, int, bool]:
    """Assign splits and write the split-named shards, manifest, card and splits.json of ``out``.

    Skips all writing when nothing that enters them changed since the last assembly.
    Returns (split counts, files, bytes, whether anything was (re)assembled).
    """
    from seggaussian.build_config import ShardConfig
    from seggaussian.shards import MANIFEST_NAME, SPLITS_NAME, write_dataset, write_json_atomic
    from seggaussian.split import SceneSplitInfo, assign_splits, read_splits, splits_payload

    out = Path(out)
    cache_root = out / CACHE_DIR
    path = cache_root / "build.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no build cache in {out} (run `seggaussian build` first)")
    record = json.loads(path.read_text())
    split_config = split_config or (config.split if config is not None else None)
    if split_config is None:
        from seggaussian.build_config import SplitConfig

        split_config = SplitConfig()
    shard_config = config.shards if config is not None else ShardConfig(**record["config"]["shards"])
    scenes = record["scenes"]
    infos = {s: SceneSplitInfo(v["domain"], v.get("official_split")) for s, v in scenes.items()}
    result = assign_splits(infos, split_config, read_splits(out / SPLITS_NAME))
    class_names = read_class_names()
    key = sha256_json([record["config_hash"], asdict(shard_config), result.assignments, class_names,
                       {s: [v["keys"], v["info"]] for s, v in scenes.items()}, code_hash("shards.py", "shard_schema.py")])
    state_path = cache_root / "assembly.json"
    state = json.loads(state_path.read_text()) if state_path.is_file() else {}
    manifest_path = out / MANIFEST_NAME
    if state.get("key") == key and manifest_path.is_file():
        manifest = json.loads(manifest_path.read_text())
        if all((out / rel).is_file() and (out / rel).stat().st_size == f["bytes"]
               for rel, f in manifest["files"].items()):
            write_json_atomic(out / SPLITS_NAME, splits_payload(result, split_config))
            return result.counts, len(manifest["files"]), sum(f["bytes"] for f in manifest["files"].values()), False
    payload = {s: dict(v["info"], fragments={k: out / f for k, f in v["fragments"].items()},
                       official_split=v.get("official_split"))
               for s, v in scenes.items()}
    manifest = write_dataset(out, result.assignments, payload, shard_config, class_names, record["config_hash"])
    write_json_atomic(out / SPLITS_NAME, splits_payload(result, split_config))
    write_json_atomic(state_path, {"key": key})
    return result.counts, len(manifest["files"]), sum(f["bytes"] for f in manifest["files"].values()), True


def split_dataset(out: Path, split_config) -> tuple[dict, dict, bool]:
    """``seggaussian split``: (re)assign splits with ``split_config`` and rewrite the split-named shards.
    Returns (counts, reasons, whether files were rewritten)."""
    from seggaussian.split import SceneSplitInfo, assign_splits, read_splits

    counts, _, _, assembled = assemble(out, None, split_config)
    record = json.loads((Path(out) / CACHE_DIR / "build.json").read_text())
    infos = {s: SceneSplitInfo(v["domain"], v.get("official_split")) for s, v in record["scenes"].items()}
    result = assign_splits(infos, replace(split_config, reassign=False), read_splits(Path(out) / "splits.json"))
    return counts, result.reasons, assembled


def export_scene_ply(dataset: Path, scene_id: str, out: Path, color_by: str | None = None) -> dict:
    """``seggaussian export-ply``: one scene's Gaussians with semantic and instance vertex properties.

    ``color_by`` (``semantic`` or ``instance``): the DC colour becomes the label's palette colour (higher SH
    zeroed, ``seggaussian.palette``) and a legend JSON + PNG is written beside ``out``.
    """
    from seggaussian.io.ply import write_gaussians_ply
    from seggaussian.palette import build_legend, colour_by_labels, write_legend
    from seggaussian.shards import find_split, read_scene

    split = find_split(dataset, scene_id)
    record = read_scene(dataset, split, scene_id, views=False)
    g = record.gaussians
    keep = {k: g.extras[k].astype(np.int32) for k in ("semantic", "instance")}
    keep["transfer_distance"] = g.extras["transfer_distance"].astype(np.float32)
    if color_by not in (None, "semantic", "instance"):
        raise ValueError(f"color_by must be semantic or instance, got {color_by!r}")
    plain = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, keep)
    if color_by is not None:
        plain = colour_by_labels(plain, keep[color_by])
    write_gaussians_ply(out, plain)
    legend = []
    if color_by is not None:
        names = read_class_names() if color_by == "semantic" else None
        legend = [str(p) for p in write_legend(out, build_legend(keep[color_by], color_by, names))]
    sem = keep["semantic"]
    return {"scene": scene_id, "split": split, "gaussians": len(g), "labelled": int((sem != IGNORE_LABEL).sum()),
            "out": str(out), "color_by": color_by, "legend": legend}


def summary_table(report: BuildReport) -> str:
    """Plain-text table: one line per scene (status, stages run, Gaussians, views, ignored share, reason)."""
    lines = [f"{'scene':24s} {'split-src':10s} {'status':8s} {'stages':26s} {'gaussians':>10s} {'views':>6s} "
             f"{'ignored':>8s} {'acc':>6s}  reason"]
    for o in report.outcomes:
        t = o.info.get("transfer", {})
        acc = o.info.get("label_accuracy", {}).get("accuracy")
        lines.append(
            f"{o.scene_id:24s} {o.domain:10s} {o.status:8s} {','.join(o.stages_run) or '-':26s} "
            f"{o.info.get('num_gaussians', 0):>10d} {o.info.get('num_views', 0):>6d} "
            f"{t.get('ignored_share', 0.0):>8.3f} {'' if acc is None else f'{acc:.3f}':>6s}  "
            f"{(o.reason or '').splitlines()[0] if o.reason else ''}"
        )
    return "\n".join(lines)
