"""Time to synthesize and to read one default synthetic scene, per layout; plus the round-trip figures.

Usage:
    .venv/bin/python benchmarks/bench_sources.py [--repeats 3] [--scenes 12] [--out benchmarks/results/sources.md]

For each layout (ScanNet++, Replica): synthesize scene 0 of seed 0 with the default SynthConfig
(320 px wide, 32 views, 5 cm edges) ``--repeats`` times into a fresh folder (the first run also pays
the open3d import, reported separately), then read it back ``--repeats`` times. Also times a full
``--scenes``-scene demo set in the default split of ``seggaussian synth --layout both`` (3/4 ScanNet++,
1/4 Replica), and reports the round-trip agreement of projected labelled vertices with the
ground-truth label images (depth test 2 mm at pixel centres). Medians in seconds, wall clock and
CPU (process time: all threads of the process, so it stays meaningful on a loaded machine).
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from seggaussian.core.constants import IGNORE_LABEL  # noqa: E402
from seggaussian.sources import replica, scannetpp, synthetic  # noqa: E402

#: Depth test of the round-trip check (metres), as in tests/seggaussian/sources/test_sources_roundtrip.py.
DEPTH_TOL = 0.002


def agreement(scene) -> tuple[int, int]:
    from seggaussian.sources._common import read_image
    from seggaussian.sources.raycast import MeshRaycaster

    caster = MeshRaycaster(scene.points, scene.faces)
    labelled = np.flatnonzero(scene.semantic != IGNORE_LABEL)
    agree = visible = 0
    for view in scene.views:
        cam = view.camera
        gt = read_image(view.semantic_path, "gt", unchanged=True).astype(np.int64)
        depth = caster.cast(cam).depth
        uv, z = cam.project(scene.points[labelled])
        px = np.floor(uv).astype(np.int64)
        inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        idx, px, z = labelled[inside], px[inside], z[inside]
        seen = np.abs(depth[px[:, 1], px[:, 0]] - z) < DEPTH_TOL
        visible += int(seen.sum())
        agree += int((gt[px[seen, 1], px[seen, 0]] == scene.semantic[idx[seen]]).sum())
    return agree, visible


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scenes", type=int, default=12)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "sources.md")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_sources_"))
    rows, notes = [], []
    try:
        for layout, reader in (("scannetpp", scannetpp), ("replica", replica)):
            synth_times, read_times, synth_cpu, read_cpu = [], [], [], []
            first = None
            for r in range(args.repeats + 1):
                root = work / f"{layout}{r}"
                t, c = time.perf_counter(), time.process_time()
                ids = synthetic.synthesize(root, 1, 0, layout)
                dt = time.perf_counter() - t
                if r == 0:
                    first = dt
                else:
                    synth_times.append(dt)
                    synth_cpu.append(time.process_time() - c)
            for _ in range(args.repeats):
                t, c = time.perf_counter(), time.process_time()
                scene = reader.read_scene(root, ids[0])
                read_times.append(time.perf_counter() - t)
                read_cpu.append(time.process_time() - c)
            agree, visible = agreement(scene)
            size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
            rows.append((layout, len(scene.points), len(scene.faces), len(scene.views), f"{scene.views[0].camera.width}x{scene.views[0].camera.height}",
                         first, statistics.median(synth_times), statistics.median(synth_cpu), statistics.median(read_times),
                         statistics.median(read_cpu), size / 1e6, agree / max(visible, 1), visible))
        replica_count = max(1, math.ceil(args.scenes / 4))
        t, c = time.perf_counter(), time.process_time()
        synthetic.synthesize(work / "demo" / "scannetpp", args.scenes - replica_count, 0, "scannetpp")
        synthetic.synthesize(work / "demo" / "replica", replica_count, 0, "replica")
        demo, demo_cpu = time.perf_counter() - t, time.process_time() - c
        notes.append(f"- demo set: {args.scenes - replica_count} ScanNet++ + {replica_count} Replica scenes synthesized in {demo:.1f} s wall, "
                     f"{demo_cpu:.1f} s CPU (one process, open3d already imported)")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    load = os.getloadavg()
    lines = [
        "# Scene sources: synthesize and read one default scene",
        "",
        f"Command: `.venv/bin/python benchmarks/bench_sources.py --repeats {args.repeats} --scenes {args.scenes}`",
        f"Machine: {os.cpu_count()} cores, load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} at the end "
        "(MEASURED UNDER LOAD when above ~1: other jobs share the cores; re-run on a quiet machine).",
        "",
        "| layout | vertices | triangles | views | image | first synth (s, incl. open3d import) | synth wall (s) | synth CPU (s) | read wall (s) | read CPU (s) | MB on disk | round-trip agreement | visible vertex-views |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for layout, nv, nf, nviews, size, first, synth, synth_c, read, read_c, mb, frac, visible in rows:
        lines.append(f"| {layout} | {nv:,} | {nf:,} | {nviews} | {size} | {first:.2f} | {synth:.2f} | {synth_c:.2f} | {read:.3f} | {read_c:.3f} | {mb:.1f} | "
                     f"{100 * frac:.2f}% | {visible:,} |")
    lines += ["", *notes, "",
              "Round-trip agreement: share of labelled mesh vertices, projected with the cameras the reader returns and visible "
              "(camera depth within 2 mm of the depth raycast through the pixel centre), whose ground-truth label pixel holds "
              "their own label (the tests require >= 99%).", ""]
    text = "\n".join(lines)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
