"""Parts that look alike and parts seen from changing sides (issue 18): look-alike drawers keep
their identity across the states, a posed laptop whose base is hidden in one state still moves,
and the same multi-part scene gives the same JSON twice."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from conftest import PARTNET_DIR, REPO_ROOT

TWINS_DIR = REPO_ROOT.parent / "shared" / "data" / "partnet-twins"
requires_twins = pytest.mark.skipif(not TWINS_DIR.is_dir(), reason=f"twin objects not found at {TWINS_DIR}")
requires_laptop = pytest.mark.skipif(not (PARTNET_DIR / "laptop_rotate_10211").is_dir(),
                                     reason=f"laptop_rotate_10211 not found in {PARTNET_DIR}")


class _Stop(Exception):
    pass


class _Grab:
    """Runs the rule labeler inside the pipeline, keeps its inputs and labels, then stops the run."""

    name = "rules"

    def __init__(self) -> None:
        from sparseart.labelers.rules import RuleBasedLabeler

        self.inner = RuleBasedLabeler()

    def label(self, start, end, scene=None, aligned=True, motion_hints=None, posed=None):
        self.labels = self.inner.label(start, end, scene, aligned=aligned, motion_hints=motion_hints, posed=posed)
        self.start, self.end = start, end
        if aligned:
            raise _Stop()
        return self.labels


def _labels(scene_dir: Path) -> _Grab:
    from sparseart.io.scene import load_scene
    from sparseart.pipeline import run

    grab = _Grab()
    with pytest.raises(_Stop):
        run(load_scene(scene_dir), labeler=grab)
    grab.scene = load_scene(scene_dir)
    return grab


@requires_twins
def test_twin_drawers_keep_their_identity(tmp_path):
    """Twin drawers, one open and one shut at start and the other way round at end: each drawer's
    points in both states go to one part of their own, moved along the drawer's own slide (not
    open-with-open across the cabinet)."""
    from sparseart.bench.evaluate import true_groups
    from sparseart.datasets.meshes import load_articulated_object
    from sparseart.datasets.partnet import joint_range, render_articulated_scene

    obj = load_articulated_object(TWINS_DIR / "drawer_19179_multi")
    q_start, q_end = {}, {}
    for k, joint in enumerate(obj.model.movable_joints):
        low, high = joint_range(joint)
        opened, shut = low + 0.6 * (high - low), low + 0.02 * (high - low)
        q_start[joint.name], q_end[joint.name] = (opened, shut) if k % 2 == 0 else (shut, opened)
    gt = render_articulated_scene(obj, tmp_path / "swap", q_start, q_end, views=3, seed=0)
    grab = _labels(tmp_path / "swap")
    labels = grab.labels
    start_truth, end_truth = true_groups(grab.start, grab.scene, gt), true_groups(grab.end, grab.scene, gt)
    seen = set()
    for joint in gt["joints"]:
        in_start = labels.start_part[start_truth == joint["mask_id"]]
        in_end = labels.end_part[end_truth == joint["mask_id"]]
        part = int(np.bincount(in_start[in_start >= 0]).argmax())
        assert part > 0 and part not in seen
        seen.add(part)
        assert np.mean(in_start == part) > 0.9 and np.mean(in_end == part) > 0.8
        motion = labels.initial_motion[part]
        expected = np.asarray(joint["axis"]) * joint["distance"]
        assert np.linalg.norm(motion[:3, 3] - expected) < 0.05 * gt["scale"]
    assert labels.diagnostics["pairing"]["runner_up_cost"] - labels.diagnostics["pairing"]["cost"] > 0.1


def _render_laptop(scene_dir: Path, q_open: float, q_closed: float) -> dict:
    """A laptop seen from behind while open (the lid hides the base) and from above when closed."""
    from sparseart.datasets.meshes import load_articulated_object
    from sparseart.datasets.partnet import gt_joints, intrinsics, look_at
    from sparseart.datasets.raycast import PreparedScene, render_view
    from sparseart.datasets.scene_writer import RenderedView, write_scene

    obj = load_articulated_object(PARTNET_DIR / "laptop_rotate_10211")
    name = obj.model.movable_joints[0].name
    q_start, q_end = {name: q_open}, {name: q_closed}
    parts_start, parts_end = obj.posed_parts(q_start), obj.posed_parts(q_end)
    vertices = np.concatenate([m.vertices for m, _ in parts_start + parts_end])
    centre = 0.5 * (vertices.min(0) + vertices.max(0))
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    width, height = 320, 240
    K = intrinsics(width, height)
    distance = radius / math.sin(0.9 * math.atan(height / 2 / K[1, 1]))

    def eye(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
        az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
        return centre + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])

    behind = [look_at(eye(-25 + 25 * k, 15 + 5 * k), centre) for k in range(3)]      # the lid's back
    above = [look_at(eye(120 * k, 75 + 4 * k), centre) for k in range(3)]           # closed, from above
    start = [RenderedView(*render_view(PreparedScene(parts_start), K, c, width, height), K, c) for c in behind]
    end = [RenderedView(*render_view(PreparedScene(parts_end), K, c, width, height), K, c) for c in above]
    first = np.concatenate([m.vertices for m, _ in parts_start])
    gt = {"schema": "sparseart/gt/1", "object": obj.name, "frame": "world", "units": "object units",
          "scale": float(np.linalg.norm(first.max(0) - first.min(0))), "static_mask_id": 1,
          "joints": gt_joints(obj, q_start, q_end, parts_start), "joint_states": {"start": q_start, "end": q_end}}
    write_scene(scene_dir, start, end, gt, posed=True)
    return gt


@requires_laptop
@pytest.mark.parametrize("use_masks", [True, False])
def test_posed_laptop_from_behind_finds_the_lid(tmp_path, use_masks):
    """Lid turned 70 deg; its base is barely seen open (behind the lid) and hidden closed. The
    cameras give the world frame, so the lid's own motion is the answer (was: "no part moved")."""
    from sparseart.bench.evaluate import evaluate
    from sparseart.io.scene import load_scene
    from sparseart.pipeline import run

    gt = _render_laptop(tmp_path / "laptop", q_open=-1.83 + math.radians(70.0), q_closed=-1.83)
    scene = load_scene(tmp_path / "laptop")
    result = run(scene, use_masks=use_masks)
    assert not any("no part moved" in w for w in result.warnings)
    rows = evaluate(result, scene, gt)
    assert rows[0]["pred_type"] == "revolute"
    assert rows[0]["axis_deg"] < 5.0


