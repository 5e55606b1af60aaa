"""Dataset build: full build of the default synthetic set, unchanged rebuild, peak memory of a 1M-Gaussian scene.

    .venv/bin/python benchmarks/bench_build.py --work /tmp/bench_build            # everything
    .venv/bin/python benchmarks/bench_build.py --work /tmp/bench_build --skip-memory

Each build runs as a child process (``python -m cli.seggaussian_cli build ...``) so that its wall time and
peak RSS (``RUSAGE_CHILDREN``) are its own. The raw tree (default synthetic set: 9 ScanNet++-layout +
3 Replica-layout rooms, ``seggaussian.sources.synthetic.generate`` defaults) is synthesized once into ``WORK/raw``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_build(args: list[str]) -> tuple[float, float, dict]:
    """(wall seconds, peak RSS GB of the build process and its workers, JSON payload)."""
    rss_file = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_build_rss_{os.getpid()}.txt"
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--child", str(rss_file), "--", *args, "--json", "--no-progress"],
                          cwd=REPO, capture_output=True, text=True)
    seconds = time.perf_counter() - t
    if proc.returncode not in (0, 1):
        raise SystemExit(f"build failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    peak_gb = float(rss_file.read_text()) / 2**20
    rss_file.unlink()
    return seconds, peak_gb, json.loads(proc.stdout)


def child(rss_file: str, argv: list[str]) -> None:
    """Run ``seggaussian build ARGV`` in this process, then record the peak RSS (KiB) of it and its workers."""
    sys.path.insert(0, str(REPO))
    from cli.seggaussian_cli import main as cli_main

    code = 0
    try:
        cli_main.main(["build", *argv], standalone_mode=False)
    except SystemExit as exc:
        code = int(exc.code or 0)
    peak = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    Path(rss_file).write_text(str(peak))
    raise SystemExit(code)


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[4:])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_build"))
    parser.add_argument("--scannetpp", type=int, default=9)
    parser.add_argument("--replica", type=int, default=3)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--gaussians", default="oracle", choices=["oracle", "fit"])
    parser.add_argument("--memory-gaussians", type=int, default=1_000_000)
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--fresh", action="store_true", help="delete WORK/raw and the datasets first")
    parser.add_argument("--build-args", default="", help="extra build options, e.g. '--view-stride 4'")
    args = parser.parse_args()

    raw, ds, mem_ds = args.work / "raw", args.work / "dataset", args.work / "dataset_1m"
    if args.fresh and args.work.exists():
        shutil.rmtree(args.work)
    for d in (ds, mem_ds):
        if d.exists():
            shutil.rmtree(d)
    results: dict = {}
    if not raw.exists():
        sys.path.insert(0, str(REPO))
        from seggaussian.sources.synthetic.generate import synthesize

        t = time.perf_counter()
        synthesize(raw / "scannetpp", args.scannetpp, 0, "scannetpp")
        synthesize(raw / "replica", args.replica, 0, "replica")
        results["synthesize_seconds"] = time.perf_counter() - t
    common = ["--source", "synthetic", "--root", str(raw), "--gaussians", args.gaussians, "--jobs", str(args.jobs),
              *args.build_args.split()]
    results["build_args"] = common[6:]
    first, first_rss, payload = run_build([*common, "--out", str(ds)])
    results["first_build_seconds"] = first
    results["first_build_peak_rss_gb"] = first_rss
    results["scenes"] = payload["counts"]
    results["splits"] = payload["splits"]
    results["bytes"] = payload["bytes"]
    results["gaussians_total"] = sum(s.get("num_gaussians", 0) for s in payload["scenes"])
    results["views_total"] = sum(s.get("num_views", 0) for s in payload["scenes"])
    results["stage_seconds_per_scene_median"] = sorted(s["seconds"] for s in payload["scenes"])[len(payload["scenes"]) // 2]
    results["label_accuracy_min"] = min((s.get("label_accuracy", {}).get("accuracy") or 1.0) for s in payload["scenes"])
    mtimes = {str(p): p.stat().st_mtime_ns for p in ds.rglob("*") if p.is_file()}
    second, _, payload2 = run_build([*common, "--out", str(ds)])
    results["unchanged_rebuild_seconds"] = second
    results["unchanged_rebuild_share"] = second / first
    results["unchanged_rebuild_counts"] = payload2["counts"]
    results["unchanged_rebuild_files_touched"] = sum(
        1 for p in ds.rglob("*") if p.is_file() and mtimes.get(str(p)) != p.stat().st_mtime_ns)
    if not args.skip_memory:
        scene = payload["scenes"][0]["scene"]
        seconds, rss, payload3 = run_build(["--source", "synthetic", "--root", str(raw), "--gaussians", "oracle",
                                            "--oracle-gaussians", str(args.memory_gaussians), "--scenes", scene,
                                            "--view-stride", "4",
                                            "--out", str(mem_ds)])
        results["memory_scene"] = scene
        results["memory_scene_gaussians"] = payload3["scenes"][0].get("num_gaussians")
        results["memory_scene_seconds"] = seconds
        results["memory_scene_peak_rss_gb"] = rss
    results["cpu_count"] = os.cpu_count()
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
