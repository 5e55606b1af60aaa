"""The benchmark profile's report: Table 1, the paper's Table 2 and the per-class table from bench payloads, and the
model-quality checks of issues #16 and #27 (``ovgaussian bench-suite``; the splat zoo's tables and checks of issue
#54 are ``ovgaussian.suite.zoo``'s)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ovgaussian.bench.bootstrap import Interval, bootstrap_ratio, overlaps
from ovgaussian.bench.config import TABLE1_COLUMNS
from ovgaussian.metrics import UnseenShare, unseen_share
from ovgaussian.suite.config import ABLATION_ROWS, Table1Row

#: The metrics the full model must win against both baselines (issue #16: every non-OVA metric).
NON_OVA_COLUMNS = (("3d", "CSA"), ("3d", "CDA"), ("2d", "CSA"), ("2d", "NVA"), ("2d", "CDA"))
#: Columns of the ablation table (the paper's Table 2).
ABLATION_COLUMNS = (("3d", "CSA"), ("2d", "CSA"), ("2d", "NVA"))

def interval_of(payload: dict, dim: str, metric: str) -> Interval:
    """The metric's value and 95 % interval from a bench payload."""
    m = payload["metrics"].get(dim, {}).get(metric)
    if m is None:
        return Interval(None, None, None, 0, 0)
    ci = m.get("ci95") or [None, None]
    return Interval(m["miou"], ci[0], ci[1], 0, 0)


