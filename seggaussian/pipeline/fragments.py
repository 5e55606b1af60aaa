"""A scene's per-scene tables in the build cache: a file until the assembly copies it into a shard, then a pointer.

    .build/scenes/<scene>/gaussians.parquet   the transfer stage's table (until assembled)
    .build/scenes/<scene>/views.parquet       the views stage's table (until assembled)
    .build/scenes/<scene>/shards.json         once assembled: per table, the scene's rows in the shard
                                              (``shards.rows.SceneRows``) and the key of the stage that made them

The cache never keeps what the shards hold (``point_at_shards``): after an assembly the files go and a later build
reads an unchanged scene's rows from the shard (``shards.rows``: its size and a sha256 of the scene's bytes are
checked first). A pointer holding another key than the stage's, or a shard removed or changed since, is a cache
miss: the stage runs again and writes its file again. A file, when present, is used before a pointer.
"""

from __future__ import annotations

import json
from pathlib import Path

from seggaussian.shards.rows import SceneRows, locate_scenes, rows_intact
from seggaussian.shards.schema import GAUSSIANS_TABLE, VIEWS_TABLE
from seggaussian.util.atomic import write_json_atomic

#: The scene's pointer record.
POINTERS = "shards.json"
#: The table each stage writes (its per-scene file is the stage's output).
STAGE_TABLES = {"transfer": GAUSSIANS_TABLE, "views": VIEWS_TABLE}
TABLE_STAGES = {table: stage for stage, table in STAGE_TABLES.items()}


def read_pointers(scene_dir: Path) -> dict:
    """The scene's pointer record ({table: {"key": stage key, "rows": SceneRows fields}}), {} when none or unreadable."""
    path = Path(scene_dir) / POINTERS
    try:
        record = json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError):
        return {}
    return record if isinstance(record, dict) else {}


def _rows(entry) -> SceneRows | None:
    try:
        return SceneRows(**entry["rows"])
    except (KeyError, TypeError):
        return None


def cached(dataset: Path, file: Path, entry: dict | None, key: str) -> Path | SceneRows | None:
    """The scene's table as the stage with ``key`` made it: its per-scene ``file`` when present, else the rows its
    pointer ``entry`` names when the entry holds ``key`` and the shard still holds them; None: the stage runs."""
    if file.is_file():
        return file
    if not isinstance(entry, dict) or entry.get("key") != key:
        return None
    rows = _rows(entry)
    return rows if rows is not None and rows_intact(dataset, rows) else None


def to_record(dataset: Path, fragment: Path | SceneRows) -> str | dict:
    """A fragment as ``.build/build.json`` keeps it: the file's path relative to ``dataset``, or the rows' fields."""
    if isinstance(fragment, SceneRows):
        return fragment._asdict()
    return str(Path(fragment).relative_to(dataset))


def from_record(dataset: Path, value: str | dict) -> Path | SceneRows:
    """What ``to_record`` wrote, back."""
    return SceneRows(**value) if isinstance(value, dict) else Path(dataset) / value


def location(dataset: Path, fragment: Path | SceneRows) -> Path:
    """The file a fragment is read from (for messages): its per-scene file, or the shard holding its rows."""
    if isinstance(fragment, SceneRows):
        return Path(dataset) / fragment.shard if fragment.shard is not None else Path(dataset)
    return Path(fragment)


def present(dataset: Path, value: str | dict) -> bool:
    """True when a recorded fragment can still be read: the file exists, or the shard still holds the rows."""
    fragment = from_record(dataset, value)
    return rows_intact(dataset, fragment) if isinstance(fragment, SceneRows) else fragment.is_file()


def point_at_shards(dataset: Path, cache_root: Path, manifest: dict, scenes: dict) -> dict:
    """After an assembly: each published scene's rows located in the shards the ``manifest`` lists, written to its
    pointer record; returns ``scenes`` (the build record's entries) with those fragments. The caller writes the build
    record, then calls ``drop_files`` (a kill in between leaves the files, which the next assembly uses again)."""
    dataset = Path(dataset)
    located: dict[str, dict[str, SceneRows]] = {}
    for rel, info in manifest["files"].items():
        table = rel.split("/", 1)[0]
        ids = [s for s in info["scenes"] if s in scenes]
        plan = {}
        for s in ids:
            fragment = from_record(dataset, scenes[s]["fragments"][table])
            plan[s] = fragment.plan_bytes if isinstance(fragment, SceneRows) else fragment.stat().st_size
        for s, rows in locate_scenes(dataset, rel, table, ids, plan).items():
            located.setdefault(s, {})[table] = rows
    updated = dict(scenes)
    for s, tables in sorted(located.items()):
        entry = scenes[s]
        pointers = {table: {"key": entry["keys"][TABLE_STAGES[table]], "rows": rows._asdict()}
                    for table, rows in sorted(tables.items())}
        write_json_atomic(Path(cache_root) / "scenes" / s / POINTERS, pointers, sort_keys=True, only_if_changed=True)
        fragments = dict(entry["fragments"])
        digests = dict(entry.get("fragment_sha256", {}))
        for table, rows in tables.items():
            fragments[table] = to_record(dataset, rows)
            digests[table] = rows.sha256
        updated[s] = dict(entry, fragments=fragments, fragment_sha256=digests)
    return updated


def drop_files(dataset: Path, before: dict, after: dict) -> int:
    """Remove the per-scene files that the build record named ``before`` an assembly and no longer names ``after``
    it (their rows are in the shards now); returns how many."""
    removed = 0
    for s, entry in before.items():
        kept = set(v for v in after.get(s, {}).get("fragments", {}).values() if isinstance(v, str))
        for value in entry["fragments"].values():
            if isinstance(value, str) and value not in kept and (Path(dataset) / value).is_file():
                (Path(dataset) / value).unlink()
                removed += 1
    return removed
