"""sparseart bench: the grid, the ICP peer, sensor degradations, outputs, stability report."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sparseart.bench.icp_peer import PeerOptions, icp_peer, joint_from_transform, register_part_icp
from sparseart.bench.objects import BenchSetting, evaluate_object
from sparseart.bench.grid import grid_settings, ratio_note, run_bench
from sparseart.bench.plots import pareto_front
from sparseart.datasets.scene_writer import add_flying_pixels, perturb_pose
from sparseart.geometry.transforms import transform_from_prismatic, transform_from_revolute
from sparseart.bench.metrics import axis_angle_error_deg, axis_position_error
from sparseart.bench.stability import DOOR_AXIS, DOOR_ORIGIN, cases, format_report, observe, run_case
from sparseart.types import LabelledCloud

from conftest import PARTNET_DIR, requires_partnet


def test_pareto_front():
    points = [(1.0, 5.0), (2.0, 1.0), (3.0, 3.0), (0.5, 10.0), (2.0, 1.0), (4.0, 0.5)]
    assert pareto_front(points) == [0, 1, 3, 4, 5]  # (3, 3) is dominated by (2, 1)


def test_grid_is_one_factor_at_a_time():
    settings, skipped = grid_settings(seed=3)
    default = settings[0]
    assert default.name == "default" and default.views == 3 and default.posed and default.depth_noise == 0
    groups = {"views": {"views"}, "posed": {"posed"}, "depth": {"depth_noise", "flying_pixels"},
              "pose": {"pose_noise_deg", "pose_noise_m"}, "refine": {"refine"},
              "masks": {"scramble_masks"}, "no_masks": {"use_masks"}, "segmenter": {"segmenter"},
              "budget": {"budget"}, "unposed_no_masks": {"posed", "use_masks"},
              "camera_moved": {"posed", "same_cameras"}, "camera_moved_no_masks": {"posed", "use_masks", "same_cameras"}}
    realistic = next(s for s in settings if s.name == "realistic")
    assert not realistic.posed and realistic.views == 3 and min(realistic.realism.levels().values()) == 1.0
    by_name = {s.name: s for s in settings}
    for setting in settings[1:]:
        assert setting.seed == 3
        if setting.name.endswith("-xfeat"):   # the same setting with the learned matcher instead of SIFT
            base = by_name[setting.name[:-len("-xfeat")]]
            assert setting.matcher and setting.matcher.startswith("xfeat:") and base.matcher is None
            assert {k for k, v in vars(setting).items() if k != "name" and v != getattr(base, k)} == {"matcher"}
            continue
        if not setting.realism.is_clean:   # realistic renders: compared with "realistic" / one knob alone
            if setting.name.startswith("knob-"):
                knob = setting.name[len("knob-"):]
                assert {k for k, v in setting.realism.levels().items() if v} == {knob}
                assert setting.realism.levels()[knob] == 1.0 and setting.posed == (knob == "pose_noise")
            elif setting.name == "robot-1view":   # a calibrated static head camera: the real captures' shape
                changed = {k for k, v in vars(setting).items() if k != "name" and v != getattr(realistic, k)}
                assert changed == {"views", "posed", "use_masks", "realism"}, changed
                assert setting.views == 1 and setting.posed and not setting.use_masks
                assert setting.realism == realistic.realism.with_levels(pose_noise=0.0)
            elif setting.name == "robot-sensor-1view":   # the same with a depth sensor (no per-state warp)
                robot = by_name["robot-1view"]
                changed = {k for k, v in vars(setting).items() if k != "name" and v != getattr(robot, k)}
                assert changed == {"realism"}, changed
                assert setting.realism == robot.realism.with_levels(depth_warp=0.0, depth_scale=0.0, confidence=0.0)
            else:
                changed = {k for k, v in vars(setting).items() if k != "name" and v != getattr(realistic, k)}
                assert changed <= {"views"} or changed <= {"refine"}, (setting.name, changed)
            continue
        changed = {k for k, v in vars(setting).items() if k != "name" and v != getattr(default, k)}
        assert any(changed and changed <= group for group in groups.values()), (setting.name, changed)
    names = [s.name for s in settings]
    assert {"views1", "views2", "views4", "unposed", "depth1%+fly", "depth3%+fly", "pose0.5deg0.5cm",
            "masks-scrambled", "no-masks", "builtin-segmenter", "budget-fast", "budget-best", "unposed-moved",
            "unposed-no-masks-moved"} <= set(names)
    assert not by_name["unposed-moved"].same_cameras and all(s.same_cameras for s in settings
                                                             if not s.name.endswith("-moved"))
    assert ("refine" in names) != any(r.startswith("refine") for r in skipped)  # run or skipped with a reason
    assert ("realistic-xfeat" in names) != any(r.startswith("*-xfeat") for r in skipped)
    assert grid_settings(quick=True)[0] == [BenchSetting(name="default")]
    assert {"realistic", "realistic-1view", "robot-1view", "robot-sensor-1view", "knob-jpeg",
            "knob-occluder"} <= set(names)


def test_settings_are_selected_by_pattern():
    from sparseart.bench.grid import select_settings
    from sparseart.types import SceneError

    settings, _ = grid_settings()
    assert [s.name for s in select_settings(settings, ["default", "realistic*"])][:3] == [
        "default", "realistic", "realistic-1view"]
    assert select_settings(settings, None) == settings
    with pytest.raises(SceneError, match="nothing-like-this"):
        select_settings(settings, ["nothing-like-this"])


def test_peer_recovers_revolute_and_prismatic_parts():
    door_motion = transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, math.radians(35))
    start, end = observe("door", door_motion, 1500, 1e-3, seed=1)
    transform, info = register_part_icp(start, end)
    joint = joint_from_transform(transform, start, info["fitness"], info["rmse"])
    assert joint.type == "revolute"
    assert axis_angle_error_deg(joint.axis, DOOR_AXIS) < 3.0
    assert axis_position_error(joint.axis, joint.origin, DOOR_AXIS, DOOR_ORIGIN) < 0.03
    assert abs(math.degrees(joint.angle) - 35.0) < 3.0
    slide = transform_from_prismatic(np.array([0.0, 0.0, 1.0]), 0.3)
    start, end = observe("lshape", slide, 1500, 1e-3, seed=2)
    transform, info = register_part_icp(start, end)
    joint = joint_from_transform(transform, start, info["fitness"], info["rmse"])
    assert joint.type == "prismatic" and abs(joint.distance - 0.3) < 0.02
    assert axis_angle_error_deg(joint.axis, [0.0, 0.0, 1.0]) < 3.0
    with pytest.raises(ValueError, match="at least"):
        register_part_icp(start[:5], end)


def _cloud(state: str, points: np.ndarray) -> LabelledCloud:
    n = len(points)
    return LabelledCloud(state, points, np.full((n, 3), 0.5), np.full(n, -1), np.zeros(n, np.int64),
                         np.arange(n), np.ones(n))


def test_peer_motion_segmentation_without_labels():
    """Ground-truth-free route: moved points + DBSCAN find the door beside a static body."""
    motion = transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, math.radians(40))
    door_start, door_end = observe("door", motion, 1500, 1e-3, seed=4)
    rng = np.random.default_rng(4)
    body = rng.uniform([-1.4, -0.5, -0.6], [-0.9, 0.5, 0.0], (1500, 3))  # static block beside the hinge
    start, end = _cloud("start", np.concatenate([body, door_start])), _cloud("end", np.concatenate([body, door_end]))
    result = icp_peer(start, end, options=PeerOptions(segmentation="motion"))
    assert len(result.joints) == 1
    assert (result.labels.start_part[:1500] == 0).mean() > 0.95
    _, joint = result.joints[0]
    assert joint.type == "revolute" and axis_angle_error_deg(joint.axis, DOOR_AXIS) < 5.0
    assert [s.name for s in result.stages] == ["peer_segment", "peer_register"]
    with pytest.raises(ValueError, match="segmentation"):
        icp_peer(start, end, options=PeerOptions(segmentation="oracle"))


def test_flying_pixels_only_touch_depth_edges():
    depth = np.zeros((40, 60))
    depth[10:30, 10:30] = 1.0  # near box on an empty background
    depth[10:30, 30:50] = 2.0  # far box beside it
    out = add_flying_pixels(depth, 1.0, np.random.default_rng(0))
    changed = out != depth
    assert changed.any()
    interior = np.zeros_like(changed)
    interior[12:28, 12:28] = interior[12:28, 32:48] = True
    assert not changed[interior].any()
    on_step = changed[10:30, 29:31]
    assert on_step.any() and np.all((out[10:30, 29:31][on_step] >= 1.0) & (out[10:30, 29:31][on_step] <= 2.0))
    assert np.array_equal(add_flying_pixels(depth, 0.0, np.random.default_rng(0)), depth)
    with pytest.raises(ValueError, match="flying_pixels"):
        add_flying_pixels(depth, 1.5, np.random.default_rng(0))


def test_pose_noise_has_the_requested_size():
    pose = transform_from_revolute([0.0, 1.0, 0.0], [0.1, 0.2, 0.3], 0.4)
    noisy = perturb_pose(pose, 0.5, 0.005, np.random.default_rng(1))
    relative = noisy[:3, :3] @ pose[:3, :3].T
    assert math.degrees(math.acos(np.clip((np.trace(relative) - 1) / 2, -1, 1))) == pytest.approx(0.5, abs=1e-6)
    assert np.linalg.norm(noisy[:3, 3] - pose[:3, 3]) == pytest.approx(0.005)


def test_stability_cases_flag_with_the_fitter_thresholds():
    angle_cases = {c.value: c for c in cases() if c.sweep == "angle"}
    rows = [run_case(angle_cases[0.5], count=600), run_case(angle_cases[30.0], count=600)]
    assert rows[0]["flagged"] and any("poorly defined" in w for w in rows[0]["warnings"])
    assert not rows[1]["flagged"] and rows[1]["axis_deg"] < 3.0 and rows[1]["type_correct"]
    assert all(math.isfinite(r["condition"]) for r in rows)
    text = format_report(rows)
    assert "small_angle_deg 1" in text and "warnings flag [0.5]" in text
    assert {c.sweep for c in cases(quick=True)} == {"angle", "pivot", "scale", "noise", "outliers"}


def test_ratio_note_names_the_more_accurate_method():
    summary = [{"setting": "default", "method": "sparseart", "axis_deg_median": 0.2, "seconds_median": 4.0,
                "success_rate": 1.0, "type_accuracy": 1.0},
               {"setting": "default", "method": "icp_peer", "axis_deg_median": 0.8, "seconds_median": 1.0,
                "success_rate": 0.5, "type_accuracy": 1.0}]
    note = ratio_note(summary)
    assert "x0.25" in note and "x4.00" in note and note.endswith("sparseart")


@requires_partnet
def test_bench_on_one_object_writes_everything(tmp_path):
    obj = PARTNET_DIR / "toaster_press_103486"
    # two scenes in two worker processes: the rows must be those of a sequential run (checked below)
    result = run_bench([obj], tmp_path, settings=[BenchSetting(name="default"), BenchSetting(views=1, name="views1")],
                       jobs=2)
    assert not result.failures, result.failures
    assert {r["method"] for r in result.rows} == {"sparseart", "icp_peer"}
    assert [r["setting"] for r in result.rows] == ["default", "default", "views1", "views1"]  # the sequential order
    assert {(s["setting"], s["method"]) for s in result.summary} == {
        (name, method) for name in ("default", "views1") for method in ("sparseart", "icp_peer")}
    assert {(s["category"], s["method"]) for s in result.per_category if s["setting"] == "default"} == {
        ("toaster", "sparseart"), ("toaster", "icp_peer")}
    ours = next(s for s in result.summary if s["method"] == "sparseart")
    assert ours["type_accuracy"] == 1.0 and ours["axis_deg_median"] < 5.0 and ours["fit_seconds_median"] > 0
    # every stated sigma beside its error, and how often it covers it (the toaster's lever slides)
    lever = next(r for r in result.rows if r["method"] == "sparseart")
    assert lever["state_sigma"] > 0 and lever["origin_sigma"] is None and lever["axis_sigma_deg"] > 0
    assert ours["state_sigma_coverage"] in (0.0, 1.0) and ours["position_sigma_coverage"] is None
    assert lever["gt_state"] > 0 and ours["full_success_rate"] in (0.0, 1.0)
    for name in ("rows.csv", "rows.json", "summary.csv", "summary.json", "table.txt", "error_vs_time.png",
                 "error_vs_factor.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert len(json.loads((tmp_path / "rows.json").read_text())) == len(result.rows)
    assert "sparseart vs ICP peer" in (tmp_path / "table.txt").read_text()
    again = evaluate_object(obj, tmp_path / "scenes", BenchSetting(name="default"))  # the render is cached
    assert again[0]["render_seconds"] == 0.0
    timing = ("render_seconds", "pipeline_seconds", "stage_seconds")
    assert [{k: v for k, v in r.items() if k not in timing} for r in again] == \
        [{k: v for k, v in r.items() if k not in timing} for r in result.rows[:1]]
    assert "the whole motion right per category" in (tmp_path / "table.txt").read_text()


def test_cli_bench_rejects_missing_objects(tmp_path, capsys):
    from sparseart.cli import main

    assert main(["bench", "--objects", str(tmp_path / "nope"), "--out", str(tmp_path / "out")]) == 2
    assert "--objects folder not found" in capsys.readouterr().err


@requires_partnet
def test_a_cached_render_of_another_renderer_version_is_rendered_again(tmp_path):
    """The bench reuses a scene folder only when its stamp names the same setting and the same
    renderer: a render from before a renderer change (coplanar duplicates re-coloured the body
    between the states) must not be scored as if it were current."""
    from sparseart.bench.objects import render_cached
    from sparseart.datasets.raycast import RENDERER_VERSION

    setting = BenchSetting(views=1, width=64, height=48)
    scene_dir = tmp_path / "scene"
    _, first = render_cached(PARTNET_DIR / "laptop_rotate_10211", scene_dir, setting)
    _, again = render_cached(PARTNET_DIR / "laptop_rotate_10211", scene_dir, setting)
    assert first > 0 and again == 0.0
    stamp_path = scene_dir / "bench_render.json"
    stamp = json.loads(stamp_path.read_text())
    assert stamp["renderer"] == RENDERER_VERSION
    stamp["renderer"] = RENDERER_VERSION - 1
    stamp_path.write_text(json.dumps(stamp))
    _, old = render_cached(PARTNET_DIR / "laptop_rotate_10211", scene_dir, setting)
    assert old > 0 and json.loads(stamp_path.read_text())["renderer"] == RENDERER_VERSION


def test_seconds_are_read_over_every_seed_s_scene():
    """--seeds renders one scene per seed under one setting name: the median seconds are read over
    all of them (the joints of one scene count once), not over the last seed's scene per object."""
    from sparseart.bench.grid import _stage_stats

    def row(seed: int, seconds: float) -> dict:
        return {"object": "box", "setting": "realistic", "method": "sparseart", "config": {"seed": seed},
                "pipeline_seconds": seconds, "stage_seconds": {"fit": seconds / 2}}

    rows = [row(0, 1.0), row(0, 1.0), row(1, 3.0), row(2, 8.0)]
    stats = _stage_stats(rows)
    assert stats["seconds_median"] == 3.0 and stats["fit_seconds_median"] == 1.5