@pytest.fixture(scope="module")
def unposed_fridge(tmp_path_factory) -> Path:
    from sparseart.datasets.partnet import render_partnet_scene

    scene_dir = tmp_path_factory.mktemp("twins") / "fridge"
    render_partnet_scene(TWINS_DIR / "refrigerator_11231_multi", scene_dir, views=3, seed=0, posed=False)
    return scene_dir


def _labels_json(labels) -> str:
    return json.dumps({"start": labels.start_part.tolist(), "end": labels.end_part.tolist(),
                       "motions": {str(k): np.asarray(v).tolist() for k, v in labels.initial_motion.items()},
                       "alternatives": {str(k): [np.asarray(a).tolist() for a in v]
                                        for k, v in labels.alternative_motions.items()},
                       "diagnostics": labels.diagnostics, "warnings": labels.warnings}, sort_keys=True, default=str)


@requires_twins
def test_labeler_is_deterministic_on_a_multi_part_scene(unposed_fridge):
    """The same clouds labelled twice (fresh labelers) give identical labels, motions and
    diagnostics (seeded sampling everywhere, no open3d feature RANSAC in the pair search)."""
    from sparseart.io.scene import load_scene
    from sparseart.labelers.rules import RuleBasedLabeler

    grab = _labels(unposed_fridge)
    scene = load_scene(unposed_fridge)
    runs = [_labels_json(RuleBasedLabeler().label(grab.start, grab.end, scene, aligned=True)) for _ in range(2)]
    assert runs[0] == runs[1]
    assert len(json.loads(runs[0])["motions"]) == 3


@requires_twins
def test_labels_are_the_same_with_threads_as_without(unposed_fridge, monkeypatch):
    """The labeler's independent registrations and motion ratings run side by side in threads
    (sparseart.parallel): with and without masks, 4 threads give the labels, motions and
    diagnostics of a sequential run."""
    import dataclasses

    import sparseart.parallel as parallel
    from sparseart.io.scene import load_scene
    from sparseart.labelers.rules import RuleBasedLabeler

    grab = _labels(unposed_fridge)
    scene = load_scene(unposed_fridge)
    maskless = [dataclasses.replace(cloud, segment=np.full_like(cloud.segment, -1)) for cloud in (grab.start, grab.end)]
    for start, end in ((grab.start, grab.end), maskless):
        runs = []
        for threads in (1, 4):
            monkeypatch.setattr(parallel, "PARALLEL_THREADS", threads)
            runs.append(_labels_json(RuleBasedLabeler().label(start, end, scene, aligned=True)))
        assert runs[0] == runs[1]


def _without_seconds(document):
    """The articulation document without its wall-clock times (every "seconds" key, any depth)."""
    if isinstance(document, dict):
        return {k: _without_seconds(v) for k, v in document.items() if k != "seconds"}
    if isinstance(document, list):
        return [_without_seconds(v) for v in document]
    return document


@requires_twins
def test_same_multi_part_scene_gives_the_same_json(unposed_fridge):
    """Determinism: an unposed multi-part scene run twice gives byte-identical articulation JSON
    (apart from the stage times). Registration of the unposed views runs open3d on one thread
    (sparseart.geometry.o3d.serial): its threaded ICP sums differed in the last bits from run to run."""
    from sparseart.io.articulation import articulation_to_dict
    from sparseart.io.scene import load_scene
    from sparseart.pipeline import run

    outputs = [json.dumps(_without_seconds(articulation_to_dict(run(load_scene(unposed_fridge)))), sort_keys=True)
               for _ in range(2)]
    assert outputs[0] == outputs[1]
    assert len(json.loads(outputs[0])["joints"]) == 2


def test_a_small_turn_about_a_far_pivot_is_charged_as_a_slide():
    """A 6.9 deg turn whose pivot lies ~7 part radii away carries a drawer a drawer width sideways
    (measured: twin drawers side by side paired that way without masks): it counts as a slide,
    along the drawer's displacement, so the slot charge sees it; a door's turn of the same angle
    about its own edge, and larger turns, are no slides."""
    from scipy.spatial.transform import Rotation

    from sparseart.labelers.correspondence import slide_direction

    rng = np.random.default_rng(0)
    drawer = rng.uniform([-0.1, -0.05, -0.05], [0.1, 0.05, 0.05], (500, 3))   # radius ~0.07

    def turn(degrees: float, pivot: np.ndarray) -> np.ndarray:
        transform = np.eye(4)
        transform[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 1.0, 0.0])).as_matrix()
        transform[:3, 3] = pivot - transform[:3, :3] @ pivot
        return transform

    far = turn(6.9, np.array([1.3, 0.0, 0.0]))
    direction = slide_direction(far, drawer)
    moved = far[:3, :3] @ drawer.mean(axis=0) + far[:3, 3] - drawer.mean(axis=0)
    np.testing.assert_allclose(direction, moved / np.linalg.norm(moved), atol=1e-12)
    assert slide_direction(turn(6.9, np.array([0.1, 0.0, 0.05])), drawer) is None   # a door on its edge
    assert slide_direction(turn(20.0, np.array([1.3, 0.0, 0.0])), drawer) is None   # a real turn
    shift = np.eye(4)
    shift[:3, 3] = [0.0, 0.0, 0.2]
    np.testing.assert_allclose(slide_direction(shift, drawer), [0.0, 0.0, 1.0])


