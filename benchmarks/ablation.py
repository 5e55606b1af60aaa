"""Ablation of paper Table 2: train each configuration, score 3D CSA, 2D CSA and NVA at K = 20, 50, 100.

Configurations (``--mode paper``, the rows of Table 2, switches added one at a time):

    V-S align  3D-T align  adapter
        -          -          -        (2D-to-text alignment only)
        x          -          -
        x          x          -
        x          x          x        (full model)

``--mode leave-one-out``: full; no adapter; no 3D-to-text align; no visual-semantic align.
The 2D-to-text alignment is always on. The visual-semantic (MaskCLIP) loss needs a local CLIP model
(``--clip-model PATH``); without one the trainer switches it off and the table marks those rows.

Each (configuration, K) pair is trained on the train split with a K-class vocabulary (the K - 4 seen
classes supervised), then scored by ``ovgaussian.bench.evaluate`` on the same dataset. ``--shared-k`` trains once
per configuration at the largest K and scores that model at every K (faster, not the paper's protocol).

Example (synthetic data from scripts/demo.sh)::

    .venv/bin/python benchmarks/ablation.py --data out/demo/dataset --out out/ablation --epochs 2 \
        --classes 20 --max-views 4
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

#: (label, no_vs_align, no_3dt_align, use_adapter) per mode.
CONFIGURATIONS = {
    "paper": (
        ("none", True, True, False),
        ("V-S", False, True, False),
        ("V-S + 3D-T", False, False, False),
        ("full", False, False, True),
    ),
    "leave-one-out": (
        ("full", False, False, True),
        ("no adapter", False, False, False),
        ("no 3D-T align", False, True, True),
        ("no V-S align", True, False, True),
    ),
}
#: Paper Table 2 (ScanNet++, rows of --mode paper): 3D CSA, 2D CSA, NVA at 20 / 50 / 100 classes.
PAPER_TABLE2 = {
    "none": ((32.18, 20.34, 15.26), (37.15, 24.58, 17.24), (56.35, 36.31, 18.42)),
    "V-S": ((34.57, 23.57, 15.66), (40.17, 26.73, 18.34), (57.71, 37.93, 19.23)),
    "V-S + 3D-T": ((40.55, 30.39, 19.11), (43.70, 31.73, 20.85), (67.55, 53.71, 27.98)),
    "full": ((43.84, 33.84, 20.73), (45.76, 33.76, 21.84), (69.51, 55.35, 28.85)),
}
COLUMNS = (("3d", "CSA"), ("2d", "CSA"), ("2d", "NVA"))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, required=True, help="dataset folder (build + split)")
    p.add_argument("--out", type=Path, required=True, help="folder for the runs, JSON reports and table.md")
    p.add_argument("--mode", choices=sorted(CONFIGURATIONS), default="paper")
    p.add_argument("--classes", default="20,50,100", help="comma-separated K values")
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--batch-scenes", type=int, default=3)
    p.add_argument("--pixels-per-view", type=int, default=4096)
    p.add_argument("--preset", choices=["slim", "default"], default="slim")
    p.add_argument("--clip-model", type=Path, default=None, help="local CLIP folder for the V-S loss")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-views", type=int, default=None, help="views scored per scene")
    p.add_argument("--max-scenes", type=int, default=None, help="scenes scored per split")
    p.add_argument("--shared-k", action="store_true", help="train once per configuration at the largest K")
    p.add_argument("--no-train", action="store_true", help="only score runs that already exist in --out")
    return p.parse_args(argv)


def train_run(args, label: str, no_vs: bool, no_3dt: bool, adapter: bool, k: int) -> tuple[Path, tuple]:
    from ovgaussian.train.loop import train
    from ovgaussian.run.config import DataConfig, LossConfig, TeacherConfig, TrainConfig

    run = args.out / "runs" / f"{label.replace(' ', '').replace('+', '_')}-K{k}"
    if args.no_train or (run / "checkpoints" / "latest.json").is_file():
        return run, ()
    # the runs share one cache folder: blend weights and text embeddings are keyed by their inputs
    # (dataset fingerprint, top_k, vocabulary), not by the run, so they are computed once
    shared = args.out / "shared-caches"
    shared.mkdir(parents=True, exist_ok=True)
    run.mkdir(parents=True, exist_ok=True)
    if not (run / "caches").exists():
        (run / "caches").symlink_to(shared.resolve(), target_is_directory=True)
    config = TrainConfig(
        out=run, epochs=args.epochs, batch_scenes=args.batch_scenes, seed=args.seed, model_preset=args.preset,
        use_adapter=adapter, progress=False,
        data=DataConfig(dataset=args.data, num_classes=k, pixels_per_view=args.pixels_per_view),
        teacher=TeacherConfig(clip_model=args.clip_model),
        loss=LossConfig(no_3dt_align=no_3dt, no_vs_align=no_vs),
    )
    result = train(config)
    return run, tuple(result.notes)


def score(args, run: Path, k: int) -> dict:
    from ovgaussian.bench.evaluate import run_bench
    from seggaussian.util.atomic import write_json_atomic
    from ovgaussian.bench.config import BenchConfig

    config = BenchConfig(dataset=args.data, run=run, metrics=("CSA", "NVA"), dims=("3d", "2d"), num_classes=k,
                         max_views_per_scene=args.max_views, max_scenes=args.max_scenes, progress=False)
    report = run_bench(config)
    write_json_atomic(args.out / "reports" / f"{run.name}-K{k}.json", report.payload)
    return report.payload["row"]


def format_table(rows: list[dict], ks: list[int], mode: str, notes: dict) -> str:
    def cell(v):
        return "-" if v is None else f"{100 * v:.2f}"

    head = "| V-S align | 3D-T align | adapter | " + " | ".join(
        f"{d.upper()} {m} K={k}" if m != "NVA" else f"NVA K={k}" for d, m in COLUMNS for k in ks) + " |"
    lines = [head, "|---|---|---|" + "---:|" * (len(COLUMNS) * len(ks))]
    for row in rows:
        marks = ["x" if row["vs"] else "", "x" if row["t3d"] else "", "x" if row["adapter"] else ""]
        if row["vs"] and row["vs_off"]:
            marks[0] = "(off: no CLIP)"
        cells = [cell(row["scores"].get(k, {}).get(f"{d}_{m}")) for d, m in COLUMNS for k in ks]
        lines.append("| " + " | ".join(marks + cells) + " |")
    if mode == "paper":
        lines.append("")
        lines.append("Paper Table 2 (ScanNet++, full-size model) for comparison:")
        lines.append("")
        lines.append(head)
        lines.append(lines[1])
        for label, (_, no_vs, no_3dt, adapter) in zip(PAPER_TABLE2, CONFIGURATIONS["paper"]):
            marks = ["x" if not no_vs else "", "x" if not no_3dt else "", "x" if adapter else ""]
            values = PAPER_TABLE2[label]
            cells = [f"{values[ci][(20, 50, 100).index(k)]:.2f}" if k in (20, 50, 100) else "-"
                     for ci in range(len(COLUMNS)) for k in ks]
            lines.append("| " + " | ".join(marks + cells) + " |")
    if notes:
        lines.append("")
        for text, labels in notes.items():
            lines.append(f"- {text} (runs: {', '.join(labels)})")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)
    ks = [int(k) for k in args.classes.split(",") if k.strip()]
    args.out.mkdir(parents=True, exist_ok=True)
    rows, notes = [], {}
    started = time.perf_counter()
    for label, no_vs, no_3dt, adapter in CONFIGURATIONS[args.mode]:
        if no_vs and args.clip_model is None and args.mode == "leave-one-out":
            # without a local CLIP the visual-semantic loss is off in every run: this row would repeat "full"
            notes.setdefault("'no V-S align' not run: without --clip-model the V-S loss is off in every row", [])
            continue
        row = {"label": label, "vs": not no_vs, "t3d": not no_3dt, "adapter": adapter, "vs_off": False, "scores": {}}
        shared = None
        for k in ks:
            t0 = time.perf_counter()
            if args.shared_k:
                if shared is None:
                    shared = train_run(args, label, no_vs, no_3dt, adapter, max(ks))
                run, run_notes = shared
            else:
                run, run_notes = train_run(args, label, no_vs, no_3dt, adapter, k)
            if any("visual-semantic" in n and "off" in n for n in run_notes):
                row["vs_off"] = True
            for note in run_notes:
                who = notes.setdefault(note, [])
                if label not in who:
                    who.append(label)
            row["scores"][k] = score(args, run, k)
            print(f"[ablation] {label} K={k}: " + ", ".join(
                f"{key}={'-' if v is None else f'{100 * v:.2f}'}" for key, v in row["scores"][k].items()
                if v is not None) + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
        rows.append(row)
    table = format_table(rows, ks, args.mode, notes)
    (args.out / "table.md").write_text(table)
    (args.out / "ablation.json").write_text(json.dumps({"mode": args.mode, "classes": ks, "rows": rows,
                                                        "seconds": time.perf_counter() - started}, indent=2))
    print(table)
    print(f"ablation: {len(rows)} configurations x {len(ks)} vocabularies in "
          f"{time.perf_counter() - started:.0f} s -> {args.out / 'table.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
