"""``seggaussian inspect DATASET``: a dataset's summary from its manifest, and the files that differ from it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.shards.files import sha256_file
from seggaussian.shards.layout import SPLITS
from seggaussian.shards.read import read_manifest


def inspect_dataset(path: Path, *, verify: bool = False) -> dict:
    """Summary of a dataset folder: per-split scene counts, class histogram, transfer statistics, files.

    Reads only the manifest and the files' sizes (no row data); flags files missing or changed in size,
    and with ``verify`` files whose sha256 differs from the manifest's (each problem names the file and
    its scenes).
    """
    dataset = Path(path)
    manifest = read_manifest(dataset)
    scenes = manifest.get("scenes", {})
    class_names = manifest.get("class_names", [])
    per_split: dict[str, dict] = {}
    for split in SPLITS:
        ids = sorted(s for s, i in scenes.items() if i.get("split") == split)
        hist: dict[int, int] = {}
        ignored = gaussians = views = 0
        shares, q50, q99, accuracies = [], [], [], []
        for s in ids:
            info = scenes[s]
            t = info.get("transfer", {})
            for k, c in t.get("class_histogram", {}).items():
                hist[int(k)] = hist.get(int(k), 0) + int(c)
            ignored += int(t.get("ignored", 0))
            gaussians += int(info.get("num_gaussians", 0))
            views += int(info.get("num_views", 0))
            shares.append(float(t.get("ignored_share", 0.0)))
            q50.append(float(t.get("distance_quantiles", {}).get("q50", 0.0)))
            q99.append(float(t.get("distance_quantiles", {}).get("q99", 0.0)))
            acc = info.get("label_accuracy", {}).get("accuracy")
            if acc is not None:
                accuracies.append(acc)
        per_split[split] = {
            "scenes": len(ids),
            "gaussians": gaussians,
            "views": views,
            "ignored_share": (ignored / gaussians) if gaussians else 0.0,
            "ignored_share_max": max(shares) if shares else 0.0,
            "distance_q50_median": float(np.median(q50)) if q50 else 0.0,
            "distance_q99_max": max(q99) if q99 else 0.0,
            "label_accuracy_min": min(accuracies) if accuracies else None,
            "class_histogram": {
                (class_names[k] if k < len(class_names) else str(k)): c for k, c in sorted(hist.items())
            },
        }
    problems = []
    for rel, f in sorted(manifest.get("files", {}).items()):
        p = dataset / rel
        whose = f" (scenes {', '.join(f.get('scenes', []))})" if f.get("scenes") else ""
        if not p.is_file():
            problems.append(f"{rel}: missing{whose}")
        elif p.stat().st_size != f["bytes"]:
            problems.append(f"{rel}: {p.stat().st_size} bytes, manifest says {f['bytes']}{whose}")
        elif verify and sha256_file(p) != f["sha256"]:
            problems.append(f"{rel}: sha256 differs from the manifest{whose}")
    counts = " / ".join(f"{per_split[s]['scenes']} {s}" for s in SPLITS)
    total_g = sum(v["gaussians"] for v in per_split.values())
    total_ignored = sum(v["ignored_share"] * v["gaussians"] for v in per_split.values())
    summary = (f"dataset {dataset}: {counts} scenes, {total_g} Gaussians, "
               f"{100 * total_ignored / total_g if total_g else 0.0:.1f}% ignored"
               + (f", {len(problems)} problem(s)" if problems else ""))
    return {
        "summary": summary,
        "path": str(dataset),
        "schema_version": manifest.get("schema_version"),
        "config_hash": manifest.get("config_hash"),
        "num_classes": len(class_names),
        "splits": per_split,
        "scenes": {s: {k: scenes[s].get(k) for k in ("split", "source", "num_gaussians", "num_views")}
                   for s in sorted(scenes)},
        "files": len(manifest.get("files", {})),
        "bytes": sum(f["bytes"] for f in manifest.get("files", {}).values()),
        "problems": problems,
        "verified": verify,
    }
