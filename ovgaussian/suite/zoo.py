"""The splat zoo of the benchmark profile (``ovgaussian bench-suite --zoo``, issue #54 item 3).

A model should label a room whatever made its splat. The zoo writes four more renditions of every room of the
profile, each a dataset of the same raw rooms, split and labels (:data:`ovgaussian.suite.config.ZOO_RENDITIONS`):

- ``default-fit``: ``FitConfig()`` (the default preset, 100,000 Gaussians or more) stopped at
  ``SuiteConfig.zoo_fit_iterations`` (:func:`default_fit_config`);
- ``oracle``: the profile's control dataset (Gaussians sampled on the seen surfaces of the labelled mesh);
- ``scan``: one isotropic Gaussian per mesh vertex with its colour (``--gaussians scan``);
- ``split``: the profile fit with every Gaussian split in two as 3DGS splits (:func:`split_splat`), which the
  recipe never trains on;

beside the profile's own fits. Each rendition is scored (3D CSA on the val rooms, 3D CDA on the cross-domain
rooms) with the zoo's recipe (one run trained across renditions, :data:`ovgaussian.suite.config.ZOO_RUNS`), with
the model trained on that rendition alone (its matched run), and with both baselines. :func:`zoo_checks` holds the
recipe to ``min_share`` of the matched model, the ratio with its paired 95 % interval over the rooms, and above both
baselines with the intervals apart.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ovgaussian.bench.bootstrap import Interval, bootstrap_ratio, overlaps
from ovgaussian.data.augmentation import drawn_positions
from ovgaussian.suite.config import ZOO_RENDITIONS, SuiteConfig, ZooRendition
from ovgaussian.suite.report import interval_of
from seggaussian import shards
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.rotations import quats_to_rotmats
from seggaussian.fit.config import FitConfig
from seggaussian.io.ply.writer import write_gaussians_ply
from seggaussian.pipeline.config import BuildConfig, SplitConfig
from seggaussian.pipeline.dataset import build_dataset
from seggaussian.util.atomic import write_json_atomic

#: The zoo's metrics: (dimension, metric, split scored).
ZOO_METRICS = (("3d", "CSA", "val"), ("3d", "CDA", "xval"))
#: Who scores each rendition, in row order: the recipe, the rendition's matched run, the two baselines.
ZOO_SCORERS = ("recipe", "matched", "majority", "nearest-colour")
#: The zoo's recipe run (of ``ZOO_RUNS``).
RECIPE_RUN = "zoo"
#: Least Gaussians per room of the default-preset fit (issue #54).
DEFAULT_FIT_MIN_GAUSSIANS = 100_000
#: 3DGS's split: each child's scales are the parent's divided by this.
SPLIT_SCALE_DIVISOR = 1.6


def split_config(config: SuiteConfig) -> SplitConfig:
    """The profile's train / val / xval split (every dataset of the profile, every rendition, uses it)."""
    return SplitConfig(ratios=(*config.val_ratio, config.replica_scenes), seed=config.seed)


def default_fit_config(config: SuiteConfig) -> FitConfig:
    """``FitConfig()`` stopped at ``zoo_fit_iterations``, its schedule as it is (not rescaled), returning its last
    state: without evaluations on the way (``eval_every`` 0) no earlier, smaller state is picked, which the default's
    selection on the novel views did at iteration 250 of these rooms (about 90,000 Gaussians at 400 and 500
    iterations; 131,000-137,000 on three demo rooms at 500 without it)."""
    return replace(FitConfig(), iterations=config.zoo_fit_iterations, eval_every=0)


def zoo_datasets(config: SuiteConfig, splats: Path, oracle: Path) -> dict[str, Path]:
    """``{rendition name: dataset folder}`` of every rendition of :data:`ZOO_RENDITIONS`."""
    zoo = Path(config.out) / "zoo"
    return {"splats": splats, "oracle": oracle, "default-fit": zoo / "default-fit", "scan": zoo / "scan",
            "split": zoo / "split"}


def split_splat(g: Gaussians, rng: np.random.Generator) -> Gaussians:
    """Every Gaussian of ``g`` split in two as 3DGS splits: each child's centre drawn from the parent's
    Gaussian, its scales the parent's / 1.6, rotation, opacity and colour the parent's; the children of all
    parents first, then the second children (2N Gaussians)."""
    quats = g.quats.astype(np.float64)
    quats = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    rotmats, scales = quats_to_rotmats(quats), np.exp(g.log_scales.astype(np.float64))
    children = [drawn_positions(rng, g.means, rotmats, scales) for _ in range(2)]
    return Gaussians.from_arrays(
        np.concatenate(children), np.tile(g.quats, (2, 1)), np.tile(g.log_scales - np.log(SPLIT_SCALE_DIVISOR), (2, 1)),
        np.tile(g.opacity_logits, 2), np.tile(g.sh, (2, 1, 1)))


