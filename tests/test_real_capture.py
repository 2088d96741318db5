"""The real robot capture (../shared/data/real/screwmimic_close_laptop_2) with the default options and
no masks: a person closes a laptop lid on a table, hands on the lid in the end state.

Ground truth: ``gt_estimate.json`` (RANSAC planes of the lid, trusted to a few degrees and ~1 cm).
Its ``angle_deg_abs`` (83.9) is the angle BETWEEN the two lid planes, which is at most 90 deg; the
lid's turn about the hinge is its supplement: measured from the hinge to the lid in each state it
is 96.2 deg, and turning the start lid by 96.2 deg about the estimated hinge lands it on the end lid
with a median gap of 1.8 mm (by 83.9 deg: 18.3 mm). So the turn is checked against 180 - 83.9.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import REPO_ROOT

REAL = REPO_ROOT.parent / "shared" / "data" / "real" / "screwmimic_close_laptop_2"
requires_real = pytest.mark.skipif(not (REAL / "gt_estimate.json").is_file(),
                                   reason=f"real capture not found at {REAL} (see ../shared/README.md)")


@pytest.fixture(scope="module")
def laptop():
    import sparseart

    gt = json.loads((REAL / "gt_estimate.json").read_text())["joints"][0]
    return sparseart.run(REAL), gt


@requires_real
def test_real_laptop_lid_hinge_and_turn(laptop) -> None:
    result, gt = laptop
    revolute = [joint for _, joint in result.joints if joint.type == "revolute"]
    assert revolute, f"no revolute joint found: {result.warnings}"
    joint = max(revolute, key=lambda j: j.confidence)
    _assert_lid_like_the_estimate(joint, gt)
    assert np.isfinite(joint.uncertainty["axis_deg"]) and joint.confidence > 0.2


@requires_real
def test_real_laptop_confidence_reads_the_residual_beyond_its_noise(laptop) -> None:
    # Sensor depth leaves a residual floor no motion removes (the lid's two disjoint samples of
    # one state pair at 3.8 mm, the fit at 4.5 mm): read against the raw residual the correct
    # lid scored 0.66; now 0.77, clean laptop renders 0.80-0.86 (experiment EXP-032).
    result, _ = laptop
    joint = max((joint for _, joint in result.joints if joint.type == "revolute"), key=lambda j: j.confidence)
    floor = joint.diagnostics["residual_floor"]
    assert 0.0 < floor < joint.residual
    assert joint.confidence > 0.72


@requires_real
def test_real_end_depth_left_in_a_patch_is_bad_input(tmp_path, capsys) -> None:
    # A failing sensor: the end view's depth valid in a 60 x 60 pixel patch only (3600 points
    # against 174k at start). The labeler finds no usable segment in the end state; that was an
    # internal error (exit 1) and is now one line naming the end depth image, exit 2, nothing written.
    import shutil

    import cv2
    from sparseart.cli import main

    scene = tmp_path / "patch"
    shutil.copytree(REAL, scene)
    path = scene / "end" / "depth" / "000.png"
    depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    kept = np.zeros_like(depth)
    kept[200:260, 300:360] = depth[200:260, 300:360]
    cv2.imwrite(str(path), kept)
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "end/depth/000.png" in err[0] and "valid points in the end state" in err[0], err
    assert not out.exists()


@requires_real
def test_real_end_pose_off_by_30_cm_is_placed_by_the_pictures(laptop, tmp_path) -> None:
    # The robot's head camera did not move, but the recorded end pose drifted 30 cm: the end
    # picture repeats the start's, so the end view is placed by the start pose. Before, two "lids"
    # came out (one flagged unstable) in 65 s.
    import shutil

    import sparseart
    from sparseart.bench.metrics import axis_angle_error_deg

    scene = tmp_path / "drifted"
    shutil.copytree(REAL, scene)
    cameras = json.loads((scene / "cameras.json").read_text())
    cameras["end"][0]["cam_to_world"][0][3] += 0.3
    (scene / "cameras.json").write_text(json.dumps(cameras))
    drifted = sparseart.run(scene)
    result, gt = laptop
    assert any("repeat the pictures" in w for w in drifted.warnings), drifted.warnings
    assert len(drifted.joints) == 1
    ((_, joint),) = drifted.joints
    (_, reference), = result.joints
    assert axis_angle_error_deg(joint.axis, gt["axis"]) < 5.0
    assert abs(abs(joint.angle) - abs(reference.angle)) < np.radians(1.0)


@requires_real
def test_real_laptop_on_a_turned_table_gives_one_lid(tmp_path) -> None:
    # The same capture with its world frame turned 90 deg about the vertical through the laptop
    # (as if the laptop stood turned on the table). The strip of the lid under the closing hands
    # lands, by a 70 deg turn, on the table the lid revealed behind it (points the start view
    # never saw); it came out as the only lid, 70.1 deg at confidence 0.97. Now it joins the lid.
    import shutil

    import sparseart
    from scipy.spatial.transform import Rotation
    from sparseart.bench.metrics import axis_angle_error_deg, point_to_line_distance

    gt = json.loads((REAL / "gt_estimate.json").read_text())["joints"][0]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 90.0, degrees=True).as_matrix()
    turn[:3, 3] = np.asarray(gt["origin"]) - turn[:3, :3] @ np.asarray(gt["origin"])
    scene = tmp_path / "turned"
    shutil.copytree(REAL, scene)
    cameras = json.loads((scene / "cameras.json").read_text())
    for state in ("start", "end"):
        for view in cameras[state]:
            view["cam_to_world"] = (turn @ np.asarray(view["cam_to_world"])).tolist()
    (scene / "cameras.json").write_text(json.dumps(cameras))
    result = sparseart.run(scene)
    assert len(result.joints) == 1, [(j.type, math.degrees(j.angle or 0.0)) for _, j in result.joints]
    ((_, joint),) = result.joints
    axis = turn[:3, :3] @ np.asarray(gt["axis"])
    assert axis_angle_error_deg(joint.axis, axis) < 5.0
    assert point_to_line_distance(np.asarray(gt["origin"]), joint.axis, joint.origin) < 0.02
    assert abs(abs(math.degrees(joint.angle)) - (180.0 - gt["angle_deg_abs"])) < 10.0


def _lid(result):
    """The one revolute joint of a run on the laptop capture (fails with the joints found)."""
    revolute = [joint for _, joint in result.joints if joint.type == "revolute"]
    assert len(revolute) == 1, [(j.type, math.degrees(j.angle or 0.0), j.confidence) for _, j in result.joints]
    return revolute[0]


def _assert_lid_like_the_estimate(joint, gt, to_world=np.eye(4)) -> None:
    """Axis within 5 deg, hinge line within 2 cm, turn within 10 deg of the estimate; ``to_world``
    maps the joint's frame (a camera frame for unposed runs) into the estimate's world frame."""
    from sparseart.bench.metrics import axis_angle_error_deg, point_to_line_distance

    axis = to_world[:3, :3] @ joint.axis
    origin = to_world[:3, :3] @ joint.origin + to_world[:3, 3]
    assert axis_angle_error_deg(axis, gt["axis"]) < 5.0
    assert point_to_line_distance(np.asarray(gt["origin"]), axis, origin) < 0.02
    turn = abs(math.degrees(joint.angle))
    assert abs(min(turn, 360.0 - turn) - (180.0 - gt["angle_deg_abs"])) < 10.0


@requires_real
def test_real_laptop_opened_instead_of_closed(laptop, tmp_path) -> None:
    # The capture played backwards: a person opens the lid, the hands are on it in the START
    # state. The same hinge comes out, turning the other way.
    import sparseart
    from sparseart.datasets.capture_variants import played_backwards

    result, gt = laptop
    opened = _lid(sparseart.run(played_backwards(REAL, tmp_path / "opened")))
    _assert_lid_like_the_estimate(opened, gt)
    closed = _lid(result)
    assert np.sign(opened.angle * (opened.axis @ closed.axis)) == -np.sign(closed.angle)


@requires_real
def test_real_laptop_without_camera_poses(laptop, tmp_path) -> None:
    # No cam_to_world (a capture whose robot did not log its head pose): the result is in the
    # start camera's frame; mapped to the world by the logged pose it is the same hinge.
    import sparseart
    from sparseart.datasets.capture_variants import without_poses

    _, gt = laptop
    result = sparseart.run(without_poses(REAL, tmp_path / "unposed"))
    assert result.frame_kind == "camera"
    to_world = np.asarray(json.loads((REAL / "cameras.json").read_text())["start"][0]["cam_to_world"])
    _assert_lid_like_the_estimate(_lid(result), gt, to_world)


@requires_real
def test_real_laptop_at_half_resolution_as_jpeg(laptop, tmp_path) -> None:
    # 320 x 240 (depth subsampled, K halved) and the pictures as JPEG at quality 60: a cheaper
    # camera's capture of the same scene.
    import sparseart
    from sparseart.datasets.capture_variants import downscaled

    _, gt = laptop
    _assert_lid_like_the_estimate(_lid(sparseart.run(downscaled(REAL, tmp_path / "half", 2, 60))), gt)


@requires_real
def test_real_scene_where_nothing_moved_has_no_part(tmp_path) -> None:
    # The start capture twice, the second with sensor-like depth noise (0.3 % of the distance)
    # and image noise: nothing moved, and nothing may come out as a part.
    import sparseart
    from sparseart.datasets.capture_variants import still_twice

    result = sparseart.run(still_twice(REAL, tmp_path / "still", 0.003, 4.0))
    assert not result.joints, [(j.type, j.confidence) for _, j in result.joints]
    assert any("no part moved" in w for w in result.warnings), result.warnings


@requires_real
def test_real_laptop_with_noisier_depth(laptop, tmp_path) -> None:
    # Both depth images with 0.5 % multiplicative per-pixel noise on top of the sensor's own (a
    # cheaper or farther sensor: 4 mm at the lid): the same one lid.
    import sparseart
    from sparseart.datasets.capture_variants import with_depth_noise

    _, gt = laptop
    _assert_lid_like_the_estimate(_lid(sparseart.run(with_depth_noise(REAL, tmp_path / "noisier", 0.005, 0.005))), gt)


@requires_real
def test_real_laptop_seen_from_a_moved_camera_at_the_end(laptop, tmp_path) -> None:
    # The end picture re-rendered from a camera 10 cm to the side and turned 5 deg (a head or a
    # phone that moved between the pictures), posed and without poses: the same hinge.
    import sparseart
    from sparseart.datasets.capture_variants import moved_end_camera

    _, gt = laptop
    _assert_lid_like_the_estimate(_lid(sparseart.run(moved_end_camera(REAL, tmp_path / "posed", 0.1, 5.0))), gt)
    result = sparseart.run(moved_end_camera(REAL, tmp_path / "unposed", 0.1, 5.0, posed=False))
    to_world = np.asarray(json.loads((REAL / "cameras.json").read_text())["start"][0]["cam_to_world"])
    _assert_lid_like_the_estimate(_lid(result), gt, to_world)


@requires_real
def test_real_laptop_in_heavy_noise_flags_the_revealed_strip(laptop, tmp_path) -> None:
    # 1 % per-pixel depth noise in both states (8 mm at the lid), noise draw 1: besides the lid
    # (96.7 deg), a 127 deg turn laid the hands' strip almost only onto the table the lid
    # revealed (4 % of its hits on seen points) and came out as a second lid, 72 deg at
    # confidence 0.75. It stays a part, said and trusted a quarter as much.
    import sparseart
    from sparseart.datasets.capture_variants import with_depth_noise

    _, gt = laptop
    result = sparseart.run(with_depth_noise(REAL, tmp_path / "noisy", 0.01, 0.01, seed=1))
    lid = max((joint for _, joint in result.joints), key=lambda joint: joint.confidence)
    _assert_lid_like_the_estimate(lid, gt)
    others = [joint for _, joint in result.joints if joint is not lid]
    assert all(joint.confidence < 0.5 * lid.confidence for joint in others), [j.confidence for j in others]
    assert any("onto surfaces the other state could not see" in w for w in result.warnings) or not others