def test_extra_parts_count_predictions_matched_to_no_true_joint():
    """A scene reporting more movable parts than the true joints it matched has extra parts (an
    arm or a strip of a lid taken for a part); success and axis error cannot show them. Counted
    once per scene (object, setting, method, seed), in the summary, the table and the CSV's seed."""
    from sparseart.bench.grid import aggregate, extra_parts, rows_csv, summary_table

    def row(obj: str, seed: int, predicted: int, unmatched: bool) -> dict:
        return {"object": obj, "setting": "robot-1view", "method": "sparseart", "config": {"seed": seed},
                "name": "joint_0", "n_predicted": predicted, "unmatched": unmatched, "axis_deg": 1.0,
                "type_correct": True, "gt_type": "revolute", "position": 0.0, "state": 0.0,
                "pipeline_seconds": 1.0, "stage_seconds": {}}

    rows = [row("oven", 0, 3, False), row("oven", 0, 3, True),   # two joints, one matched, three parts: 2 extra
            row("box", 0, 1, False), row("box", 1, 2, False),     # seed 1 of the box: 1 extra
            row("door", 0, 0, True)]                              # nothing found: no extra
    assert extra_parts(rows) == {"extra_parts": 3, "extra_scenes": 2}
    summary = aggregate(rows, ("setting", "method"))
    assert summary[0]["extra_parts"] == 3 and summary[0]["extra_scenes"] == 2
    assert summary_table(summary).splitlines()[0].split()[-1] == "extra"
    assert summary_table(summary).splitlines()[1].split()[-1] == "3"
    assert "seed" in rows_csv(rows).splitlines()[0].split(",")