@requires_twins
def test_four_drawers_side_by_side_without_masks(tmp_path):
    """Four look-alike drawers side by side, all pulled out by different lengths (0.11-0.25 object
    units), no masks: touching drawers come as one moved piece whose registration blends their
    slides, and two of them differ in travel by about one inlier radius. Each drawer must still be
    its own part sliding along its own slot (before: 1 of 4 within 10 deg)."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "drawers"
    gt = render_partnet_scene(TWINS_DIR / "drawer_32761_multi", scene_dir, views=3, seed=0, posed=True)
    result = sparseart.run(scene_dir, use_masks=False)
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert len(rows) == 4
    for row in rows:
        assert row["type_correct"] and row["axis_deg"] < 10.0, row
    assert len({row["part"] for row in rows}) == 4


def test_a_step_along_a_neighbouring_surface_is_not_blocked():
    """Physics of the pair cost and the motion layers: a sash sliding past its neighbour at a gap
    under the inlier radius meets that surface at every step but runs along it, not into it (before:
    a sliding window's true motion was charged as 96 % blocked and could never be chosen without
    masks); the same sash pushed sideways into its neighbour is blocked."""
    from scipy.spatial import cKDTree

    from sparseart.geometry.sweep import blocked_step_share

    rng = np.random.default_rng(0)
    radius = 0.02
    sash = np.column_stack([rng.uniform(0.0, 0.5, 3000), rng.uniform(0.0, 0.5, 3000), np.zeros(3000)])
    neighbour = np.column_stack([rng.uniform(0.45, 1.0, 3000), rng.uniform(0.0, 0.5, 3000),
                                 np.full(3000, 0.5 * radius)])
    tree = cKDTree(neighbour)

    def near(points: np.ndarray) -> np.ndarray:
        return tree.query(points, k=1, distance_upper_bound=radius)[0] < radius

    along, into = np.eye(4), np.eye(4)
    along[:3, 3] = [0.4, 0.0, 0.0]      # slides in its own plane over the neighbour
    into[:3, 3] = [0.0, 0.0, 0.4]       # pushed through the neighbour's plane
    neighbour_wide = np.column_stack([rng.uniform(0.0, 1.0, 6000), rng.uniform(0.0, 0.5, 6000), np.full(6000, 0.06)])   # the first step (15 %) lands on it
    wide = cKDTree(neighbour_wide)

    def near_wide(points: np.ndarray) -> np.ndarray:
        return wide.query(points, k=1, distance_upper_bound=radius)[0] < radius

    assert blocked_step_share(along, 1.0, sash, radius, near) > 0.2            # without normals: "blocked"
    assert blocked_step_share(along, 1.0, sash, radius, near, surface=tree) == 0.0
    assert blocked_step_share(into, 1.0, sash, radius, near_wide, surface=wide) > 0.5


@pytest.mark.skipif(not (PARTNET_DIR / "window_push_102801").is_dir(),
                    reason=f"window_push_102801 not found in {PARTNET_DIR}")
def test_sliding_window_without_masks_unposed(tmp_path):
    """A sash that slides in its own plane past the fixed one (unposed, 3 views, no masks). Its
    steps meet the fixed sash all along the way; counted as blocked, its true slide could not win
    the motion layers and the run reported a slide 44 deg off (before the along/into test)."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "window"
    gt = render_partnet_scene(PARTNET_DIR / "window_push_102801", scene_dir, views=3, seed=0, posed=False)
    rows = evaluate(sparseart.run(scene_dir, use_masks=False), load_scene(scene_dir), gt)
    assert len(rows) == 1 and rows[0]["type_correct"] and rows[0]["axis_deg"] < 10.0, rows


@pytest.mark.skipif(not (PARTNET_DIR / "drawer_31249").is_dir(), reason=f"drawer_31249 not found in {PARTNET_DIR}")
def test_drawer_slides_along_the_body_axis_without_masks(tmp_path):
    """A table's drawer without masks (posed, 3 views): its moved pieces register to a slide
    tilted 8 deg off its slot; the slides along the body's own axes, voted by the moved points,
    give the true one (before: 8.3 deg)."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "drawer"
    gt = render_partnet_scene(PARTNET_DIR / "drawer_31249", scene_dir, views=3, seed=0, posed=True)
    rows = evaluate(sparseart.run(scene_dir, use_masks=False), load_scene(scene_dir), gt)
    assert len(rows) == 1 and rows[0]["type_correct"] and rows[0]["axis_deg"] < 2.0, rows


@pytest.mark.skipif(not (PARTNET_DIR / "drawer_31249").is_dir(), reason=f"drawer_31249 not found in {PARTNET_DIR}")
def test_a_drawer_front_read_loosely_holds_the_slide_where_the_data_cannot_tell(tmp_path):
    """The table's drawer on the realistic bench render (seed 3: warped, noisy depth, ragged masks,
    an arm on it): the free slide tilts within the front (15 deg off; 5.5 from the static body's
    axis); the slide along the front's normal fits about as well and is held (2.0 deg). Its front's normals read 3.9 deg apart
    since a split piece of its mask rejoins it (mask_repair.split_mask_ids); with the piece apart
    they read 5.8 deg apart and the loose-face rule held them (10.2 -> 2.5 deg; the rule's own
    cases are in test_candidates)."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.bench.grid import grid_settings
    from sparseart.bench.objects import render_cached
    from sparseart.io.scene import load_scene

    setting = next(s for s in grid_settings(3)[0] if s.name == "realistic")
    scene_dir = tmp_path / "drawer"
    gt, _ = render_cached(PARTNET_DIR / "drawer_31249", scene_dir, setting)
    result = sparseart.run(scene_dir, seed=3)
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert len(rows) == 1 and rows[0]["type_correct"] and rows[0]["axis_deg"] < 5.0, rows
    joint = next(joint for _, joint in result.joints)
    assert any("slide taken along the part's face normal" in w for w in joint.warnings)
    assert joint.diagnostics["free_slide"]["face_states_deg"] < 10.0


