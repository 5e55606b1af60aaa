"""The cost of building one real-size scene: CPU seconds per stage, peak memory, shard and cache bytes.

    .venv/bin/python benchmarks/bench_real_size_scene.py --work /tmp/real_size --out benchmarks/results/real_size_scene.md

The scene: one ScanNet++-layout room of ``seggaussian synth`` (``--max-edge`` 0.01 m: about 1.77 M mesh vertices),
``--views`` views, ``--gaussians`` oracle Gaussians, at each ``--sizes`` WxH (640x480, and 876x584, the size of
ScanNet++'s undistorted DSLR images; ``--max-image-side`` is set to the longer side so the views are rendered at that
size). The raw tree is written once into ``WORK/raw_WxH`` and not timed.

Each build is a fresh ``seggaussian build --gaussians oracle --json`` in a child process (its cache folder removed
first): its CPU seconds (user + system, the child and the processes it waited for: ``os.wait4``) and peak RSS are
its own, robust to other work on the machine. The per-stage CPU seconds are the build's own record
(``cpu_seconds`` of its ``--json``: each scene's stages, and the build's discover and assemble). ``shards`` counts
the writing of the scene's Parquet tables in the stages and the assembly of the split-named shards.

From the 640 x 480 figures the whole 288-scene build is projected (every scene as this one, the scenes spread evenly
over the cores, one scene per core at a time, no other cost): a table of hours on one machine of N cores and on K
such machines.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: Scenes of the paper's dataset (230 train + 50 val + 8 cross-domain).
PAPER_SCENES = 288
#: The stages of the per-stage table, in build order (``SceneOutcome.cpu_seconds`` names, ``shards`` with assembly).
STAGES = ("read", "gaussians", "transfer", "occlusion", "views", "shards")
#: Goals of the issue: CPU seconds per rendered view at 640 px (transfer included), peak GB, shard MB per scene.
GOAL_CPU_PER_VIEW, GOAL_PEAK_GB, GOAL_SHARD_MB = 0.6, 4.0, 100.0


def synthesize_raw(raw: Path, width: int, height: int, views: int, max_edge: float) -> dict:
    """Write the room into ``raw`` unless it is there; returns its mesh vertex and face counts."""
    from seggaussian.sources.layout import reader
    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    if not raw.exists():
        synthesize(raw, 1, 0, "scannetpp", SynthConfig(width=width, height=height, num_views=views,
                                                       max_edge=max_edge))
    scannetpp = reader("scannetpp")
    (scene_id,) = scannetpp.list_scenes(raw)
    scene = scannetpp.read_scene(raw, scene_id)
    sizes = {(v.camera.width, v.camera.height) for v in scene.views}
    return {"scene": scene_id, "vertices": int(len(scene.points)), "faces": int(len(scene.faces)),
            "views": len(scene.views), "view_sizes": sorted(sizes)}


#: Environment variables that cap a process's compute threads (torch/OpenMP, numba, BLAS, open3d's OpenMP).
THREAD_VARIABLES = ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def run_build(raw: Path, dataset: Path, gaussians: int, max_side: int, threads: int | None = None) -> dict:
    """A fresh build in a child process: its JSON payload plus wall and CPU seconds and peak RSS (bytes)."""
    if dataset.exists():
        shutil.rmtree(dataset)
    cmd = [sys.executable, "-m", "cli.seggaussian_cli", "build", "--source", "synthetic", "--root", str(raw),
           "--out", str(dataset), "--gaussians", "oracle", "--oracle-gaussians", str(gaussians),
           "--max-image-side", str(max_side), "--no-progress", "--json"]
    log = dataset.parent / f"{dataset.name}.log"
    start = time.perf_counter()
    with open(log, "w") as out:
        env = dict(os.environ)
        if threads is not None:
            env.update({name: str(threads) for name in THREAD_VARIABLES})
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=out, stderr=subprocess.STDOUT, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    text = log.read_text()
    if proc.returncode != 0:
        raise SystemExit(f"build failed ({proc.returncode}): {text[-3000:]}")
    payload = json.loads(text[text.index("{"):])
    return {"payload": payload, "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_rss_bytes": usage.ru_maxrss * 1024}


def folder_bytes(folder: Path) -> dict[str, int]:
    """Bytes per file name (summed over the folder's files of that name)."""
    sizes: dict[str, int] = {}
    for path in folder.rglob("*"):
        if path.is_file():
            sizes[path.name] = sizes.get(path.name, 0) + path.stat().st_size
    return sizes


def measure(work: Path, width: int, height: int, args) -> dict:
    raw, dataset = work / f"raw_{width}x{height}", work / f"dataset_{width}x{height}"
    scene = synthesize_raw(raw, width, height, args.views, args.max_edge)
    build = run_build(raw, dataset, args.gaussians, max(width, height), args.threads)
    payload = build.pop("payload")
    (record,) = payload["scenes"]
    stages = {name: float(record["cpu_seconds"].get(name, 0.0)) for name in STAGES}
    stages["shards"] += float(payload["cpu_seconds"].get("assemble", 0.0))
    outside = float(payload["cpu_seconds"].get("discover", 0.0))
    cache = folder_bytes(dataset / ".build")
    shard_bytes = int(payload["bytes"])
    views = int(record["num_views"])
    return {"size": f"{width}x{height}", "threads": args.threads, **scene, "gaussians": int(record["num_gaussians"]),
            "rendered_views": views,
            **build, "stages_cpu_s": stages, "discover_cpu_s": outside,
            "cpu_s_per_view": build["cpu_s"] / views, "shard_bytes": shard_bytes,
            "cache_bytes": sum(cache.values()), "cache_files": dict(sorted(cache.items(), key=lambda kv: -kv[1]))}


def projection(cpu_per_scene: float, cores: tuple[int, ...], nodes: tuple[int, ...]) -> list[str]:
    """Markdown rows: hours of the 288-scene build on K machines of N cores."""
    lines = ["| cores per machine | " + " | ".join(f"{k} machine{'s' if k > 1 else ''}" for k in nodes) + " |",
             "|---:|" + "---:|" * len(nodes)]
    for n in cores:
        cells = [f"{PAPER_SCENES * cpu_per_scene / (n * k) / 3600:.2f} h" for k in nodes]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return lines


def report(results: list[dict], args) -> str:
    cap = "no thread cap" if args.threads is None else f"compute threads capped at {args.threads}"
    lines = [f"Real-size scene build, `--gaussians oracle` ({args.gaussians:,} Gaussians), one scene, {cap}; "
             f"CPU seconds are user + system of the build process and its children.", "",
             "| size | mesh vertices | views | CPU s total | CPU s / view | " + " | ".join(STAGES) + " | wall s | "
             "peak RSS GB | shards MB | build cache MB |",
             "|---|---:|---:|---:|---:|" + "---:|" * len(STAGES) + "---:|---:|---:|---:|"]
    for r in results:
        stage_cells = " | ".join(f"{r['stages_cpu_s'][s]:.1f}" for s in STAGES)
        lines.append(f"| {r['size']} | {r['vertices']:,} | {r['rendered_views']} | {r['cpu_s']:.1f} | "
                     f"{r['cpu_s_per_view']:.2f} | {stage_cells} | {r['wall_s']:.1f} | "
                     f"{r['peak_rss_bytes'] / 1e9:.2f} | {r['shard_bytes'] / 1e6:.1f} | {r['cache_bytes'] / 1e6:.1f} |")
    lines += ["", "Build cache by file (MB): " + "; ".join(
        f"{r['size']}: " + ", ".join(f"{name} {size / 1e6:.1f}" for name, size in r["cache_files"].items()
                                      if size >= 1e5) for r in results)]
    first = results[0]
    lines += ["", f"Goals at {first['size']} (2 cores): CPU s / view {first['cpu_s_per_view']:.2f} "
              f"(goal <= {GOAL_CPU_PER_VIEW}), peak {first['peak_rss_bytes'] / 1e9:.2f} GB (goal <= {GOAL_PEAK_GB}), "
              f"shards {first['shard_bytes'] / 1e6:.1f} MB (goal <= {GOAL_SHARD_MB}), "
              f"cache {first['cache_bytes'] / 1e6:.1f} MB (goal <= the shards)."]
    lines += ["", f"Projection of the {PAPER_SCENES}-scene build from the {first['size']} scene "
              f"({first['cpu_s']:.0f} CPU s each; every scene this size, spread evenly over the cores, one scene per "
              f"core at a time, which needs {first['peak_rss_bytes'] / 1e9:.1f} GB of memory per core):", ""]
    lines += projection(first["cpu_s"], (2, 16, 64), (1, 4, 16))
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/real_size"))
    parser.add_argument("--sizes", nargs="+", default=["640x480", "876x584"], help="WxH of the views")
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--views", type=int, default=200)
    parser.add_argument("--max-edge", type=float, default=0.01, help="longest mesh edge (m): 0.01 gives 1.77 M vertices")
    parser.add_argument("--threads", type=int, default=None,
                        help="cap the build's compute threads (THREAD_VARIABLES); 1 is how each scene runs in a build of "
                             "many scenes with one scene per core, the projection's assumption (default: no cap)")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown report here")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = []
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        results.append(measure(args.work, width, height, args))
        print(json.dumps(results[-1], indent=1), flush=True)
    text = report(results, args)
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
