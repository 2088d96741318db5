"""Accuracy and seconds per scene over the shared PartNet-Mobility objects.

    python benchmarks/partnet_accuracy.py [--views 3] [--seed 0] [--no-masks] [--out FILE] [OBJECT ...]

Renders each object at two joint states (posed, clean depth), runs the default pipeline and
prints one line per joint and the summary of design section 4 (axis position in raw object units).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from sparseart.bench.objects import BenchSetting, evaluate_object, format_table

PARTNET = Path(__file__).resolve().parents[2] / "shared" / "data" / "partnet"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("objects", nargs="*")
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-masks", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="also write the table and JSON rows here")
    args = parser.parse_args()
    if not PARTNET.is_dir():
        print(f"no shared data at {PARTNET}", file=sys.stderr)
        return 2
    names = args.objects or sorted(p.name for p in PARTNET.iterdir() if (p / "mobility.urdf").exists())
    setting = BenchSetting(views=args.views, seed=args.seed, use_masks=not args.no_masks)
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for name in names:
            began = time.perf_counter()
            rows.extend(evaluate_object(PARTNET / name, work, setting))
            print(f"{name}: {time.perf_counter() - began:.1f}s", file=sys.stderr, flush=True)
    header = (f"# {date.today()} on {platform.machine()} ({platform.processor() or 'cpu'}), "
              f"views={args.views} seed={args.seed} masks={not args.no_masks}, posed, clean depth, 320x240")
    table = header + "\n" + format_table(rows)
    print(table)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(table + "\n")
        args.out.with_suffix(".json").write_text(json.dumps(
            [{k: v for k, v in r.items() if k != "warnings"} for r in rows], indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
