"""One default threshold for every query: the viewer's calibrated relevancy against LERF's at 0.5 and against the
best threshold chosen per query (an oracle that reads the labels).

    .venv/bin/python benchmarks/relevancy_threshold.py --data out/demo/dataset --run out/demo/run \\
        --out benchmarks/results/relevancy.md

For every room of the splits (val and xval by default) and every ground-truth class with at least
``--min-gaussians`` Gaussians in it, the class's name is the query. A query's mask is the Gaussians the viewer
highlights (relevancy >= threshold, one query at a time); its IoU is taken with the class's Gaussians in the shard
labels. Five masks per query:

- ``LERF 0.5``: the LERF relevancy (pairwise softmax against the canonical negatives) at 0.5, the viewer's old default;
- ``LERF best``: the LERF relevancy at the threshold of highest IoU for this query (oracle);
- ``softmax 0.5``: the softmax against the run's vocabulary and the negatives at its training temperature, at 0.5,
  every offset 0 (``ovgaussian view --no-calibrate``);
- ``calibrated``: the viewer's calibrated relevancy at the default threshold: that softmax with each name's logit
  offset fitted on the run's **train** rooms (``ovgaussian.view.calibration.run_calibration``: fitted once, cached in
  the run folder; the val and xval labels are read here only to score);
- ``calibrated best``: the calibrated relevancy at its best threshold per query (oracle).

Oracle thresholds are searched over the 401 quantiles of each query's scores in the room. Means are over queries,
separately for the classes of the run's vocabulary and the others (names the run never saw in training); the gap of
the calibrated default to the LERF oracle comes with a 95 % interval from a bootstrap over the rooms.

A default must also leave a room alone when the queried thing is not there: every name of the run's vocabulary
that no Gaussian of the room carries is queried too, and the share of the room's Gaussians each default highlights
is reported (the best threshold has no meaning there).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: Quantiles of a query's scores tried as its oracle threshold.
ORACLE_QUANTILES = 401
METHODS = ("LERF 0.5", "LERF best", "softmax 0.5", "calibrated", "calibrated best")
#: Bootstrap draws of the gap's interval.
BOOTSTRAP_RESAMPLES = 2000
#: Defaults whose highlight of absent names is reported.
DEFAULTS = ("LERF 0.5", "softmax 0.5", "calibrated")


def iou(mask: np.ndarray, truth: np.ndarray) -> float:
    return float(np.count_nonzero(mask & truth)) / max(float(np.count_nonzero(mask | truth)), 1.0)


def best_iou(scores: np.ndarray, truth: np.ndarray) -> float:
    thresholds = np.unique(np.quantile(scores, np.linspace(0.0, 1.0, ORACLE_QUANTILES)))
    return max(iou(scores >= t, truth) for t in thresholds)


def measure(run: Path, data: Path, splits, min_gaussians: int, progress) -> tuple[list[dict], dict]:
    """Rows of one run and its calibration record (offsets per name and where they came from)."""
    from ovgaussian.predict.query import load_model_predictor
    from ovgaussian.view.calibration import run_calibration
    from ovgaussian.view.field import QueryField
    from ovgaussian.view.relevancy import CANONICAL_NEGATIVES, DEFAULT_THRESHOLD, relevancy
    from ovgaussian.view.scene import ViewScene
    from ovgaussian.view.session import run_temperature, run_vocabulary
    from ovgaussian.view.state import ViewerState
    from seggaussian import shards
    from seggaussian.core.constants import IGNORE_LABEL, read_class_names

    names = read_class_names()
    predictor = load_model_predictor(run)
    vocabulary = run_vocabulary(run)
    temperature = run_temperature(run)
    calibration = run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, temperature, progress)
    progress(f"{run.name}: {calibration.note}")
    if calibration.calibration is not None and Path(calibration.calibration.dataset).resolve() != Path(data).resolve():
        progress(f"{run.name}: calibrated on {calibration.calibration.dataset}, measured on {data}")
    rows = []
    for split in splits:
        for scene_id in shards.list_scenes(data, split):
            record = shards.read_scene(data, split, scene_id, views=False)
            semantic = np.asarray(record.gaussians.extras["semantic"]).astype(np.int64)
            field = QueryField.from_predictor(predictor, predictor.encode_gaussians(record.gaussians))
            scene = ViewScene(record.gaussians, f"{data}:{scene_id}")
            plain = ViewerState(scene, field, vocabulary, CANONICAL_NEGATIVES, temperature)
            state = ViewerState(scene, field, vocabulary, CANONICAL_NEGATIVES, temperature, calibration.offsets)
            negatives = field.scores(CANONICAL_NEGATIVES)
            ids, counts = np.unique(semantic[semantic != IGNORE_LABEL], return_counts=True)
            for class_id, count in zip(ids.tolist(), counts.tolist()):
                if count < min_gaussians or class_id >= len(names):
                    continue
                query = names[class_id]
                truth = semantic == class_id
                lerf = relevancy(field.scores((query,))[:, 0], negatives)
                softmax = plain.relevancies((query,))[:, 0]
                calibrated = state.relevancies((query,))[:, 0]
                rows.append({"run": str(run), "split": split, "scene": scene_id, "query": query, "gaussians": count,
                             "in_vocabulary": query in vocabulary,
                             "LERF 0.5": iou(lerf >= 0.5, truth), "LERF best": best_iou(lerf, truth),
                             "softmax 0.5": iou(softmax >= DEFAULT_THRESHOLD, truth),
                             "calibrated": iou(calibrated >= DEFAULT_THRESHOLD, truth),
                             "calibrated best": best_iou(calibrated, truth)})
            present = {names[i] for i in ids.tolist() if i < len(names)}
            for query in (name for name in vocabulary if name not in present):
                lerf = relevancy(field.scores((query,))[:, 0], negatives)
                rows.append({"run": str(run), "split": split, "scene": scene_id, "query": query, "gaussians": 0,
                             "absent": True, "LERF 0.5": float(np.mean(lerf >= 0.5)),
                             "softmax 0.5": float(np.mean(plain.relevancies((query,))[:, 0] >= DEFAULT_THRESHOLD)),
                             "calibrated": float(np.mean(state.relevancies((query,))[:, 0] >= DEFAULT_THRESHOLD))})
            progress(f"{run.name} {split} {scene_id}: {sum(r['scene'] == scene_id for r in rows)} queries")
    fitted = calibration.calibration
    record = {"run": str(run), "note": calibration.note,
              "offsets": {} if fitted is None else {n: o for n, o, k in zip(fitted.names, fitted.offsets, fitted.rooms)
                                                    if k > 0}}
    return rows, record


def gap_interval(rows: list[dict], resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> tuple[float, float]:
    """95 % interval of the mean gap (LERF best - calibrated) over ``rows``, by a bootstrap over their rooms (a room's
    queries are drawn together: they share one prediction)."""
    rooms = list(dict.fromkeys((r["split"], r["scene"]) for r in rows))
    gaps = [np.array([r["LERF best"] - r["calibrated"] for r in rows if (r["split"], r["scene"]) == room])
            for room in rooms]
    rng = np.random.default_rng(seed)
    means = []
    for _ in range(resamples):
        draw = np.concatenate([gaps[i] for i in rng.integers(0, len(rooms), len(rooms))])
        means.append(draw.mean())
    return float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def summary(rows: list[dict]) -> list[tuple]:
    """Per run and vocabulary group: queries, mean IoU of each method, gap of the default to the LERF oracle and its
    95 % interval (``gap_interval``)."""
    out = []
    for run in dict.fromkeys(r["run"] for r in rows):
        for group, flag in (("in vocabulary", True), ("not in vocabulary", False)):
            sel = [r for r in rows if r["run"] == run and not r.get("absent") and r["in_vocabulary"] == flag]
            if not sel:
                continue
            means = [float(np.mean([r[m] for r in sel])) for m in METHODS]
            out.append((run, group, len(sel), *means, means[METHODS.index("LERF best")]
                        - means[METHODS.index("calibrated")], *gap_interval(sel)))
    return out


def absent_table(rows: list[dict]) -> str:
    """Per run: queries of names absent from their room, and the mean share of the room each default highlights."""
    lines = ["| run | absent queries | " + " | ".join(f"{m} highlights" for m in DEFAULTS) + " |",
             "|---|---|" + "---|" * len(DEFAULTS)]
    for run in dict.fromkeys(r["run"] for r in rows):
        sel = [r for r in rows if r["run"] == run and r.get("absent")]
        if sel:
            lines.append(f"| {Path(run).name} | {len(sel)} | "
                         + " | ".join(f"{100 * np.mean([r[m] for r in sel]):.2f} %" for m in DEFAULTS) + " |")
    return "\n".join(lines)


def offsets_table(records: list[dict]) -> str:
    """Per run: each name's fitted offset (its threshold on the softmax probability; "-": too rare in the train rooms,
    offset 0) and where they came from."""
    names = list(dict.fromkeys(n for r in records for n in r["offsets"]))
    lines = ["| run | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for r in records:
        cells = [f"{r['offsets'][n]:+.2f} ({1 / (1 + np.exp(-r['offsets'][n])):.2f})" if n in r["offsets"] else "-"
                 for n in names]
        lines.append(f"| {Path(r['run']).name} | " + " | ".join(cells) + " |")
    notes = "\n".join(f"- {Path(r['run']).name}: {r['note']}" for r in records)
    return "\n".join(lines) + "\n\n" + notes


def table(rows: list[dict]) -> str:
    lines = ["| run | queries | n | " + " | ".join(METHODS) + " | LERF best - calibrated | 95 % interval (rooms) |",
             "|---|---|---|" + "---|" * (len(METHODS) + 2)]
    for run, group, n, *values in summary(rows):
        means, gap, low, high = values[:-3], *values[-3:]
        lines.append(f"| {Path(run).name} | {group} | {n} | " + " | ".join(f"{v:.3f}" for v in means)
                     + f" | {gap:.4f} | {low:.4f} to {high:.4f} |")
    return "\n".join(lines)


def per_query_table(rows: list[dict]) -> str:
    lines = ["| run | split | room | query | Gaussians | " + " | ".join(METHODS) + " |",
             "|---|---|---|---|---|" + "---|" * len(METHODS)]
    for r in rows:
        if not r.get("absent") and r["in_vocabulary"]:
            lines.append(f"| {Path(r['run']).name} | {r['split']} | {r['scene']} | {r['query']} | {r['gaussians']:,} | "
                         + " | ".join(f"{r[m]:.3f}" for m in METHODS) + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (seggaussian build + split)")
    parser.add_argument("--run", type=Path, action="append", required=True, help="run folder (repeat for several)")
    parser.add_argument("--splits", default="val,xval", help="comma-separated splits whose rooms are measured")
    parser.add_argument("--min-gaussians", type=int, default=20, help="smallest class (Gaussians in a room) queried")
    parser.add_argument("--out", type=Path, default=None, help="write the tables as Markdown here")
    args = parser.parse_args()

    from seggaussian.util.atomic import atomic_path
    from seggaussian.util.threads import cap_threads

    cap_threads(2)
    splits = [s.strip() for s in args.splits.split(",") if s.strip()]
    rows, records = [], []
    for run in args.run:
        more, record = measure(run, args.data, splits, args.min_gaussians,
                               lambda m: print(m, file=sys.stderr, flush=True))
        rows += more
        records.append(record)
    if not rows:
        print(f"relevancy: no class with >= {args.min_gaussians} Gaussians in {args.data} ({', '.join(splits)})",
              file=sys.stderr)
        return 1
    text = table(rows) + "\n\n" + absent_table(rows)
    print(text)
    if args.out is not None:
        from ovgaussian.view.relevancy import DEFAULT_THRESHOLD

        doc = (f"# Relevancy: one default threshold for every query\n\n"
               f"`benchmarks/relevancy_threshold.py --data DATA {' '.join('--run ' + r.name for r in args.run)} "
               f"--splits {','.join(splits)}`: the rooms of {', '.join(splits)}, each ground-truth class with at "
               f"least {args.min_gaussians} Gaussians queried by its name; per-Gaussian IoU of the highlighted "
               f"Gaussians with the class's (mean over queries). Default threshold: {DEFAULT_THRESHOLD}; "
               f"\"softmax 0.5\": every offset 0 (`--no-calibrate`); \"calibrated\": each name's offset fitted on "
               f"the run's train rooms (`ovgaussian.view.calibration`). "
               f"\"best\": the threshold of highest IoU chosen per query with the labels (oracle).\n\n"
               f"{text}\n\n## Offsets fitted on the train rooms (threshold on the softmax probability; "
               f"-: too rare there, offset 0)\n\n"
               f"{offsets_table(records)}\n\n"
               f"## Per query (classes of the run's vocabulary)\n\n{per_query_table(rows)}\n")
        with atomic_path(args.out, suffix=".md") as tmp:
            tmp.write_text(doc)
    gaps = [s[-3] for s in summary(rows) if s[1] == "in vocabulary"]
    absent = sum(bool(r.get("absent")) for r in rows)
    print(f"relevancy: {len(rows)} queries ({absent} of absent names); in-vocabulary gap of the calibrated default to "
          f"the per-query best (LERF): {', '.join(f'{g:.4f}' for g in gaps)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
