"""Benchmark: one trained model scored on several renditions of the same rooms (a splat zoo).

A model should label a room whatever made its splat. For the val and cross-domain rooms of a built dataset, this
writes renditions of each room, builds each as its own dataset (the same raw tree, so the same labels, split and
views), and scores every given run on every rendition (3D CSA on the val rooms, 3D CDA on the cross-domain rooms,
K = 20, ``ovgaussian bench``):

- ``own``: the dataset itself (the fits the runs were trained on, or their like);
- ``default-fit``: ``seggaussian fit`` with the default preset under a time budget (``--fit-seconds``);
- ``oracle``: Gaussians sampled on the seen surfaces of the labelled mesh (``seggaussian build --gaussians oracle``);
- ``scan``: one isotropic Gaussian per mesh vertex with its colour (a scan turned into splats,
  ``seggaussian build --gaussians scan``);
- ``split``: the own fit densified, every Gaussian split in two as 3DGS splits (children drawn from the parent,
  scales / 1.6), which no run trains on.

Prints a markdown table (runs x renditions) and writes it with the numbers as JSON (``--out``). Example (the demo):

    .venv/bin/python benchmarks/renditions.py --raw out/demo/raw --data out/demo/dataset \\
        --run robust=out/demo/run --work out/renditions --out out/renditions/table.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
BIN = Path(sys.executable).parent

def run(cmd: list[str]) -> str:
    result = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, cwd=REPO)
    if result.returncode:
        raise SystemExit(f"failed ({result.returncode}): {' '.join(map(str, cmd))}\n{result.stdout}\n{result.stderr}")
    return result.stdout


def scored_scenes(data: Path) -> tuple[list[str], list[str]]:
    from seggaussian.shards.read import list_scenes

    return list_scenes(data, "val"), list_scenes(data, "xval")


def scene_gaussians(data: Path, scene_id: str):
    """The Gaussians of ``scene_id`` in ``data`` (whichever split holds it)."""
    from seggaussian.shards.read import read_manifest, read_scene

    split = read_manifest(data)["scenes"][scene_id]["split"]
    return read_scene(data, split, scene_id, views=False).gaussians


def write_split_splats(data: Path, scenes: list[str], out: Path, seed: int) -> None:
    """``out/<scene>.ply``: the dataset's Gaussians of each scene, every one split in two (3DGS's split,
    ``ovgaussian.suite.zoo.split_splat``; kept when present, so the split datasets of several runs' benches are the
    same)."""
    from ovgaussian.suite.zoo import split_splat
    from seggaussian.io.ply.writer import write_gaussians_ply

    out.mkdir(parents=True, exist_ok=True)
    for scene_id in scenes:
        if not (out / f"{scene_id}.ply").exists():  # kept: the rendition datasets' build caches stay valid
            rng = np.random.default_rng([seed, scenes.index(scene_id)])
            write_gaussians_ply(out / f"{scene_id}.ply", split_splat(scene_gaussians(data, scene_id), rng))


def write_default_fits(raw: Path, scenes: list[str], out: Path, seconds: float) -> None:
    """``out/<scene>.ply``: ``seggaussian fit`` with the default preset and a time budget (kept when present)."""
    out.mkdir(parents=True, exist_ok=True)
    for scene_id in scenes:
        if not (out / f"{scene_id}.ply").exists():
            run([BIN / "seggaussian", "fit", "--root", raw, "--scene", scene_id, "--out", out / f"{scene_id}.ply",
                 "--time-budget", seconds, "--no-progress"])


def build(raw: Path, out: Path, scenes: list[str], extra: list) -> None:
    run([BIN / "seggaussian", "build", "--source", "synthetic", "--root", raw, "--out", out,
         "--scenes", ",".join(scenes), "--jobs", 2, "--no-progress", *extra])
    run([BIN / "seggaussian", "split", "--data", out])


def score(data: Path, run_dir: Path, metric: str, report: Path) -> float | None:
    """3D mIoU (percent) of ``metric`` for the run on ``data`` (``ovgaussian bench``; its report kept at ``report``)."""
    run([BIN / "ovgaussian", "bench", "--data", data, "--run", run_dir, "--metric", metric, "--dim", "3d",
         "--classes", 20, "--out", report, "--no-progress"])
    value = json.loads(report.read_text())["row"].get(f"3d_{metric.upper()}")
    return None if value is None else 100.0 * float(value)


def report_interval(report: Path, base: Path, metric: str) -> dict:
    """The 95 % bootstrap intervals over rooms of one cell (from its ``ovgaussian bench`` report): the mIoU's, and
    the paired ratio to the ``base`` report's (the run on its own rendition: the same rooms, one draw for both;
    ``ovgaussian.suite.zoo.paired_ratio``)."""
    from ovgaussian.suite.zoo import paired_ratio

    cell, own = json.loads(report.read_text()), json.loads(base.read_text())
    entry = cell["metrics"]["3d"][metric.upper()]
    ratio = paired_ratio(cell, own, "3d", metric.upper())
    return {"miou_ci95": entry.get("ci95"), "rooms": entry["num_scenes"],
            "ratio_to_own": None if ratio is None else ratio.value,
            "ratio_ci95": None if ratio is None or ratio.low is None else [ratio.low, ratio.high]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--raw", type=Path, required=True, help="raw tree the dataset was built from (seggaussian synth)")
    parser.add_argument("--data", type=Path, required=True, help="the dataset the runs were trained on")
    parser.add_argument("--run", action="append", required=True, help="NAME=RUN_DIR, repeatable")
    parser.add_argument("--work", type=Path, required=True, help="folder for the renditions and their datasets")
    parser.add_argument("--fit-seconds", type=float, default=90.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    runs = dict(item.split("=", 1) for item in args.run)
    val, xval = scored_scenes(args.data)
    scenes = val + xval
    work = args.work
    datasets = {"own": args.data}
    write_split_splats(args.data, scenes, work / "ply" / "split", args.seed)
    write_default_fits(args.raw, scenes, work / "ply" / "default-fit", args.fit_seconds)
    for name in ("default-fit", "split"):
        datasets[name] = work / "data" / name
        build(args.raw, datasets[name], scenes, ["--ply-dir", work / "ply" / name, "--fit", "never"])
    for name in ("scan", "oracle"):
        datasets[name] = work / "data" / name
        build(args.raw, datasets[name], scenes, ["--gaussians", name])
    table: dict = {"scenes": {"val": val, "xval": xval}, "gaussians": {}, "scores": {}}
    for name, data in datasets.items():
        table["gaussians"][name] = {s: len(scene_gaussians(data, s).means) for s in scenes}
    for run_name, run_dir in runs.items():
        for name, data in datasets.items():
            for metric in ("csa", "cda"):
                report = work / "reports" / f"{run_name}-{name}-{metric}.json"
                report.parent.mkdir(parents=True, exist_ok=True)
                table["scores"].setdefault(run_name, {}).setdefault(name, {})[metric] = score(
                    data, Path(run_dir), metric, report)
    for run_name in runs:  # intervals over rooms, and each rendition's ratio to the run's own fit
        for name in datasets:
            for metric in ("csa", "cda"):
                report = work / "reports" / f"{run_name}-{name}-{metric}.json"
                base = work / "reports" / f"{run_name}-own-{metric}.json"
                table.setdefault("intervals", {}).setdefault(run_name, {}).setdefault(name, {})[metric] = (
                    report_interval(report, base, metric))
    names = list(datasets)
    lines = ["| run | " + " | ".join(f"{n} CSA / CDA" for n in names) + " |",
             "|---|" + "---:|" * len(names)]
    for run_name in runs:
        cells = []
        for n in names:
            s = table["scores"][run_name][n]
            cells.append(" / ".join("-" if s[m] is None else f"{s[m]:.1f}" for m in ("csa", "cda")))
        lines.append(f"| {run_name} | " + " | ".join(cells) + " |")
    lines += ["", "Ratio to the own fit, 95 % interval over rooms (paired bootstrap), CSA / CDA:", "",
              "| run | " + " | ".join(names[1:]) + " |", "|---|" + "---:|" * (len(names) - 1)]
    for run_name in runs:
        cells = []
        for n in names[1:]:
            parts = []
            for m in ("csa", "cda"):
                cell = table["intervals"][run_name][n][m]
                ci = cell["ratio_ci95"]
                value = "-" if cell["ratio_to_own"] is None else f"{cell['ratio_to_own']:.2f}"
                parts.append(value + ("" if ci is None else f" [{ci[0]:.2f}, {ci[1]:.2f}]"))
            cells.append(" / ".join(parts))
        lines.append(f"| {run_name} | " + " | ".join(cells) + " |")
    counts = " ; ".join(f"{n}: " + ", ".join(f"{c:,}" for c in table["gaussians"][n].values()) for n in names)
    print("\n".join(lines))
    print(f"\nGaussians per scene ({', '.join(scenes)}): {counts}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
