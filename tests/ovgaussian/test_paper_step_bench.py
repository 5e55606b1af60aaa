"""benchmarks/bench_paper_step.py at a tiny scale: it runs, times every phase and the sparse U-Net on its own, and
its budget check fails loudly (exit status 1, the missed figure named) when a budget is missed.

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
    res = _run("--max-step-s", "1000", "--max-peak-gb", "100", "--max-backward-ratio", "100")
    assert res.returncode == 0, res.stderr[-2000:]
    result, _ = json.JSONDecoder().raw_decode(res.stdout)
    assert result["workload"]["gaussians_per_scene"] == 3000 and len(result["steps"]) == 1
    step = result["steps"][0]
    assert step["phases_s"]["network"] > 0 and step["phases_s"]["backward"] > 0
    assert 0 < step["unet_forward_s"] and 0 < step["unet_backward_s"] <= step["phases_s"]["backward"] + 1e-6
    assert result["unet_backward_over_forward"] > 0 and result["peak_rss_gb"] > 0
    assert "within budget" in res.stdout.splitlines()[-1]

    missed = _run("--max-step-s", "0.000001", "--max-peak-gb", "100", "--max-backward-ratio", "100")
    assert missed.returncode == 1
    assert "FAILED: step" in missed.stdout.splitlines()[-1] and "Traceback" not in missed.stderr
