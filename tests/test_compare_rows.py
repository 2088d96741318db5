"""benchmarks/compare_rows.py: two bench runs paired row by row."""
import csv
import importlib.util

from conftest import REPO_ROOT

FIELDS = ["object", "setting", "method", "name", "gt_type", "pred_type", "type_correct", "unmatched", "axis_deg"]


def _load():
    spec = importlib.util.spec_from_file_location("compare_rows", REPO_ROOT / "benchmarks" / "compare_rows.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _write(path, rows, fields=FIELDS):
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fields)
        writer.writeheader()
        for row in rows:
            writer.writerow(dict(zip(fields, row)))


def test_compare_rows_pairs_seeds_in_order_and_lists_what_moved(tmp_path, capsys):
    before = [("door", "realistic", "sparseart", "joint_0", "revolute", "revolute", "True", "False", "1.0"),
              ("door", "realistic", "sparseart", "joint_0", "revolute", "revolute", "True", "False", "12.0"),
              ("door", "realistic", "icp_peer", "joint_0", "revolute", "revolute", "True", "False", "30.0"),
              ("oven", "realistic", "sparseart", "joint_1", "prismatic", "", "False", "True", ""),
              ("oven", "realistic", "sparseart", "joint_2", "prismatic", "prismatic", "True", "False", "3.0")]
    after = [("door", "realistic", "sparseart", "joint_0", "revolute", "revolute", "True", "False", "1.5"),
             ("door", "realistic", "sparseart", "joint_0", "revolute", "revolute", "True", "False", "4.0"),
             ("oven", "realistic", "sparseart", "joint_1", "prismatic", "prismatic", "True", "False", "2.0")]
    _write(tmp_path / "a.csv", before)
    _write(tmp_path / "b.csv", after)
    assert _load().main([str(tmp_path / "a.csv"), str(tmp_path / "b.csv")]) == 0
    lines = capsys.readouterr().out.splitlines()
    # 3 pairs: successes 1 -> 3 (the unmatched joint counts 90 deg), types 2 -> 3, median 12 -> 2
    assert lines[0] == "realistic: n 3 success 1 -> 3, type 2 -> 3, median 12.00 -> 2.00"
    moved = [line.split() for line in lines[1:-1]]
    assert [(m[0], m[3], m[5]) for m in moved] == [("door", "12.00", "4.00"), ("oven", "90.00", "2.00")]
    assert lines[-1] == "(1 rows present in one run only were left out)"


def test_compare_rows_counts_extra_parts_per_scene(tmp_path, capsys):
    """Parts reported beyond the true joints they matched, per scene (object, setting, seed)."""
    fields = FIELDS + ["n_predicted", "seed"]
    def oven(seed, predicted, second_unmatched):
        return [("oven", "robot", "sparseart", "joint_0", "revolute", "revolute", "True", "False", "1.0", predicted, seed),
                ("oven", "robot", "sparseart", "joint_1", "revolute", "", "False", str(second_unmatched), "90.0",
                 predicted, seed)]

    _write(tmp_path / "a.csv", oven(0, 1, True) + oven(1, 2, False), fields)     # every part matched
    _write(tmp_path / "b.csv", oven(0, 3, True) + oven(1, 2, False), fields)     # seed 0: 3 parts for 1 match
    assert _load().main([str(tmp_path / "a.csv"), str(tmp_path / "b.csv")]) == 0
    assert capsys.readouterr().out.splitlines()[0].endswith("extra parts 0 -> 2")