def _cell(interval: Interval) -> str:
    if interval.value is None:
        return "-"
    if interval.low is None:
        return f"{100 * interval.value:.1f}"
    return f"{100 * interval.value:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def format_table1(reports: dict) -> str:
    """Table 1 (mIoU %, 95 % interval over scenes in brackets)."""
    head = "| method | " + " | ".join(f"{d.upper()} {m}" for d, m in TABLE1_COLUMNS) + " |"
    lines = [head, "|---|" + "---:|" * len(TABLE1_COLUMNS)]
    for label, payload in reports.items():
        lines.append(f"| {label} | " + " | ".join(_cell(interval_of(payload, d, m)) for d, m in TABLE1_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def format_ablation(run_reports: dict, vs_available: bool) -> str:
    """The paper's Table 2 rows at K = 20 on this profile, the paper's values beside them."""
    head = ("| V-S align | 3D-T align | adapter | run | " + " | ".join(f"{d.upper()} {m}" for d, m in ABLATION_COLUMNS)
            + " | paper " + " | paper ".join(f"{d.upper()} {m}" for d, m in ABLATION_COLUMNS) + " |")
    lines = [head, "|---|---|---|---|" + "---:|" * (2 * len(ABLATION_COLUMNS))]
    for row in ABLATION_ROWS:
        vs = "x" if row.vs_align and vs_available else ("(off: no CLIP)" if row.vs_align else "")
        payload = run_reports.get(row.run)
        cells = ["-"] * len(ABLATION_COLUMNS) if payload is None else [
            _cell(interval_of(payload, d, m)) for d, m in ABLATION_COLUMNS]
        lines.append(f"| {vs} | {'x' if row.t3d_align else ''} | {'x' if row.adapter else ''} | {row.run} | "
                     + " | ".join(cells) + " | " + " | ".join(f"{v:.2f}" for v in row.paper) + " |")
    return "\n".join(lines) + "\n"


def format_classes(reports: dict, dim: str = "3d", metric: str = "CSA") -> str:
    """Per-class IoU (%) of every Table-1 row on the metric's set."""
    labels = list(reports)
    first = reports[labels[0]]["metrics"][dim][metric]
    names = list(first["per_class_iou"])
    lines = ["| class | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    for name in names:
        cells = []
        for label in labels:
            v = reports[label]["metrics"][dim][metric]["per_class_iou"].get(name)
            cells.append("-" if v is None else f"{100 * v:.1f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def present_seen_classes(payload: dict, dim: str = "3d") -> list[str]:
    """Seen classes present in the val ground truth (a confusion row with samples)."""
    counts = np.asarray(payload["confusion"][f"val_{dim}"])
    names, unseen = payload["vocabulary"]["names"], set(payload["vocabulary"]["unseen"])
    return [n for i, n in enumerate(names) if counts[i].sum() > 0 and n not in unseen]


def report_unseen_share(payload: dict) -> UnseenShare | None:
    """``ovgaussian.metrics.unseen_share`` of a bench report's NVA confusion matrix; None without NVA."""
    counts = payload["confusion"].get("train_2d")
    if counts is None:
        return None
    names = payload["vocabulary"]["names"]
    return unseen_share(np.asarray(counts), [names.index(n) for n in payload["vocabulary"]["unseen"]])


def nva_unseen_share(payload: dict) -> str:
    """What the unseen classes decide of a report's NVA (:func:`report_unseen_share`), as a sentence."""
    share = report_unseen_share(payload)
    if share is None:
        return "no NVA confusion"
    if share.unseen_right is None or share.seen_only is None:
        return "no class scored"
    ious = payload["metrics"].get("2d", {}).get("NVA", {}).get("per_class_iou", {})
    unseen = ", ".join(f"{n} {'-' if ious.get(n) is None else f'{100 * ious[n]:.1f}'}"
                       for n in payload["vocabulary"]["unseen"])
    return (f"with every unseen pixel right it would be {100 * share.unseen_right:.1f}; "
            f"the seen classes score {100 * share.seen_only:.1f} with the unseen pixels left out; "
            f"unseen classes' IoU: {unseen}")


def checks(reports: dict, full_label: str, baseline_labels: tuple[str, ...], run_reports: dict,
           stacking_labels: tuple[str, ...] = (), method_labels: tuple[str, ...] = ()) -> dict:
    """The model-quality checks of issue #16: ``{name: (passed, detail)}``. ``stacking_labels``: the Table-1
    rows scored with calibrated stacking (OVA > 0 in 3D and 2D, gamma recorded in the report).
    ``method_labels``: the open-vocabulary method rows; NVA >= 60 holds when the full model or one of them reaches
    it, and the detail names each row's NVA and what its unseen classes decide."""
    out = {}
    for label in stacking_labels:
        payload = reports[label]
        gamma = (payload.get("predictor") or {}).get("stacking", {}).get("gamma")
        ova = {dim: interval_of(payload, dim, "OVA") for dim in ("3d", "2d")}
        out[f"OVA > 0 in 3D and 2D with calibrated stacking ({label}), gamma recorded"] = (
            gamma is not None and all(i.value is not None and i.value > 0 for i in ova.values()),
            f"gamma {gamma}; " + "; ".join(f"{d.upper()} OVA {_cell(i)}" for d, i in ova.items()))
    full = reports[full_label]
    for dim, metric in NON_OVA_COLUMNS:
        mine = interval_of(full, dim, metric)
        details, passed = [], mine.value is not None
        for label in baseline_labels:
            other = interval_of(reports[label], dim, metric)
            separate = overlaps(mine, other) is False
            passed = passed and other.value is not None and mine.value > other.value and separate
            details.append(f"{label}: {_cell(other)}")
        out[f"full beats both baselines on {dim.upper()} {metric}, intervals apart"] = (
            bool(passed), f"full {_cell(mine)} vs " + "; ".join(details))
    nva_rows = [full_label] + [label for label in method_labels if label != full_label]
    reaching = [label for label in nva_rows if (interval_of(reports[label], "2d", "NVA").value or 0.0) >= 0.60]
    out["NVA >= 60"] = (bool(reaching),
                        (f"reached by {', '.join(reaching)}" if reaching else "reached by no row") + "; "
                        + "; ".join(f"{label}: NVA {_cell(interval_of(reports[label], '2d', 'NVA'))}, "
                                    + nva_unseen_share(reports[label]) for label in nva_rows))
    for dim in ("3d", "2d"):
        ious = full["metrics"][dim]["CSA"]["per_class_iou"]
        zero = [n for n in present_seen_classes(full, dim) if not (ious.get(n) or 0.0) > 0.0]
        out[f"every seen class of the val rooms above 0 IoU ({dim.upper()})"] = (
            not zero, "zero: " + ", ".join(zero) if zero else f"{len(present_seen_classes(full, dim))} classes > 0")
    order = []
    for dim, metric in ABLATION_COLUMNS:
        values = [interval_of(run_reports[r.run], dim, metric).value if r.run in run_reports else None
                  for r in ABLATION_ROWS]
        if None in values:
            continue
        rising = all(b >= a for a, b in zip(values, values[1:]))
        order.append(f"{dim.upper()} {metric} {'rises' if rising else 'does not rise'} down the rows "
                     f"({', '.join(f'{100 * v:.1f}' for v in values)})")
    if order:
        out["ablation rows order as the paper's"] = (all("does not" not in o for o in order), "; ".join(order))
    return out


#: Issue #27: the full model's 3D CSA on fitted splats is at least this share of what it reaches on oracle Gaussians.
FIT_TO_ORACLE_MIN_SHARE = 0.9


def paired_csa_ratio(fitted: dict, control: dict) -> Interval | None:
    """3D CSA of ``fitted`` over ``control`` (bench payloads) with its paired bootstrap interval over the val rooms
    (``bootstrap_ratio``), or None when the two did not score the same rooms in the same order or hold no per-room
    matrices (a report of an older bench)."""
    rooms = [payload.get("dataset", {}).get("scenes", {}).get("val") for payload in (fitted, control)]
    mats = [payload.get("scene_confusion", {}).get("val_3d") for payload in (fitted, control)]
    if not rooms[0] or rooms[0] != rooms[1] or any(m is None or len(m) != len(rooms[0]) for m in mats):
        return None
    top, bottom = (np.asarray(m, dtype=np.int64) for m in mats)
    return bootstrap_ratio(top, bottom) if top.shape == bottom.shape else None


def control_checks(reports: dict, pairs: Sequence[tuple[str, str]], splats: str, recipe: str | None = None) -> dict:
    """The 90 % check of issue #27: a method on fitted splats against its control (the same method trained and
    scored on the rooms' oracle Gaussians), its 3D CSA on the splats at least ``FIT_TO_ORACLE_MIN_SHARE`` of the
    control's. ``pairs``: ``(fitted, control)`` Table-1 labels; the pair whose fitted row is ``recipe`` (the
    profile's method for fitted splats) decides, else the first (the full model's). The detail gives every pair, each
    ratio with its paired 95 % interval over the val rooms (``paired_csa_ratio``); the rule reads the ratio alone."""
    if splats != "fit" or not pairs:
        return {}

    def share(pair: tuple[str, str]) -> tuple[bool, str]:
        fitted, oracle = (interval_of(reports[label], "3d", "CSA") for label in pair)
        mine, control = fitted.value, oracle.value
        ok = mine is not None and bool(control) and mine >= FIT_TO_ORACLE_MIN_SHARE * control
        ratio = f"{100 * mine / control:.1f} %" if mine is not None and control else "-"
        paired = paired_csa_ratio(reports[pair[0]], reports[pair[1]])
        if paired is not None and paired.low is not None:
            ratio += (f" (paired 95 % interval over the {paired.scenes} val rooms: {100 * paired.low:.1f}-"
                      f"{100 * paired.high:.1f} %)")
        return ok, f"{pair[0]}: fitted {_cell(fitted)} vs oracle {_cell(oracle)}: {ratio}"

    decisive = next((pair for pair in pairs if pair[0] == recipe), pairs[0])
    ok, detail = share(decisive)
    others = [share(pair)[1] for pair in pairs if pair != decisive]
    name = f"3D CSA on fitted splats >= {100 * FIT_TO_ORACLE_MIN_SHARE:.0f} % of the oracle control ({decisive[0]})"
    return {name: (ok, detail + ("; the other methods: " + "; ".join(others) if others else ""))}


def control_pairs(rows: Sequence[Table1Row], trained_on: dict[str, str]) -> list[tuple[str, str]]:
    """``(fitted, control)`` labels: each row trained and scored on oracle Gaussians, with the row of the full
    run on the splats that has the same bench options and as many ensemble members, in the rows' order."""
    pairs = []
    for control in rows:
        if control.scored_on != "oracle" or trained_on.get(control.run) != "oracle":
            continue
        fitted = next((r.label for r in rows if r.run == "full" and r.scored_on == "splats"
                       and r.options == control.options and r.stacking_run is None
                       and len(r.ensemble) == len(control.ensemble)), None)
        if fitted is not None:
            pairs.append((fitted, control.label))
    return pairs


def format_checks(result: dict) -> str:
    return "\n".join(f"- [{'x' if ok else ' '}] {name}: {detail}" for name, (ok, detail) in result.items()) + "\n"
