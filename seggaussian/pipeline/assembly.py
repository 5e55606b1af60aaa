"""The build record and the assembly: which scenes the dataset publishes, and its split-named shards.

``DATASET/.build/build.json`` lists every scene the shards publish, with its cache keys, facts and the
sha256 of its cached fragments; ``assemble`` turns it into the split-named shards, manifest, dataset card
and ``splits.json`` (skipped when nothing that enters them changed); ``split_dataset`` reassigns splits.
"""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path

from seggaussian.pipeline import fragments as fragments_mod
from seggaussian.pipeline.cache import code_digest, sha256_json
from seggaussian.pipeline.config import BuildConfig, SplitConfig, config_dict
from seggaussian.shards.config import ShardConfig
from seggaussian.util.atomic import write_json_atomic
from seggaussian.pipeline.records import SceneOutcome
from seggaussian.core.constants import read_class_names
from seggaussian.util.jsonsafe import NAN_AS_NULL
from seggaussian.shards.files import sha256_file
from seggaussian.shards.layout import MANIFEST_NAME, SPLITS_NAME
from seggaussian.shards.writer import write_dataset
from seggaussian.pipeline.split import SceneSplitInfo, assign_splits, read_splits, splits_payload

CACHE_DIR = ".build"


def content_config_hash(config: BuildConfig) -> str:
    """Hash of every setting that changes dataset bytes (no paths, job counts or executors)."""
    d = config_dict(config)
    for k in ("root", "out", "scenes", "jobs", "executor", "address", "progress", "ply_dir",
              "synthesize_missing", "synthetic_counts", "split", "ray_cpus", "ray_memory_gb", "ray_retries",
              "ray_timeout", "ray_scene_timeout", "num_shards", "shard_index"):
        d.pop(k, None)
    return sha256_json(d)[:16]


def write_build_record(cache_root: Path, config: BuildConfig, outcomes: list[SceneOutcome]) -> list[str]:
    """``.build/build.json``: every scene the shards publish (merged with earlier builds of other scenes).

    Policy for a scene that fails now but was built before: its last good copy stays published (its
    entry is kept) as long as its cached fragments are byte-identical to that copy (sha256 recorded per
    fragment); the caller warns and exits non-zero unless ``--keep-going``. Returns those scene ids.
    A failed scene with no intact earlier copy is left out.
    """
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
        fragments = {k: fragments_mod.to_record(root, v) for k, v in o.fragments.items()}
        old = scenes.get(o.scene_id, {})
        digests = {k: _fragment_digest(root, k, f, old, reuse=not o.stages_run) for k, f in fragments.items()}
        scenes[o.scene_id] = {"domain": o.domain, "official_split": o.official_split, "info": o.info,
                              "keys": o.keys, "fragments": fragments, "fragment_sha256": digests}
    # a scene whose cached fragments vanished is dropped rather than shipped broken (those of the scenes built
    # now were checked by their workers)
    checked = {o.scene_id for o in outcomes if o.status != "failed"}
    scenes = {s: v for s, v in scenes.items()
              if s in checked or all(fragments_mod.present(root, f) for f in v["fragments"].values())}
    record = {"config_hash": content_config_hash(config), "config": _content_config(config),
              "scenes": dict(sorted(scenes.items()))}
    write_json_atomic(path, record, nan=NAN_AS_NULL, sort_keys=True, only_if_changed=True)
    return kept


def _fragment_digest(root: Path, table: str, fragment: str | dict, old: dict, reuse: bool) -> str:
    """sha256 of a recorded fragment: the file's (the earlier record's when ``reuse`` and it names the same file),
    or the rows' fingerprint (``shards.rows.SceneRows.sha256``)."""
    if isinstance(fragment, dict):
        return fragment["sha256"]
    if reuse and old.get("fragments", {}).get(table) == fragment and table in old.get("fragment_sha256", {}):
        return old["fragment_sha256"][table]
    return sha256_file(root / fragment)


def _fragments_intact(root: Path, entry: dict) -> bool:
    """True when every cached fragment of a build-record entry still holds the bytes it recorded (a file its sha256;
    rows in a shard their fingerprint)."""
    digests = entry.get("fragment_sha256", {})
    for k, f in entry["fragments"].items():
        if isinstance(f, dict):
            if not fragments_mod.present(root, f):
                return False
        elif not (k in digests and (root / f).is_file() and sha256_file(root / f) == digests[k]):
            return False
    return True