def _robot_run(tmp_path, name: str, setting_name: str, seed: int = 0):
    """Render PartNet object ``name`` under bench setting ``setting_name`` (one posed view per
    state, realism knobs; render and run ``seed`` as the bench's) and run it without masks:
    (result, scene, gt, evaluated rows)."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.bench.grid import grid_settings
    from sparseart.bench.objects import render_cached
    from sparseart.io.scene import load_scene

    setting = next(s for s in grid_settings(seed)[0] if s.name == setting_name)
    scene_dir = tmp_path / name
    gt, _ = render_cached(PARTNET_DIR / name, scene_dir, setting)
    result = sparseart.run(scene_dir, use_masks=False, seed=seed)
    scene = load_scene(scene_dir)
    return result, scene, gt, evaluate(result, scene, gt)


@pytest.mark.skipif(not (PARTNET_DIR / "toaster_press_103486").is_dir(),
                    reason=f"toaster_press_103486 not found in {PARTNET_DIR}")
def test_a_lever_slid_far_down_its_slot_is_a_slide_without_masks(tmp_path):
    """A clean posed render (3 views, seed 1), no masks: the toaster's lever slides 0.39 down its
    slot, about 7 radii of its own visible points. That slide was ruled "detached" (no joint
    carries a part that far) and the lever came out as two turns onto the patches it hides in
    each state: 72 deg off at confidence 0.9. It lays seen points onto seen points in both states
    (labelers.motion_ratings.seen_both_ways), so it is the lever seen at both poses."""
    rows = _robot_run(tmp_path, "toaster_press_103486", "no-masks", seed=1)[3]
    assert len(rows) == 1 and rows[0]["pred_type"] == "prismatic" and rows[0]["axis_deg"] < 5.0, rows


@pytest.mark.skipif(not (PARTNET_DIR / "refrigerator_11231").is_dir(),
                    reason=f"refrigerator_11231 not found in {PARTNET_DIR}")
def test_a_hand_in_one_state_does_not_join_the_door_without_masks(tmp_path):
    """The robot shape (one posed view per state, no masks, every realism knob): an arm reaches
    over the fridge door in the end state only. Carried back by the door's turn it lands behind
    the cabinet, hidden, like the door's own sides; it touches none of the door's hits. It joined
    the door (5.8k arm points against 1.3k door points), the fit's cleaning then kept the arm
    and dropped the door, and the joint came out a slide 62 deg off."""
    from sparseart.bench.evaluate import true_groups

    result, scene, gt, rows = _robot_run(tmp_path, "refrigerator_11231", "robot-1view")
    assert len(rows) == 1 and rows[0]["type_correct"] and rows[0]["axis_deg"] < 10.0, rows
    groups = true_groups(result.end_cloud, scene, gt)
    part = result.labels.end_part == rows[0]["part"]
    door = gt["joints"][0]["mask_id"]
    assert np.count_nonzero(part & (groups == 0)) < 0.2 * np.count_nonzero(part & (groups == door))


def test_slide_votes_count_exactly_what_a_query_per_length_counts():
    """The slide vote (one 2-D tube query per point instead of one 3-D query per point and length)
    gives the same count at every length as landing each slid point on its nearest target."""
    from scipy.spatial import cKDTree
    from sparseart.labelers.motion_candidates import slide_votes

    rng = np.random.default_rng(0)
    for _ in range(10):
        points, targets = rng.normal(size=(300, 3)), rng.normal(size=(500, 3)) * rng.uniform(0.5, 2.0)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        radius = rng.uniform(0.05, 0.3)
        steps = np.arange(2.0 * radius, 3.0, 0.5 * radius)
        lengths = np.concatenate([-steps[::-1], steps])
        tree = cKDTree(targets)
        brute = [(tree.query(points + d * direction, distance_upper_bound=radius)[0] < radius).sum() for d in lengths]
        assert np.array_equal(slide_votes(points, tree, direction, lengths, radius), brute)


@requires_laptop
def test_a_lid_without_masks_is_one_part(tmp_path):
    """A flat lid slid within its own plane still lands on itself: without masks (posed, 3 views)
    the motion layers chose two motions with the same 53 deg turn and translations 0.35 apart,
    each claiming half of the lid, and the run reported two lids. They differ only by a shift in
    the lid's plane, so they are one part."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "laptop"
    gt = render_partnet_scene(PARTNET_DIR / "laptop_rotate_10211", scene_dir, views=3, seed=0, posed=True)
    result = sparseart.run(scene_dir, use_masks=False)
    assert len(result.joints) == 1, [joint.type for _, joint in result.joints]
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert rows[0]["type_correct"] and rows[0]["axis_deg"] < 2.0, rows


@pytest.mark.skipif(not (PARTNET_DIR / "box_rotate_100221").is_dir(),
                    reason=f"box_rotate_100221 not found in {PARTNET_DIR}")
def test_a_lid_turned_far_is_found_from_its_planes_without_masks(tmp_path):
    """The robot shape with sensor depth (one posed view per state, no masks): a box lid turned
    by 75 deg towards the camera, seen from above closed and face-on open, with an arm on it.
    Registration from identity or from the moved pieces' shapes offered only turns of 0.5-16
    deg, and the lid came out as two slides 88 deg off; the turn about the line where its start
    and end planes meet is its hinge (labelers.motion_candidates.plane_hinges)."""
    rows = _robot_run(tmp_path, "box_rotate_100221", "robot-sensor-1view")[3]
    assert len(rows) == 1 and rows[0]["pred_type"] == "revolute" and rows[0]["axis_deg"] < 5.0, rows


