"""Scene discovery of ``seggaussian build``: the scenes of the raw tree, each with a fingerprint of its raw files
and of the reader code, its trained PLY (if any) and its official split."""

from __future__ import annotations

import os
from pathlib import Path

from seggaussian.pipeline.cache import code_digest, sha256_json
from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.records import SceneOutcome, SceneTask, failed_outcome
from seggaussian.sources.synthetic import generate as synthetic
from seggaussian.sources.layout import layout_roots, reader
from seggaussian.pipeline.split import read_official_lists


def synthesize_default(config: BuildConfig) -> list[str]:
    """Write the default synthetic set (ScanNet++ and Replica layouts) into ``config.root``."""
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
    """``ply_dir/<scene>.ply`` (or ``.compressed.ply``, ``.splat``, ``.spz``, ``.ksplat``: any format ``io.formats``
    reads, detected by content) or the highest ``ply_dir/<scene>/point_cloud/iteration_*/point_cloud.ply``."""
    if ply_dir is None:
        return None
    for suffix in (".ply", ".compressed.ply", ".splat", ".spz", ".ksplat"):
        flat = Path(ply_dir) / f"{scene_id}{suffix}"
        if flat.is_file():
            return flat
    runs = sorted((Path(ply_dir) / scene_id / "point_cloud").glob("iteration_*/point_cloud.ply"),
                  key=lambda p: int(p.parent.name.split("_")[-1]) if p.parent.name.split("_")[-1].isdigit() else -1)
    return runs[-1] if runs else None


def find_transform_file(ply_dir: Path | None, scene_id: str) -> Path | None:
    """``ply_dir/<scene>.transform.json`` (the frame of that scene's trained splat), or None."""
    if ply_dir is None:
        return None
    path = Path(ply_dir) / f"{scene_id}.transform.json"
    return path if path.is_file() else None


def discover(config: BuildConfig) -> tuple[list[SceneTask], list[SceneOutcome]]:
    """Scene tasks of the build, and failures found while listing (a bad layout fails its scenes only)."""
    tasks: list[SceneTask] = []
    failures: list[SceneOutcome] = []
    wanted = set(config.scenes) if config.scenes else None
    for domain, root in layout_roots(config.source, config.root):
        read_code = code_digest(reader(domain).__name__)  # the reader's code and the data_specs it reads
        ids = sorted(reader(domain).list_scenes(root))
        if wanted is not None:
            ids = [s for s in ids if s in wanted]
        official = read_official_lists(root) if domain == "scannetpp" else {}
        prints = fingerprint_tree(root, ids)
        for scene_id in ids:
            ply = find_trained_ply(config.ply_dir, scene_id)
            tasks.append(SceneTask(scene_id, domain, root, sha256_json([prints[scene_id], read_code, domain]),
                                   ply, official.get(scene_id), find_transform_file(config.ply_dir, scene_id)))
    seen: dict[str, SceneTask] = {}
    for t in tasks:
        if t.scene_id in seen:
            failures.append(failed_outcome(t, f"duplicate scene id (also in {seen[t.scene_id].root})", 0.0))
        seen[t.scene_id] = t
    if wanted:
        for missing in sorted(wanted - set(seen)):
            failures.append(SceneOutcome(missing, "?", None, "failed", (), "scene not found in the raw tree",
                                         {}, {}, {}, 0.0))
    dup = {f.scene_id for f in failures}
    return [t for t in seen.values() if t.scene_id not in dup], failures
