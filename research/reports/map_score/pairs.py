"""Paired differences of the map rules against every other row of a report, per rotated set and summed.

Run from the repository root after the report this folder holds was made:

    python research/reports/map_score/pairs.py runs/report_map

It reads ``seed_<s>/<strategy>/results.json`` of the report, takes mIoU@0.4 (in points) per seed, and prints,
for each map rule against each other row, the mean paired difference over seeds with its 95 % Student-t
interval and how many seeds agree with the mean's sign; ``pairs.csv`` beside this script gets the same rows.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

from lightning_vtr.experiments.statistics import paired_difference

TREATMENTS = ("map", "map_tau1", "visible_tau10_search")
BASELINES = ("none", "random", "random_area", "visible_tau10_search")
SETS = ("aligned", "hemispherical", "spherical", "rotated (sum)")


def per_seed(report: Path) -> dict[str, dict[str, dict[int, float]]]:
    """strategy -> view set -> seed -> mIoU@0.4 in points (``rotated (sum)``: Hemispherical + Spherical)."""
    values: dict[str, dict[str, dict[int, float]]] = {}
    for path in sorted(report.glob("seed_*/*/results.json")):
        seed, strategy = int(path.parent.parent.name.removeprefix("seed_")), path.parent.name
        results = json.loads(path.read_text())["results"]
        sets = values.setdefault(strategy, {})
        for name in SETS[:3]:
            sets.setdefault(name, {})[seed] = 100 * results[name]["iou@0.4"]
        sets.setdefault(SETS[3], {})[seed] = sets["hemispherical"][seed] + sets["spherical"][seed]
    return values


def main(report: Path) -> None:
    values = per_seed(report)
    rows = []
    for treatment in TREATMENTS:
        for baseline in BASELINES:
            if treatment == baseline:
                continue
            row = {"difference": f"{treatment} - {baseline}"}
            for name in SETS:
                est = paired_difference(values[treatment][name], values[baseline][name])
                row[name] = f"{est.mean:+.2f} [{est.low:+.2f}, {est.high:+.2f}] {est.agree}/{est.n}"
            rows.append(row)
    print("| paired difference, mIoU@0.4 points [95 % CI], seeds agreeing | " + " | ".join(SETS) + " |")
    print("|---" * (len(SETS) + 1) + "|")
    for row in rows:
        print("| " + " | ".join(row.values()) + " |")
    with open(Path(__file__).with_name("pairs.csv"), "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "runs/report_map"))