def test_a_turn_no_hinge_on_the_static_body_makes_is_detached():
    """A lid's turn about an edge of the static box is a hinge; the same turn screwed along its
    axis, or about a line far from every static point, is not (an arm carried onto an occluded
    patch); a small tilt is judged as a slide, and a slide far beyond the part's own size is no
    joint's."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation
    from sparseart.geometry.transforms import make_transform
    from sparseart.labelers.motion_ratings import detached

    rng = np.random.default_rng(0)
    for scale in (1.0, 1000.0):
        body = scale * rng.uniform([-0.3, -0.3, -0.6], [0.3, 0.3, 0.0], size=(5000, 3))
        lid = scale * rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.02], size=(2000, 3))
        tree = cKDTree(body)

        def turn(deg: float, pivot, shift=0.0) -> np.ndarray:
            rotation = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 1.0, 0.0])).as_matrix()
            pivot = scale * np.asarray(pivot, dtype=float)
            return make_transform(rotation, pivot - rotation @ pivot + scale * np.array([0.0, shift, 0.0]))

        assert not detached(turn(70.0, [0.3, 0.0, 0.0]), lid, tree)             # hinge on the back edge
        assert detached(turn(70.0, [0.3, 0.0, 0.0], shift=0.4), lid, tree)      # screwed along its axis
        assert detached(turn(70.0, [1.5, 0.0, 1.0]), lid, tree)                 # about a line in the air
        assert not detached(turn(5.0, [1.5, 0.0, 1.0]), lid, tree)              # a tilt: judged as a slide
        # slides: the lid radius is 0.25; pulled out 0.4 (1.6 radii) it is a drawer's slide, carried
        # 2 (8 radii) away it is no slide a joint makes
        assert not detached(make_transform(np.eye(3), scale * np.array([0.4, 0.0, 0.0])), lid, tree)
        assert detached(make_transform(np.eye(3), scale * np.array([2.0, 0.0, 0.0])), lid, tree)
        # ... unless the slide lays seen points onto seen points in both states alike (the part
        # seen at both poses: a small lever down a long slot); turns are judged as before
        far = make_transform(np.eye(3), scale * np.array([2.0, 0.0, 0.0]))
        assert not detached(far, lid, tree, seen_both=True)
        assert detached(turn(70.0, [1.5, 0.0, 1.0]), lid, tree, seen_both=True)


def test_seen_both_ways_needs_hits_in_both_states_alike():
    from sparseart.labelers.motion_ratings import seen_both_ways

    assert seen_both_ways(464, 426)          # a toaster lever slid down its slot, seen at both poses
    assert not seen_both_ways(514, 3)        # an arm or a protrusion laid onto the patch it hides
    assert not seen_both_ways(300, 100)      # one way far more than the other
    assert not seen_both_ways(8, 8)          # too few to tell


@pytest.mark.skipif(not (PARTNET_DIR / "oven_7201").is_dir(), reason=f"oven_7201 not found in {PARTNET_DIR}")
def test_an_oven_door_beats_a_turn_no_hinge_makes_without_masks(tmp_path):
    """The robot shape with sensor depth (one posed view per state, no masks): an oven door
    pulled down with an arm on it. A 144 deg turn that also shifts 0.65 part radii along its own
    axis (no hinge does) out-voted the door's turn (shift 0.00, axis 0.07 radii from the oven)
    and the joint came out 42 deg off; a turn must be a hinge on the static body
    (labelers.motion_ratings.detached)."""
    rows = _robot_run(tmp_path, "oven_7201", "robot-sensor-1view")[3]
    assert len(rows) == 1 and rows[0]["pred_type"] == "revolute" and rows[0]["axis_deg"] < 10.0, rows


@pytest.mark.skipif(not (PARTNET_DIR / "drawer_26525").is_dir(), reason=f"drawer_26525 not found in {PARTNET_DIR}")
def test_a_drawer_beats_a_slide_far_beyond_its_size_without_masks(tmp_path):
    """The robot shape with reconstructor depth (one posed view per state, no masks): a nightstand
    drawer pulled out with an arm on it. A slide carrying a patch 11.3 of its radii (no drawer
    travels that far) won on hidden credit over the drawer's slide of 0.6 radii, whose layer then
    fell below the part floor: no part was found (labelers.motion_ratings.detached)."""
    rows = _robot_run(tmp_path, "drawer_26525", "robot-1view")[3]
    assert len(rows) == 1 and rows[0]["pred_type"] == "prismatic" and rows[0]["axis_deg"] < 10.0, rows


@pytest.mark.skipif(not (PARTNET_DIR / "washing_machine_103508").is_dir(),
                    reason=f"washing_machine_103508 not found in {PARTNET_DIR}")
def test_a_lid_in_a_room_is_judged_by_its_own_size_without_masks(tmp_path):
    """The robot shape with sensor depth (one posed view per state, no masks): a washing
    machine's lid raised with an arm on it, the machine on a table in a room. The part floor was
    1 % of the whole cloud (543 points, most of them walls and floor), more than the lid's raised
    plane holds, so its hinge was never proposed and a 37 deg wrong turn came out; the floor now
    follows the moved points (labelers.rules._layers_without_masks)."""
    rows = _robot_run(tmp_path, "washing_machine_103508", "robot-sensor-1view")[3]
    assert len(rows) == 1 and rows[0]["pred_type"] == "revolute" and rows[0]["axis_deg"] < 10.0, rows


@pytest.mark.skipif(not (PARTNET_DIR / "microwave_7128").is_dir(), reason=f"microwave_7128 not found in {PARTNET_DIR}")
def test_a_hand_of_another_colour_does_not_join_the_door_without_masks(tmp_path):
    """The robot shape with sensor depth (one posed view per state, no masks): a microwave door
    opened with an arm on it in the end state. Carried back by the door's turn, the hand and the
    sleeve land on the patch of the cabinet they hide, hits by position alone; 548 arm points
    joined the door's layer and the hinge came out 11.9 deg off. A hit must keep the colour
    (labelers.motion_ratings.off_colour) for a point to join a part: 59 arm points are left, the
    hinge is 0.4 deg off."""
    from sparseart.bench.evaluate import true_groups

    result, scene, gt, rows = _robot_run(tmp_path, "microwave_7128", "robot-sensor-1view")
    assert len(rows) == 1 and rows[0]["pred_type"] == "revolute" and rows[0]["axis_deg"] < 3.0, rows
    groups = true_groups(result.end_cloud, scene, gt)
    part = result.labels.end_part == rows[0]["part"]
    door = gt["joints"][0]["mask_id"]
    assert np.count_nonzero(part & (groups == 0)) < 0.05 * np.count_nonzero(part & (groups == door))


def test_colour_offset_between_states_is_taken_out_of_the_hit_test():
    """A hit compares the colour of its two points after the states' global colour offset (a
    white balance change between the captures): the same red part under a bluish end image
    still hits, a grey wall patch does not; a part darkened by shading (a*b* moves, the
    chromaticity does not) still hits."""
    from types import SimpleNamespace

    from scipy.spatial import cKDTree

    from sparseart.labelers.colour import chroma
    from sparseart.labelers.motion_ratings import moved_chroma, off_colour

    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(0, 1, (400, 2)), np.zeros(400)]
    part = np.c_[rng.uniform(0, 0.3, (200, 2)), np.full(200, 0.5)]
    red = np.tile([0.8, 0.2, 0.2], (200, 1))
    start = SimpleNamespace(points=np.r_[wall, part], colors=np.r_[np.full((400, 3), 0.5), red])
    tint = np.array([-0.05, 0.0, 0.08])       # the end image's white balance
    grey_patch = np.full((50, 3), 0.5) + tint
    end = SimpleNamespace(points=np.r_[wall, part, part[:50] + [0, 0, -0.5]],
                          colors=np.r_[start.colors + tint, grey_patch])
    start_moved, end_moved = np.arange(400, 600), np.arange(400, 650)
    start_chroma, end_chroma = moved_chroma(start, end, start_moved, end_moved, cKDTree(end.points))
    assert off_colour(chroma(red[:50]), chroma(red[:50] + tint)).all()          # a miss without the offset
    assert not off_colour(start_chroma[:50], end_chroma[:50]).any()              # a hit with it
    assert off_colour(start_chroma[:50], end_chroma[200:250]).all()              # the wall is another colour
    assert not off_colour(chroma(red[:50]), chroma(0.4 * red[:50])).any()        # shade is no colour


def test_a_motion_that_only_lands_hidden_is_not_selected():
    """The selection's pool: a motion earns its price from hits. One that lands 2000 points
    hidden (credit 0.5 each, worth 1000 > the price) with no hit is not chosen; one with more
    hits than the price is, and a detached turn is not, whatever its hits."""
    from types import SimpleNamespace

    from sparseart.labelers.motion_layers import _select
    from sparseart.labelers.motion_ratings import HIDDEN_CREDIT

    points = 3000
    hidden_only = np.zeros(points)
    hidden_only[:2000] = HIDDEN_CREDIT
    hits = np.zeros(points)
    hits[2000:2800] = 1.0

    def ratings(rows, detached):
        return SimpleNamespace(rows=rows, unseen=np.zeros(points, dtype=bool), physics=[0.0] * len(rows),
                               slides=[0.0] * len(rows), motions=[np.eye(4)] * len(rows), detached=detached)

    assert _select(ratings([hidden_only, hits], [False, False]), price=600.0) == [1]
    assert _select(ratings([hidden_only], [False]), price=600.0) == []
    assert _select(ratings([hits], [True]), price=600.0) == []


def test_points_a_dropped_layer_took_by_a_tie_go_back_to_the_part():
    """Layers below the floor are no parts: their motion leaves the chosen set and its points
    are assigned again. A patch both motions explain went to the small motion (its own hits lie
    nearer) and was lost with it; it now stays with the part whose motion explains it."""
    from types import SimpleNamespace

    from sparseart.labelers.motion_layers import _layers_over_floor

    rng = np.random.default_rng(0)
    part = rng.uniform(0.0, 1.0, size=(1000, 3))                 # explained by motion 0 only
    patch = rng.uniform(0.0, 0.2, size=(100, 3)) + [10.0, 0, 0]   # explained by both
    other = rng.uniform(0.0, 0.2, size=(50, 3)) + [10.5, 0, 0]    # explained by motion 1 only
    points = np.concatenate([part, patch, other])
    n = len(points)
    moved = np.arange(n)
    row_part = np.concatenate([np.ones(1100), np.zeros(50)])
    row_small = np.concatenate([np.zeros(1000), np.ones(150)])
    rows = [np.concatenate([row_part, row_part]), np.concatenate([row_small, row_small])]
    cloud = SimpleNamespace(points=points)
    ratings = SimpleNamespace(start=cloud, end=cloud, start_moved=moved, end_moved=moved, rows=rows,
                              coloured_row=lambda k: rows[k],       # every hit keeps its colour
                              motions=[np.eye(4), np.eye(4).copy()], physics=[0.0, 0.0], slides=[0.0, 0.0],
                              context=SimpleNamespace(radius=0.3))
    layers, dropped = _layers_over_floor(ratings, [0, 1], floor_start=300, floor_end=300)
    assert len(layers) == 1 and len(layers[0].start) == 1100 and len(layers[0].end) == 1100
    assert dropped == {1}


def _turn(degrees: float, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis)).as_matrix()
    return transform


def test_a_layer_landing_only_on_unseen_points_joins_the_part_it_touches():
    """A lid's strip under a closing hand, carried by a 70 deg turn onto the table the lid revealed
    (points the start view never saw), is a blind layer: it joins the touching 96 deg layer whose
    hits land on seen points, with its seen points only. Layers that both see, or that turn about
    other axes, stay apart."""
    from types import SimpleNamespace

    from sparseart.labelers.motion_layers import MotionLayer, _blind_piece, _merge_agreeing

    rng = np.random.default_rng(0)
    lid = rng.uniform(0.0, 1.0, size=(300, 3))
    strip = rng.uniform(0.0, 0.2, size=(100, 3)) + [1.05, 0.0, 0.0]    # touches the lid
    revealed = rng.uniform(0.0, 0.2, size=(80, 3)) + [1.05, 1.5, 0.0]  # end points, unseen at start
    points = np.concatenate([lid, strip, revealed])
    n = len(points)
    moved = np.arange(n)
    unseen_end = np.zeros(n, dtype=bool)
    unseen_end[400:] = True
    unseen = np.concatenate([np.zeros(n, dtype=bool), unseen_end])
    lid_row = np.zeros(2 * n)
    lid_row[:300] = lid_row[n:n + 300] = 1.0
    strip_row = np.zeros(2 * n)
    strip_row[300:400] = 1.0            # the strip's start points land on the revealed table ...
    strip_row[n + 400:] = 1.0           # ... whose unseen end points land back on the strip
    strip_blind = np.zeros(2 * n, dtype=bool)
    strip_blind[300:400] = True
    rows = [lid_row, strip_row]
    cloud = SimpleNamespace(points=points)
    ratings = SimpleNamespace(start=cloud, end=cloud, start_moved=moved, end_moved=moved, rows=rows,
                              coloured_row=lambda k: rows[k], blind=[np.zeros(2 * n, dtype=bool), strip_blind],
                              unseen=unseen, start_unseen=unseen[:n], end_unseen=unseen[n:],
                              motions=[_turn(96.0), _turn(70.0, axis=(0.0, 0.1, 0.995))],
                              physics=[0.0, 0.0], slides=[0.0, 0.0], context=SimpleNamespace(radius=0.3))
    ratings.radius = 0.3
    lid_layer = MotionLayer(ratings.motions[0], 0.0, np.arange(300), np.arange(300))
    strip_layer = MotionLayer(ratings.motions[1], 0.0, np.arange(300, 400), np.arange(400, n))
    assert _blind_piece(ratings, lid_layer, strip_layer) is strip_layer
    (merged,) = _merge_agreeing(ratings, [lid_layer, strip_layer])
    assert merged.transform is ratings.motions[0]
    assert len(merged.start) == 400 and len(merged.end) == 300      # the revealed table stays out
    # both layers land on seen points: no blind piece
    ratings.blind = [np.zeros(2 * n, dtype=bool)] * 2
    assert _blind_piece(ratings, lid_layer, strip_layer) is None
    # a blind layer turning about another axis (a second door) is not a piece of the lid
    ratings.blind = [np.zeros(2 * n, dtype=bool), strip_blind]
    ratings.motions[1] = _turn(70.0, axis=(1.0, 0.0, 0.0))
    strip_layer = MotionLayer(ratings.motions[1], 0.0, np.arange(300, 400), np.arange(400, n))
    assert _blind_piece(ratings, lid_layer, strip_layer) is None


def test_an_ambiguous_pairing_lowers_the_joint_confidence():
    # The labeler's per-part trust in its pairing (look-alike parts that could pair the other way
    # round get margin / 0.08, at least 0.3, with a warning saying "confidence lowered") reaches
    # the joint: it used to stay on the labels, and an ambiguous twin reported 0.8.
    from synthetic import make_clouds

    from sparseart.joints.candidates import fit_parts
    from sparseart.types import PartLabels, PartSpec

    # the panel opens away from the body: turned +40 deg it would swing into the body, which the
    # turn check (joints/sweep_check.py) says and trusts half as much (tests/test_sweep_check.py)
    start, end, _ = make_clouds("revolute", np.radians(-40))
    parts = [PartSpec(id=0, role="static"), PartSpec(id=1, role="movable")]

    def fitted(confidence: dict[int, float]):
        labels = PartLabels(parts=parts, start_part=np.where(start.segment == 2, 1, 0),
                            end_part=np.where(end.segment == 2, 1, 0), confidence=confidence)
        return fit_parts(start, end, labels, warnings=[])[1].joint

    sure, ambiguous = fitted({}), fitted({1: 0.4})
    assert sure.confidence > 0.5 and "pairing_confidence" not in sure.diagnostics
    assert ambiguous.confidence == pytest.approx(0.4 * sure.confidence)
    assert ambiguous.diagnostics["pairing_confidence"] == 0.4


@pytest.mark.skipif(not (PARTNET_DIR / "storage_40147").is_dir(), reason=f"storage_40147 not found in {PARTNET_DIR}")
def test_a_drawer_shadowed_by_a_dropped_motion_is_selected_again_without_masks(tmp_path):
    """The robot shape (one posed view per state, no masks, every realism knob), seed 3: a
    storage unit's door and drawer. A 69 deg turn with door and background hits was selected
    beside the door's turn, which also lands part of the closed drawer; the drawer's slide lost
    its gain and stayed out, then the 69 deg layer was too small and was dropped: only the door
    was found. Selected again without the dropped motion, the drawer is a part
    (motion_layers._layers_with_reselection)."""
    rows = _robot_run(tmp_path, "storage_40147", "robot-1view", seed=3)[3]
    by_type = {row["gt_type"]: row for row in rows}
    assert not by_type["prismatic"]["unmatched"] and by_type["prismatic"]["axis_deg"] < 5.0, rows
    assert not by_type["revolute"]["unmatched"] and by_type["revolute"]["axis_deg"] < 10.0, rows


@requires_twins
def test_a_textureless_cabinet_unposed_is_registered_through_its_mask_ids(tmp_path):
    """A black, nearly cubic cabinet with two drawers, unposed, 3 views per state, masks given. SIFT
    finds 3-5 matches, and every geometric fit of the bare geometry lays the box a quarter turn
    round (walls onto walls, nothing seen through). The mask ids settle it: the turned fit lays the
    drawer fronts onto a side wall. Before, three views stayed unregistered, the states were aligned
    through the turned-around carcass, and both drawers came out as turns 90 deg off."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "cabinet"
    gt = render_partnet_scene(TWINS_DIR / "drawer_19179_multi", scene_dir, views=3, seed=0, posed=False)
    result = sparseart.run(scene_dir)
    assert not any("could not be registered" in w for w in result.warnings), result.warnings
    assert any("its mask ids agreeing" in w for w in result.warnings), result.warnings
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert len(rows) == 2
    for row in rows:
        assert not row["unmatched"] and row["type_correct"] and row["axis_deg"] < 10.0, rows


