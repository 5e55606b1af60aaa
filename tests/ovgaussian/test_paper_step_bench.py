"""benchmarks/bench_paper_step.py at a tiny scale: it runs, times every phase and the sparse U-Net on its own, and
it reports the device's busy share and, with ``--compare-workers``, the steps with a loader worker against those
without, and its budget check fails loudly (exit status 1, the missed figure named) when a budget is missed.

The bench wraps library functions by name (``net.voxel_stage``, ``net.backbone``, the kernel-map builders, ...);
this keeps a rename from breaking it unnoticed. Timings are not asserted (they belong in BENCHMARKS.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "benchmarks" / "bench_paper_step.py"
TINY = ["--gaussians", "3000", "--scenes", "2", "--pixels", "128", "--steps", "1", "--preset", "slim"]


def _run(*budgets: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *TINY, *budgets], capture_output=True, text=True, cwd=REPO,
                          timeout=600)


def test_tiny_paper_step_reports_phases_and_the_unet_and_fails_a_missed_budget():
    res = _run("--max-step-s", "1000", "--max-peak-gb", "100", "--max-backward-ratio", "100", "--compare-workers", "1")
    assert res.returncode == 0, res.stderr[-2000:]
    result, _ = json.JSONDecoder().raw_decode(res.stdout)
    assert result["workload"]["gaussians_per_scene"] == 3000 and len(result["steps"]) == 1
    step = result["steps"][0]
    assert step["phases_s"]["network"] > 0 and step["phases_s"]["backward"] > 0
    assert step["phases_s"]["sample"] > 0 and 0 < step["device_busy"] <= 1 and step["compute_s"] <= step["wall_s"]
    # the same steps with one loader worker: it samples (this process does not) and both blocks report their peaks
    compare = result["compare_workers"]
    worker_step = compare["with"]["steps"][0]
    assert compare["without"]["loader_workers"] == 0 and compare["with"]["loader_workers"] == 1
    assert worker_step["phases_s"]["sample"] == 0 and worker_step["worker_sample_s"] > 0
    assert compare["with"]["block_workers_peak_gb"] > 0 and compare["without"]["block_workers_peak_gb"] == 0
    assert compare["step_ratio"] > 0 and compare["peak_ratio"] > 1
    assert "with 1 loader workers / without: step" in res.stdout
    assert 0 < step["unet_forward_s"] and 0 < step["unet_backward_s"] <= step["phases_s"]["backward"] + 1e-6
    assert result["unet_backward_over_forward"] > 0 and result["peak_rss_gb"] > 0
    assert "within budget" in res.stdout.splitlines()[-1]

    missed = _run("--max-step-s", "0.000001", "--max-peak-gb", "100", "--max-backward-ratio", "100")
    assert missed.returncode == 1
    assert "FAILED: step" in missed.stdout.splitlines()[-1] and "Traceback" not in missed.stderr
