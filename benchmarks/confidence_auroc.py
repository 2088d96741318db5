"""How well the reported confidence tells right joints from wrong ones, from bench rows.

Usage: ``python benchmarks/confidence_auroc.py ROWS.json [ROWS.json ...]`` with the ``rows.json``
of ``sparseart bench`` (the rows of experiment EXP-032 are in the ``notebook-archive`` tag).
Per file and setting, over the matched sparseart rows: how many joints are right (axis error
< 10 deg) and wrong, the median confidence of each, and the AUROC of the confidence as a
right-vs-wrong score (the probability that a random right joint gets a higher confidence than a
random wrong one; Mann-Whitney U / (n_right n_wrong)). Unmatched ground-truth joints have no
confidence and are left out. O(R log R) for R rows.
"""
from __future__ import annotations

import json
import sys

import numpy as np
from scipy.stats import mannwhitneyu

SUCCESS_DEG = 10.0


def summarise(rows: list[dict]) -> tuple[int, float, int, float, float]:
    """(n right, median confidence right, n wrong, median wrong, AUROC); NaN where undefined."""
    right = np.array([r["confidence"] for r in rows if r["axis_deg"] < SUCCESS_DEG])
    wrong = np.array([r["confidence"] for r in rows if r["axis_deg"] >= SUCCESS_DEG])
    auroc = (mannwhitneyu(right, wrong).statistic / (len(right) * len(wrong))
             if len(right) and len(wrong) else float("nan"))
    return (len(right), float(np.median(right)) if len(right) else float("nan"), len(wrong),
            float(np.median(wrong)) if len(wrong) else float("nan"), float(auroc))


def main(paths: list[str]) -> None:
    print(f"{'file':48s} {'setting':20s} right  median  wrong  median  AUROC")
    for path in paths:
        rows = [r for r in json.load(open(path)) if r["method"] == "sparseart" and not r["unmatched"]
                and r.get("confidence") is not None]
        for setting in sorted({r["setting"] for r in rows}) + ["ALL"]:
            chosen = [r for r in rows if setting in ("ALL", r["setting"])]
            n_right, med_right, n_wrong, med_wrong, auroc = summarise(chosen)
            print(f"{path[-48:]:48s} {setting:20s} {n_right:5d}  {med_right:6.3f}  "
                  f"{n_wrong:5d}  {med_wrong:6.3f}  {auroc:5.3f}")


if __name__ == "__main__":
    main(sys.argv[1:])