def test_mask_ids_tell_a_quarter_turned_box_from_the_true_pose():
    """Two views' points of a cube-like body with a drawer front on one face: a quarter turn about
    the vertical lays the body onto itself, but the drawer's id onto the body's."""
    from scipy.spatial.transform import Rotation

    from sparseart.align.geometric import IdAgreement
    from sparseart.geometry.transforms import make_transform

    rng = np.random.default_rng(0)
    walls = []
    for axis in (0, 2):                       # the four side walls of a unit box (y up)
        for side in (-0.5, 0.5):
            wall = rng.uniform(-0.5, 0.5, (800, 3))
            wall[:, axis] = side
            walls.append(wall)
    points = np.concatenate(walls)
    ids = np.full(len(points), 1)
    ids[(points[:, 2] == -0.5) & (np.abs(points[:, 0]) < 0.4) & (np.abs(points[:, 1]) < 0.4)] = 2  # the front
    agreement = IdAgreement(points, ids, points, ids, 0.05, seed=0)
    assert agreement.usable
    assert agreement(np.eye(4)) == 1.0
    quarter = make_transform(Rotation.from_euler("y", 90, degrees=True).as_matrix(), np.zeros(3))
    assert agreement(quarter) < 0.6
    scrambled = IdAgreement(points, ids, points, np.where(ids == 1, 2, 1), 0.05, seed=0)
    assert scrambled(np.eye(4)) < 0.2       # ids that do not name the same parts do not vouch