def write_split_splats(dataset: Path, out: Path, seed: int) -> list[Path]:
    """``out/<scene>.ply``: :func:`split_splat` of every scene of ``dataset`` (seeded per scene by its position in
    the sorted scene list). A file that exists is kept, so the split dataset's build cache stays valid."""
    manifest = shards.read_manifest(dataset)
    scenes = sorted(manifest["scenes"])
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for index, scene_id in enumerate(scenes):
        path = out / f"{scene_id}.ply"
        if not path.exists():
            g = shards.read_scene(dataset, manifest["scenes"][scene_id]["split"], scene_id, views=False).gaussians
            write_gaussians_ply(path, split_splat(g, np.random.default_rng([seed, index])))
        written.append(path)
    return written


def build_rendition(config: SuiteConfig, name: str, splats: Path, oracle: Path, slices: int = 1, index: int = 0
                    ) -> Path:
    """Build one rendition's dataset of every room of the profile, in this process (incremental: an unchanged one
    costs seconds). ``splats``, ``oracle``: the profile's datasets (the split rendition is made from ``splats``).
    ``slices`` > 1: only the rooms of slice ``index`` (``BuildConfig.num_shards``), so that several processes fit
    one rendition's rooms at once; a build with ``slices`` 1 then finds them cached and assembles the dataset."""
    raw, out = Path(config.out) / "raw", zoo_datasets(config, splats, oracle)[name]
    common = dict(source="synthetic", root=raw, out=out, jobs=1, seed=config.seed, progress=False,
                  split=split_config(config), synthesize_missing=False, num_shards=slices, shard_index=index)
    if name == "scan":
        build_dataset(BuildConfig(gaussians="scan", **common))
    elif name == "split":
        ply = Path(config.out) / "zoo" / "ply-split"
        write_split_splats(splats, ply, config.seed)
        build_dataset(BuildConfig(gaussians="fit", fit="never", ply_dir=ply, **common))
    elif name == "default-fit":
        build_dataset(BuildConfig(gaussians="fit", fit="always", fit_config=default_fit_config(config), **common))
    else:
        raise ValueError(f"zoo rendition {name!r}: only default-fit, scan and split are built here")
    return out


class ZooCell(NamedTuple):
    """One scorer on one rendition, one metric.

    Fields:
        value: mIoU (fraction) with its 95 % interval over the rooms.
        ratio: the recipe's mIoU over the matched run's on the same rooms, with its paired 95 % interval (the
            recipe's cells only; None elsewhere).
    """

    value: Interval
    ratio: Interval | None


def paired_ratio(top: dict, bottom: dict, dim: str, metric: str) -> Interval | None:
    """mIoU of ``top`` over ``bottom`` (two bench payloads of the same rooms) with its paired bootstrap interval
    over the rooms, on the classes ``top`` scores; None when they did not score the same rooms."""
    entry = top["metrics"].get(dim, {}).get(metric)
    other = bottom["metrics"].get(dim, {}).get(metric)
    if entry is None or other is None:
        return None
    key = f"{entry['split']}_{dim}"
    if top["dataset"]["scenes"].get(entry["split"]) != bottom["dataset"]["scenes"].get(entry["split"]):
        return None
    names = top["vocabulary"]["names"]
    classes = [names.index(n) for n in entry["classes"]]
    return bootstrap_ratio(np.asarray(top["scene_confusion"][key], dtype=np.int64),
                           np.asarray(bottom["scene_confusion"][key], dtype=np.int64), classes)


def zoo_cells(reports: dict) -> dict:
    """``{rendition: {scorer: {metric: ZooCell}}}`` from ``{rendition: {scorer: bench payload}}``."""
    cells: dict = {}
    for rendition, by_scorer in reports.items():
        for scorer, payload in by_scorer.items():
            for dim, metric, _ in ZOO_METRICS:
                ratio = (paired_ratio(payload, by_scorer["matched"], dim, metric)
                         if scorer == "recipe" and "matched" in by_scorer else None)
                cells.setdefault(rendition, {}).setdefault(scorer, {})[metric] = ZooCell(
                    interval_of(payload, dim, metric), ratio)
    return cells


def _shown(interval: Interval | None, scale: float, digits: int) -> str:
    """``value [low, high]`` times ``scale``; ``-`` without a value."""
    if interval is None or interval.value is None:
        return "-"
    value = f"{scale * interval.value:.{digits}f}"
    return value if interval.low is None else (
        f"{value} [{scale * interval.low:.{digits}f}, {scale * interval.high:.{digits}f}]")


def _pct(interval: Interval | None) -> str:
    return _shown(interval, 100.0, 1)


def _times(interval: Interval | None) -> str:
    return _shown(interval, 1.0, 2)


