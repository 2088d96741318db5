"""Compare two ``sparseart bench`` runs row by row: what a change moved.

    python benchmarks/compare_rows.py BEFORE/rows.csv AFTER/rows.csv [--degrees 1.0] [--method sparseart]

Rows of one method are paired by (object, setting, joint name) in the order they occur (one row
per seed, seeds in the same order in both runs; rows present in only one run are left out and
counted). Per setting it prints the joints, the successes (axis error < 10 deg; an unmatched
joint counts ``UNMATCHED_AXIS_DEG``, 90), the correct types, the median axis error and the movable
parts that match no true joint (``extra parts``) before -> after; then every
paired row whose axis error moved by more than ``--degrees``, crossed the 10 deg line or changed
its predicted type. O(R log R) for R rows.
"""
from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict

import numpy as np

from sparseart.bench.grid import extra_parts as grid_extra_parts
from sparseart.bench.metrics import SUCCESS_AXIS_DEG, UNMATCHED_AXIS_DEG


def axis_error(row: dict) -> float:
    """The row's axis error in degrees; ``UNMATCHED_AXIS_DEG`` for an unmatched joint or a missing value."""
    if row["unmatched"] in ("True", "true", "1") or row["axis_deg"] in ("", "nan", "None"):
        return UNMATCHED_AXIS_DEG
    return float(row["axis_deg"])


def read_rows(path: str, method: str) -> list[dict]:
    with open(path, newline="") as handle:
        return [row for row in csv.DictReader(handle) if row["method"] == method]


def pair_rows(before: list[dict], after: list[dict]) -> tuple[list[tuple[dict, dict]], int]:
    """(pairs of rows with the same object, setting and joint name, matched in order of occurrence;
    the number of rows left unpaired in either run)."""
    pending: dict[tuple, list[dict]] = defaultdict(list)
    for row in before:
        pending[(row["object"], row["setting"], row["name"])].append(row)
    pairs = []
    for row in after:
        waiting = pending.get((row["object"], row["setting"], row["name"]))
        if waiting:
            pairs.append((waiting.pop(0), row))
    unpaired = len(before) + len(after) - 2 * len(pairs)
    return pairs, unpaired


def extra_parts(rows: list[dict]) -> int | None:
    """Movable parts reported beyond the true joints they were matched to, summed over scenes:
    :func:`sparseart.bench.grid.extra_parts` on the CSV rows; None when the rows carry no
    ``n_predicted``. Rows written before the seed column was added tell their scenes apart by
    ``pipeline_seconds``. O(R)."""
    if not rows or any(not row.get("n_predicted") for row in rows):
        return None
    return grid_extra_parts([{"object": row["object"], "setting": row["setting"], "method": row["method"],
                              "config": {"seed": row.get("seed") or row.get("pipeline_seconds")},
                              "n_predicted": int(row["n_predicted"]),
                              "unmatched": row["unmatched"] in ("True", "true", "1")} for row in rows])["extra_parts"]


def report(pairs: list[tuple[dict, dict]], degrees: float) -> list[str]:
    lines = []
    for setting in sorted({b["setting"] for b, _ in pairs}):
        chosen = [(b, a) for b, a in pairs if b["setting"] == setting]
        eb = np.array([axis_error(b) for b, _ in chosen])
        ea = np.array([axis_error(a) for _, a in chosen])
        tb = sum(b["type_correct"] == "True" for b, _ in chosen)
        ta = sum(a["type_correct"] == "True" for _, a in chosen)
        xb, xa = extra_parts([b for b, _ in chosen]), extra_parts([a for _, a in chosen])
        lines.append(f"{setting}: n {len(chosen)} success {int((eb < SUCCESS_AXIS_DEG).sum())} -> "
                     f"{int((ea < SUCCESS_AXIS_DEG).sum())}, type {tb} -> {ta}, median {np.median(eb):.2f} -> "
                     f"{np.median(ea):.2f}" + ("" if xb is None or xa is None else f", extra parts {xb} -> {xa}"))
    for b, a in pairs:
        x, y = axis_error(b), axis_error(a)
        if abs(x - y) > degrees or (x < SUCCESS_AXIS_DEG) != (y < SUCCESS_AXIS_DEG) or b["pred_type"] != a["pred_type"]:
            lines.append(f"  {b['object'][:24]:24s} {b['setting'][:18]:18s} {b['name']} {x:6.2f} -> {y:6.2f} "
                         f"{b['pred_type']}->{a['pred_type']}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("--degrees", type=float, default=1.0, help="list rows whose axis error moved more (deg)")
    parser.add_argument("--method", default="sparseart", help="the method column to compare (default sparseart)")
    args = parser.parse_args(argv)
    pairs, unpaired = pair_rows(read_rows(args.before, args.method), read_rows(args.after, args.method))
    lines = report(pairs, args.degrees)
    if unpaired:
        lines.append(f"({unpaired} rows present in one run only were left out)")
    try:
        print("\n".join(lines))
    except BrokenPipeError:     # piped into head: stop quietly
        sys.stderr.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