def test_categories_are_read_off_the_object_folder_names():
    from sparseart.bench.grid import category_of

    assert category_of("laptop_rotate_10040") == "laptop"
    assert category_of("oven_7179_multi") == "oven"
    assert category_of("washing_machine_103508") == "washing_machine"
    assert category_of("toaster_press_103486") == "toaster"
    assert category_of("trash_can_102181") == "trash_can"


def test_the_whole_motion_needs_the_hinge_line_and_the_turn_too():
    """The whole motion right (what a robot acts on): the axis alone passes a door turned the
    other way about the right line, and a right turn about a line beside the hinge."""
    from sparseart.bench.grid import aggregate, category_table
    from sparseart.bench.metrics import SUCCESS_POSITION, motion_right, summarise

    def row(obj: str, method: str = "sparseart", **changes) -> dict:
        base = {"object": obj, "setting": "default", "method": method, "config": {"seed": 0}, "name": "joint_0",
                "gt_type": "revolute", "type_correct": True, "axis_deg": 1.0, "position": 0.01, "state": 2.0,
                "gt_state": 90.0, "pipeline_seconds": 1.0, "stage_seconds": {}}
        return base | changes

    right = row("door_1")
    reversed_turn = row("door_2", state=175.0)
    beside = row("door_3", position=SUCCESS_POSITION * 1.2)
    slide = row("drawer_4", gt_type="prismatic", position=None, state=0.01, gt_state=0.3)
    assert [motion_right(r) for r in (right, reversed_turn, beside, slide)] == [True, False, False, True]
    summary = summarise([right, reversed_turn, beside, slide])
    assert summary["success_rate"] == 1.0 and summary["full_success_rate"] == 0.75
    assert summary["motion_success_rate"] == 0.5
    assert motion_right({k: v for k, v in right.items() if k != "gt_state"}) is None
    rows = [right, reversed_turn, beside, slide, row("door_1", method="icp_peer", axis_deg=20.0)]
    per_category = aggregate(rows, ("category", "setting", "method"))
    table = category_table(per_category)
    assert "door" in table and "0.33/0.00 3" in table and "1.00/- 1" in table
