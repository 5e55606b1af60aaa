"""Print Table-1 rows (mIoU %) from ``ovgaussian bench`` JSON reports: python scripts/table1.py A.json B.json ..."""

import json
import sys
from pathlib import Path

COLUMNS = ["3d_CSA", "3d_OVA", "3d_CDA", "2d_CSA", "2d_OVA", "2d_NVA", "2d_CDA"]


def main(paths: list[str]) -> None:
    print("| method | " + " | ".join(c.replace("_", " ").upper() for c in COLUMNS) + " |")
    print("|---|" + "---:|" * len(COLUMNS))
    for path in paths:
        report = json.loads(Path(path).read_text())
        row = report["row"]
        label = report.get("label") or Path(path).stem
        cells = ["-" if row.get(c) is None else f"{100 * row[c]:.2f}" for c in COLUMNS]
        print(f"| {label} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