def test_a_run_without_masks_hands_no_mask_to_any_stage(tmp_path):
    """use_masks=False: the stages see a scene without the folder's masks (before, the registration's
    free-space checks still read the object's outline from them, and the labeler got them too)."""
    from sparseart.datasets.synth import render_synth_scene
    from sparseart.io.scene import load_scene
    from sparseart.labelers.rules import RuleBasedLabeler
    from sparseart.pipeline import run

    class Spy(RuleBasedLabeler):
        def label(self, start, end, scene=None, **kwargs):
            self.masks = [f.mask for f in scene.all_frames]
            return super().label(start, end, scene, **kwargs)

    render_synth_scene(tmp_path / "cabinet", views=2, seed=0, posed=False, width=160, height=120)
    scene = load_scene(tmp_path / "cabinet")
    spy = Spy()
    run(scene, labeler=spy, use_masks=False)
    assert spy.masks and all(mask is None for mask in spy.masks)
    assert all(f.mask is not None for f in scene.all_frames)     # the caller's scene is left as it was


def test_without_masks_only_a_swap_of_parts_is_an_ambiguous_pairing():
    """Without masks a runner-up pairing that gives a part an end piece nothing else took (the real
    laptop's lid paired with the arm that closed it) does not lower the part's confidence: the
    motion layers weigh that motion over every moved point. A runner-up that swaps two parts does,
    with masks or without."""
    from types import SimpleNamespace

    from sparseart.labelers.rules import _pairing_diagnostics

    candidates = {(i, j): SimpleNamespace(i=i, j=j, score=0.5, physics=0.0, slide=0.0, mask=0.0, transform=np.eye(4))
                  for i in range(3) for j in range(3)}
    other_piece = SimpleNamespace(cost=-1.18, pairs=[(0, 0), (1, 1)], runner_up=[(0, 0), (1, 2)],
                                  runner_up_cost=-1.15, margin=0.03)
    swap = SimpleNamespace(cost=-1.5, pairs=[(0, 0), (1, 1), (2, 2)], runner_up=[(0, 0), (1, 2), (2, 1)],
                           runner_up_cost=-1.47, margin=0.03)
    parts = {(0, 0): 0, (1, 1): 1, (2, 2): 2}
    for assignment, swaps_only, lowered in ((other_piece, True, False), (other_piece, False, True),
                                            (swap, True, True), (swap, False, True)):
        warnings: list[str] = []
        result = _pairing_diagnostics(assignment, candidates, parts, warnings, 0.01, swaps_only=swaps_only)
        assert (result["confidence"][1] < 1.0) == lowered, (assignment.pairs, swaps_only, result["confidence"])
        assert any("ambiguous pairing" in w for w in warnings) == lowered
        assert result["pairing"]["runner_up"]          # the runner-up is kept in the diagnostics either way


@pytest.mark.skipif(not (PARTNET_DIR / "oven_7179_multi").is_dir(),
                    reason=f"oven_7179_multi not found in {PARTNET_DIR}")
def test_an_ovens_wire_racks_are_found_without_masks(tmp_path):
    """A clean posed render (3 views per state, seed 0), no masks: two oven doors open and three
    wire racks slide out 0.16-0.35. Each rack holds 2-4 % of the moved points (under the motion
    layers' part price) and a rack slid along its own wires reads as static point by point, so
    the racks were not found. Sought among the points no door explains
    (labelers.small_slides), each rack is one part with its own slide and nothing else is."""
    result, _, gt, rows = _robot_run(tmp_path, "oven_7179_multi", "no-masks")
    assert len(rows) == len(gt["joints"]) == 5
    assert all(row["type_correct"] and row["axis_deg"] < 5.0 for row in rows), rows
    racks = [row for row in rows if row["gt_type"] == "prismatic"]
    assert all(abs(row["state_along"]) < 0.1 * row["gt_state"] for row in racks), racks
    assert sum(part.role == "movable" for part in result.labels.parts) == 5