def _content_config(config: BuildConfig) -> dict:
    d = config_dict(config)
    return {k: d[k] for k in ("source", "fit", "gaussians", "seed", "transfer", "oracle", "views", "shards")}


def assemble(out: Path, config: BuildConfig | None = None, split_config=None) -> tuple[dict, int, int, bool]:
    """Assign splits and write the split-named shards, manifest, card and splits.json of ``out``.

    Skips all writing when nothing that enters them changed since the last assembly.
    Returns (split counts, files, bytes, whether anything was (re)assembled).
    """
    out = Path(out)
    cache_root = out / CACHE_DIR
    path = cache_root / "build.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no build cache in {out} (run `seggaussian build` first)")
    record = json.loads(path.read_text())
    split_config = split_config or (config.split if config is not None else None)
    if split_config is None:
        split_config = SplitConfig()
    shard_config = config.shards if config is not None else ShardConfig(**record["config"]["shards"])
    scenes = record["scenes"]
    infos = {s: SceneSplitInfo(v["domain"], v.get("official_split")) for s, v in scenes.items()}
    result = assign_splits(infos, split_config, read_splits(out / SPLITS_NAME))
    class_names = read_class_names()
    key = sha256_json([record["config_hash"], asdict(shard_config), result.assignments, class_names,
                       {s: [v["keys"], v["info"]] for s, v in scenes.items()}, code_digest("seggaussian.shards")])
    state_path = cache_root / "assembly.json"
    state = json.loads(state_path.read_text()) if state_path.is_file() else {}
    manifest_path = out / MANIFEST_NAME
    # nothing to write when the key is unchanged, the files are there and every scene's rows are in them already
    # (a scene served from a per-scene file has just been rebuilt: its shard was removed or changed)
    if state.get("key") == key and manifest_path.is_file() and all(
            isinstance(f, dict) for v in scenes.values() for f in v["fragments"].values()):
        manifest = json.loads(manifest_path.read_text())
        if all((out / rel).is_file() and (out / rel).stat().st_size == f["bytes"]
               for rel, f in manifest["files"].items()):
            write_json_atomic(out / SPLITS_NAME, splits_payload(result, split_config), nan=NAN_AS_NULL, sort_keys=True,
                              only_if_changed=True)
            return result.counts, len(manifest["files"]), sum(f["bytes"] for f in manifest["files"].values()), False
    payload = {s: dict(v["info"], fragments={k: fragments_mod.from_record(out, f) for k, f in v["fragments"].items()},
                       official_split=v.get("official_split"))
               for s, v in scenes.items()}
    manifest = write_dataset(out, result.assignments, payload, shard_config, class_names, record["config_hash"])
    write_json_atomic(out / SPLITS_NAME, splits_payload(result, split_config), nan=NAN_AS_NULL, sort_keys=True,
                      only_if_changed=True)
    write_json_atomic(state_path, {"key": key}, nan=NAN_AS_NULL, sort_keys=True, only_if_changed=True)
    # the cache keeps no copy of the shards' rows: pointers first, then the record naming them, then the files go
    pointed = fragments_mod.point_at_shards(out, cache_root, manifest, scenes)
    write_json_atomic(path, dict(record, scenes=pointed), nan=NAN_AS_NULL, sort_keys=True, only_if_changed=True)
    fragments_mod.drop_files(out, scenes, pointed)
    return result.counts, len(manifest["files"]), sum(f["bytes"] for f in manifest["files"].values()), True


def split_dataset(out: Path, split_config) -> tuple[dict, dict, bool]:
    """``seggaussian split``: (re)assign splits with ``split_config`` and rewrite the split-named shards.
    Returns (counts, reasons, whether files were rewritten)."""
    counts, _, _, assembled = assemble(out, None, split_config)
    record = json.loads((Path(out) / CACHE_DIR / "build.json").read_text())
    infos = {s: SceneSplitInfo(v["domain"], v.get("official_split")) for s, v in record["scenes"].items()}
    result = assign_splits(infos, replace(split_config, reassign=False), read_splits(Path(out) / "splits.json"))
    return counts, result.reasons, assembled