def format_zoo(cells: dict, gaussians: dict[str, list[int]], renditions: tuple[ZooRendition, ...] = ZOO_RENDITIONS
               ) -> str:
    """The zoo's cross tables (markdown): per metric, scorers x renditions (mIoU % with the 95 % interval over
    rooms), the recipe's ratio to each matched run (paired interval), and the Gaussians per room."""
    present = [r for r in renditions if r.name in cells]
    head = "| | " + " | ".join(r.label for r in present) + " |"
    rule = "|---|" + "---:|" * len(present)
    lines = []
    for dim, metric, split in ZOO_METRICS:
        lines += [f"{dim.upper()} {metric} ({split} rooms), mIoU % [95 % interval over rooms]:", "", head, rule]
        for scorer in ZOO_SCORERS:
            label = {"recipe": f"recipe ({RECIPE_RUN})", "matched": "trained on the rendition alone"}.get(
                scorer, f"{scorer} (baseline)")
            row = [_pct(cells[r.name][scorer][metric].value) if scorer in cells[r.name] else "-" for r in present]
            lines.append(f"| {label} | " + " | ".join(row) + " |")
        lines.append("| matched run | " + " | ".join(r.matched_run for r in present) + " |")
        lines += [f"| recipe / matched [paired 95 %] | " + " | ".join(
            _times(cells[r.name]["recipe"][metric].ratio) if "recipe" in cells[r.name] else "-" for r in present)
                  + " |", ""]
    lines += [head, rule]
    lines.append("| recipe trains on it | " + " | ".join("yes" if r.recipe_trains else "no" for r in present) + " |")
    lines.append("| Gaussians per room (min / median / max) | " + " | ".join(
        (lambda n: f"{min(n):,} / {int(np.median(n)):,} / {max(n):,}" if n else "-")(gaussians.get(r.name, []))
        for r in present) + " |")
    return "\n".join(lines) + "\n"


def zoo_checks(cells: dict, gaussians: dict[str, list[int]],
               renditions: tuple[ZooRendition, ...] = ZOO_RENDITIONS) -> dict:
    """Issue #54 item 3: ``{check: (passed, detail)}``. Per rendition: the recipe reaches ``min_share`` of its
    matched run on every metric (the ratio decides; its paired 95 % interval is in the detail), and beats both
    baselines with the intervals apart; the default-preset fit holds at least 100,000 Gaussians per room."""
    out = {}
    for r in renditions:
        if r.name not in cells:
            continue
        by = cells[r.name]
        ratios = {m: by["recipe"][m].ratio for _, m, _ in ZOO_METRICS}
        ok = all(i is not None and i.value is not None and i.value >= r.min_share for i in ratios.values())
        out[f"zoo: the recipe on the {r.label} >= {r.min_share:.2f} x the run trained on it alone ({r.matched_run})"] = (
            ok, "; ".join(f"3D {m} {_pct(by['recipe'][m].value)} vs {_pct(by['matched'][m].value)}: "
                          f"{_times(i)}" for m, i in ratios.items()))
        details, ok = [], True
        for _, metric, _ in ZOO_METRICS:
            mine = by["recipe"][metric].value
            for baseline in ("majority", "nearest-colour"):
                other = by[baseline][metric].value
                apart = overlaps(mine, other) is False
                ok = ok and mine.value is not None and other.value is not None and mine.value > other.value and apart
                details.append(f"3D {metric} {_pct(mine)} vs {baseline} {_pct(other)}")
        out[f"zoo: the recipe on the {r.label} beats both baselines, intervals apart"] = (bool(ok), "; ".join(details))
    counts = gaussians.get("default-fit")
    if counts:
        out[f"zoo: the default-preset fit holds >= {DEFAULT_FIT_MIN_GAUSSIANS:,} Gaussians per room"] = (
            min(counts) >= DEFAULT_FIT_MIN_GAUSSIANS, f"min {min(counts):,}, max {max(counts):,} over {len(counts)} rooms")
    return out


def scored_gaussians(dataset: Path) -> list[int]:
    """Gaussians per val and cross-domain room of a dataset (its manifest)."""
    scenes = shards.read_manifest(dataset)["scenes"]
    return [int(s["num_gaussians"]) for s in scenes.values() if s.get("split") in ("val", "xval")]


def write_zoo_summary(path: Path, cells: dict, gaussians: dict[str, list[int]]) -> None:
    """``zoo.json``: every cell's value, interval and ratio, and the Gaussians per room."""
    def entry(cell: ZooCell) -> dict:
        return {"miou": list(cell.value[:3]), "ratio_to_matched": None if cell.ratio is None else list(cell.ratio[:3])}

    write_json_atomic(path, {"cells": {r: {s: {m: entry(c) for m, c in by_m.items()} for s, by_m in by_s.items()}
                                       for r, by_s in cells.items()}, "gaussians": gaussians})
