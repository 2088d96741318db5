"""How honest the stated 1-sigma is, from bench rows: 1- and 2-sigma coverage of every stated sigma.

Usage: ``python benchmarks/sigma_coverage.py ROWS.json [ROWS.json ...]`` with the ``rows.json`` of
``sparseart bench``. Per file and setting, over the successful sparseart joints (axis error < 10
deg) of the right type that state the sigma (:func:`sparseart.bench.metrics.covered_share`):
the share whose error lies within 1 x and 2 x it,
for the axis (``axis_deg`` / ``axis_sigma_deg``), the hinge line's position (``position`` /
``origin_sigma``, revolute) and the angle or slide (``state_along`` / ``state_sigma``: the state
read along its own axis, which is what the sigma is about; ``state`` compares whole motions and
carries the axis error too). Honest levels:
63 % / 98 % for the axis (the norm of two components: 1 - exp(-k^2 / 2) for a 2-D normal), at
least that for the position (the lines' closest distance is at most the hinge's 2-D offset
across the axis), 68 % / 95 % for the state (one component). Rows written before the bench
recorded ``origin_sigma`` / ``state_sigma`` / ``state_along`` show "-" there. O(R) for R rows.
"""
from __future__ import annotations

import json
import sys

from sparseart.bench.metrics import covered_share

QUANTITIES = (("axis", "axis_deg", "axis_sigma_deg"), ("position", "position", "origin_sigma"),
              ("state", "state_along", "state_sigma"))


def main(paths: list[str]) -> None:
    print(f"{'file':40s} {'setting':20s} " + " ".join(f"{name:>18s}" for name, _, _ in QUANTITIES))
    print(f"{'':40s} {'':20s} " + " ".join(f"{'n   1σ    2σ':>18s}" for _ in QUANTITIES))
    for path in paths:
        rows = [r for r in json.load(open(path)) if r["method"] == "sparseart" and not r.get("unmatched")]
        for setting in sorted({r["setting"] for r in rows}):
            chosen = [r for r in rows if r["setting"] == setting]
            cells = []
            for _, error, sigma in QUANTITIES:
                n, one = covered_share(chosen, error, sigma)
                two = covered_share(chosen, error, sigma, factor=2.0)[1]
                cells.append(f"{n:4d} {one:5.2f} {two:5.2f}" if n else f"{'-':>18s}")
            print(f"{path[-40:]:40s} {setting:20s} " + " ".join(f"{c:>18s}" for c in cells))


if __name__ == "__main__":
    main(sys.argv[1:])
