"""Ray build on two nodes against one node with the same cores: the speed-up of spreading scenes over nodes.

    .venv/bin/python benchmarks/bench_ray_nodes.py --work /tmp/bench_ray_nodes --repeats 2

The raw tree is the default synthetic set (9 ScanNet++-layout + 3 Replica-layout rooms, ``seggaussian synth``
defaults), synthesized once into ``WORK/raw``. Each repeat builds it twice with ``--gaussians oracle --executor
ray``, once on a cluster of one node with 2 CPUs and once on a cluster of two nodes with 1 CPU each (both clusters
on this machine, every node bound to 127.0.0.1: ``seggaussian.tools.ray_cluster``), one scene task per CPU
(``--ray-cpus 1``), the two alternated in one run (ABBA). The figure is the ratio of the median wall times of the builds
(the cluster started before the clock starts); the two outputs are compared byte for byte.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from seggaussian.tools.ray_cluster import LoopbackRayCluster  # noqa: E402

#: (label, nodes, CPUs a node) of the two clusters compared.
LAYOUTS = (("1 node x 2 CPUs", 1, 2), ("2 nodes x 1 CPU", 2, 1))


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def build_on(cluster: LoopbackRayCluster, raw: Path, out: Path) -> tuple[float, dict]:
    """(wall seconds, JSON report) of one build of ``raw`` into a fresh ``out`` on ``cluster``."""
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    command = [sys.executable, "-m", "cli.seggaussian_cli", "build", "--root", str(raw), "--out", str(out),
               "--gaussians", "oracle", "--executor", "ray", "--address", cluster.address, "--ray-cpus", "1",
               "--ray-memory-gb", "1", "--json", "--no-progress"]
    proc = subprocess.run(command, cwd=REPO, env=cluster.driver_env(), capture_output=True, text=True, timeout=3600)
    seconds = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"build failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return seconds, json.loads(proc.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_ray_nodes"))
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a stopped benchmark stops its clusters too
    work = args.work.resolve()
    raw = work / "raw"
    if not raw.is_dir():
        subprocess.run([sys.executable, "-m", "cli.seggaussian_cli", "synth", "--out", str(raw), "--no-progress"],
                       cwd=REPO, check=True)
    times: dict[str, list[float]] = {label: [] for label, _, _ in LAYOUTS}
    load = [os.getloadavg()[0]]
    for rep in range(args.repeats):
        for label, nodes, cpus in (LAYOUTS if rep % 2 == 0 else LAYOUTS[::-1]):  # ABBA: load drift hits both
            with LoopbackRayCluster(work / f"cluster-{nodes}", nodes=nodes, cpus=cpus, memory_gb=1.5 * cpus,
                                    object_store_mb=200) as cluster:
                seconds, report = build_on(cluster, raw, work / f"out-{nodes}")
            assert report["counts"]["failed"] == 0 and report["counts"]["built"] == len(report["scenes"])
            assert len(report["ray_nodes"]) == nodes and {n["address"] for n in report["ray_nodes"]} == {"127.0.0.1"}
            times[label].append(seconds)
            (work / f"report-{nodes}-{rep}.json").write_text(json.dumps(report, indent=1))
            scene_seconds = sum(o["seconds"] for o in report["scenes"])
            load.append(os.getloadavg()[0])
            print(f"repeat {rep}: {label}: {seconds:.1f} s, {report['counts']['built']} scenes, "
                  f"{scene_seconds:.1f} s of scene tasks (sum)", flush=True)
    same = files(work / "out-1") == files(work / "out-2")
    one, two = (statistics.median(times[label]) for label, _, _ in LAYOUTS)
    print(f"median build: 1 node x 2 CPUs {one:.1f} s, 2 nodes x 1 CPU {two:.1f} s; speed-up of two nodes "
          f"{one / two:.2f}x; outputs identical: {same}; load average {min(load):.1f}-{max(load):.1f}")
    if not same:
        raise SystemExit("the two clusters built different bytes")


if __name__ == "__main__":
    main()
