"""Paste the corpus bench's tables into the docs: one script, never by hand.

    sparseart bench --corpus --settings default unposed realistic robot-1view --seeds 0 --out OUT
    python benchmarks/corpus_tables.py OUT [OUT ...]

Reads each OUT's ``rows.json`` (rows of ``sparseart bench``), writes
``benchmarks/results/current/corpus.txt`` (the summary per setting beside the ICP peer, the stated
sigma's coverage at 1 and 2 sigma, and the whole motion right per category) and replaces the part of
``docs/benchmarks.md`` between ``<!-- corpus:begin -->`` and ``<!-- corpus:end -->`` with it.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from sparseart.bench.grid import aggregate, category_table, machine_line, summary_table
from sparseart.bench.metrics import covered_share

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "benchmarks" / "results" / "current" / "corpus.txt"
DOCS = ROOT / "docs" / "benchmarks.md"
BEGIN, END = "<!-- corpus:begin -->", "<!-- corpus:end -->"


def coverage_lines(rows: list[dict]) -> list[str]:
    """Per setting: the share of successful joints whose axis error lies within 1 and 2 stated sigma."""
    lines = [f"{'setting':17s} {'joints':>6s} {'axis 1σ':>8s} {'axis 2σ':>8s}"]
    for setting in dict.fromkeys(r["setting"] for r in rows):
        ours = [r for r in rows if r["setting"] == setting and r["method"] == "sparseart"]
        count, one = covered_share(ours, "axis_deg", "axis_sigma_deg", right_type=False)
        _, two = covered_share(ours, "axis_deg", "axis_sigma_deg", factor=2.0, right_type=False)
        lines.append(f"{setting:17s} {count:6d} {one if one is not None else float('nan'):8.2f} "
                     f"{two if two is not None else float('nan'):8.2f}")
    return lines


def corpus_text(rows: list[dict]) -> str:
    summary = aggregate(rows, ("setting", "method"))
    per_category = aggregate(rows, ("category", "setting", "method"))
    seeds = sorted({r.get("config", {}).get("seed") for r in rows})
    return "\n".join([f"# sparseart bench --corpus, seeds {seeds}; {machine_line()}",
                      "# motion = the whole motion right: type, axis < 10 deg, angle < 10 deg or slide within 10 % "
                      "of its travel, and a revolute hinge line within 0.05 object units",
                      summary_table(summary), "",
                      "stated axis sigma against the error (successful joints; honest ~63 % / ~95 %):",
                      *coverage_lines(rows), "",
                      "the whole motion right per category (sparseart/peer, joints):",
                      category_table(per_category)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outs", nargs="+", type=Path, help="sparseart bench --out folders")
    args = parser.parse_args()
    rows = [row for out in args.outs for row in json.loads((out / "rows.json").read_text())]
    text = corpus_text(rows)
    RESULT.write_text(text + "\n")
    docs = DOCS.read_text()
    head, rest = docs.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    DOCS.write_text(f"{head}{BEGIN}\n```text\n{text}\n```\n{END}{tail}")
    print(text)


if __name__ == "__main__":
    main()
