"""Accuracy on the 16 real PartNet-Mobility objects, rendered posed with clean depth, 3 views per
state, through the real default pipeline (rule-based labeler on the rendered masks).

Issue 2 floor: type correct >= 90 %, median axis angle error <= 1 deg, median axis position
error <= 0.02 object units, over every movable joint of every object.
"""
from __future__ import annotations

import statistics

import pytest

from sparseart.bench.objects import BenchSetting, evaluate_object, format_table

from conftest import PARTNET_DIR, requires_partnet

pytestmark = [requires_partnet, pytest.mark.partnet, pytest.mark.slow]


@pytest.fixture(scope="module")
def partnet_rows(tmp_path_factory) -> list[dict]:
    work = tmp_path_factory.mktemp("partnet")
    rows = []
    for object_dir in sorted(p for p in PARTNET_DIR.iterdir() if (p / "mobility.urdf").exists()):
        rows.extend(evaluate_object(object_dir, work, BenchSetting(views=3, seed=0)))
    print("\n" + format_table(rows))
    return rows


def test_all_sixteen_objects_present() -> None:
    objects = [p for p in PARTNET_DIR.iterdir() if (p / "mobility.urdf").exists()]
    assert len(objects) == 16


def test_partnet_accuracy_floor(partnet_rows) -> None:
    rows = partnet_rows
    assert len(rows) >= 21  # 14 single-joint objects + 2 + 5 joints
    type_accuracy = sum(r["type_correct"] for r in rows) / len(rows)
    axis_median = statistics.median(r["axis_deg"] for r in rows)
    positions = [r["position"] for r in rows if r["position"] is not None]
    position_median = statistics.median(positions)
    assert type_accuracy >= 0.90, format_table(rows)
    assert axis_median <= 1.0, format_table(rows)
    assert position_median <= 0.02, format_table(rows)


def test_noisy_depth_small_static_base(tmp_path) -> None:
    """The laptop at 1 % depth noise + flying pixels: its small visible base overlaps itself less
    than a spurious registration does, so no pair passes the static test; the fallback takes the
    pair that staying put explains nearly as well (not the largest, the lid)."""
    rows = evaluate_object(PARTNET_DIR / "laptop_rotate_10211", tmp_path,
                           BenchSetting(views=3, seed=0, depth_noise=0.01, flying_pixels=0.5))
    (row,) = rows
    assert row["pred_type"] == "revolute", format_table(rows)
    assert row["axis_deg"] < 3.0, format_table(rows)
