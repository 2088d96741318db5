"""Tests of the realism knobs of the renderer (sparseart.datasets.realism). Fast: small renders of
the procedural cabinet (no shared data needed), a few seconds in total."""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("open3d")

from sparseart.datasets import realism as rz
from sparseart.datasets.partnet import render_articulated_scene
from sparseart.datasets.raycast import PreparedScene, render_view
from sparseart.datasets.realism import CLEAN, PRESETS, Realism
from sparseart.datasets.scene_writer import RenderedView, write_scene
from sparseart.datasets.synth import build_cabinet

W, H = 160, 120
Q0 = {"door_hinge": 0.0, "drawer_slide": 0.0}
Q1 = {"door_hinge": 0.9, "drawer_slide": 0.2}


def _render(root: Path, realism: Realism | None = None, seed: int = 0, views: int = 2, **kwargs) -> dict:
    extra = {} if realism is None else {"realism": realism}
    return render_articulated_scene(build_cabinet(0), root, Q0, Q1, views=views, seed=seed, width=W, height=H,
                                    **extra, **kwargs)


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _img(root: Path, state: str, kind: str, i: int = 0) -> np.ndarray:
    return cv2.imread(str(root / state / kind / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)


def _near(mask: np.ndarray, px: int) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)).astype(bool)


def _label_border(label: np.ndarray) -> np.ndarray:
    k = np.ones((3, 3), np.uint8)
    return cv2.dilate(label, k) != cv2.erode(label, k)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Renders shared by the tests: {name: folder}, all with seed 0 (same cameras)."""
    base = tmp_path_factory.mktemp("realism")
    settings = {"default": None, "clean": CLEAN, "realistic": PRESETS["realistic"],
                "realistic_again": PRESETS["realistic"], "background": Realism(background=1),
                "warp": Realism(depth_warp=1), "conf": Realism(confidence=1), "occluder": Realism(occluder=1),
                "jpeg": Realism(jpeg=1), "smear": Realism(edge_smear=1), "noise": Realism(depth_noise=1),
                "pose": Realism(pose_noise=1)}
    out = {}
    for name, realism in settings.items():
        _render(base / name, realism)
        out[name] = base / name
    return out


def test_presets_and_validation():
    assert CLEAN.is_clean and not PRESETS["realistic"].is_clean
    assert set(PRESETS["realistic"].levels().values()) == {1.0}
    assert tuple(rz.KNOB_TABLE) == rz.KNOBS
    assert rz.preset("realistic").with_levels(jpeg=0).jpeg == 0.0
    with pytest.raises(ValueError, match="depth_scale"):
        Realism(depth_scale=-1)
    with pytest.raises(ValueError, match="depth_scale"):
        Realism(depth_scale=math.nan)
    with pytest.raises(ValueError, match="realistic"):
        rz.preset("dirty")
    assert rz.jpeg_quality(1.0) == 70
    assert CLEAN.key() == "" and Realism(background=1, occluder=0.5).key() == "re-bg1-oc0.5"
    assert set(rz.KNOB_ABBREVIATIONS) == set(rz.KNOBS) and len(set(rz.KNOB_ABBREVIATIONS.values())) == len(rz.KNOBS)


def test_clean_is_the_plain_raycast(scenes, tmp_path):
    """Clean realism = no argument = the pre-realism code path (render_view + write_scene)."""
    assert _hashes(scenes["clean"]) == _hashes(scenes["default"])
    gt = json.loads((scenes["clean"] / "gt.json").read_text())
    assert "realism" not in gt and "mask_maps" not in gt and "gt_masks" not in gt
    assert not list(scenes["clean"].rglob("conf")) and not (scenes["clean"] / "gt_mask").exists()
    # re-render the same cameras with the bare raycaster and writer: identical images and cameras
    cams = json.loads((scenes["clean"] / "cameras.json").read_text())
    obj = build_cabinet(0)
    views = {}
    for state, q in (("start", Q0), ("end", Q1)):
        prep = PreparedScene(obj.posed_parts(q))
        views[state] = []
        for entry, c2w in zip(cams[state], gt["cameras"][state]):
            K, c2w = np.array(entry["K"]), np.array(c2w)
            views[state].append(RenderedView(*render_view(prep, K, c2w, W, H), K, c2w))
    write_scene(tmp_path, views["start"], views["end"], None, seed=0)
    ref = _hashes(tmp_path)
    got = {k: v for k, v in _hashes(scenes["clean"]).items() if k != "gt.json"}
    assert ref == got


def test_background_is_label_zero_with_depth(scenes):
    for state in ("start", "end"):
        for i in range(2):
            depth, mask = _img(scenes["background"], state, "depth", i), _img(scenes["background"], state, "mask", i)
            clean_depth = _img(scenes["clean"], state, "depth", i)
            assert not np.any((_img(scenes["clean"], state, "mask", i) == 0) & (clean_depth > 0))
            bg = (mask == 0) & (depth > 0)
            assert bg.mean() > 0.3, bg.mean()
            # the object itself is unchanged where it was seen
            obj = mask > 0
            assert np.array_equal(depth[obj], clean_depth[obj])
    gt = json.loads((scenes["background"] / "gt.json").read_text())
    assert gt["realism"]["background"]["table_top_z"] < 0.0 + 1e-9  # cabinet stands on z = 0


def test_warp_field_is_smooth_and_bounded():
    rng = np.random.default_rng(3)
    f = rz.warp_field(96, 128, 0.02, rng)
    assert np.abs(f - 1).max() <= 0.02 + 1e-12 and np.abs(f - 1).max() >= 0.01 - 1e-12
    # high-frequency energy: the discrete Laplacian of white noise has ~20 x its variance; a field of
    # at most one cycle per image has < (2 pi / 96) ** 4 ~ 2e-5 x
    lap = f[1:-1, :-2] + f[1:-1, 2:] + f[:-2, 1:-1] + f[2:, 1:-1] - 4 * f[1:-1, 1:-1]
    assert np.mean(lap ** 2) < 1e-4 * np.var(f)


def test_rendered_warp_within_amplitude(scenes):
    for state in ("start", "end"):
        d0 = _img(scenes["clean"], state, "depth").astype(float)
        d1 = _img(scenes["warp"], state, "depth").astype(float)
        valid = (d0 > 0) & (d1 > 0)
        ratio = d1[valid] / d0[valid]
        assert np.abs(ratio - 1).max() <= rz.DEPTH_WARP_AMPLITUDE + 1.5 / d0[valid].min()
        assert np.abs(ratio - 1).max() > 0.004
        assert np.array_equal(_img(scenes["warp"], state, "mask"), _img(scenes["clean"], state, "mask"))


def test_edge_smear_only_near_discontinuities(scenes):
    d0 = _img(scenes["clean"], "end", "depth").astype(float)
    d1 = _img(scenes["smear"], "end", "depth").astype(float)
    changed = d0 != d1
    assert changed.sum() > 20
    edges = rz.depth_discontinuities(d0)
    assert not np.any(changed & ~_near(edges, 3))
    both = changed & (d0 > 0) & (d1 > 0)
    near = cv2.erode(np.where(d0 > 0, d0, np.inf).astype(np.float32), np.ones((7, 7), np.uint8))
    far = cv2.dilate(d0.astype(np.float32), np.ones((7, 7), np.uint8))
    assert np.all((d1[both] >= near[both] - 1) & (d1[both] <= far[both] * 1.26 + 1))


def test_depth_noise_and_holes(scenes):
    d0 = _img(scenes["clean"], "start", "depth").astype(float)
    d1 = _img(scenes["noise"], "start", "depth").astype(float)
    holes = (d0 > 0) & (d1 == 0)
    assert holes.sum() > 0
    both = (d0 > 0) & (d1 > 0)
    rel = d1[both] / d0[both] - 1
    assert 0.002 < np.std(rel) < 0.02


def test_confidence_files(scenes):
    for name in ("conf", "realistic"):
        for state in ("start", "end"):
            for i in range(2):
                conf = np.load(scenes[name] / state / "conf" / f"{i:03d}.npy")
                depth = _img(scenes[name], state, "depth", i)
                assert conf.dtype == np.float32 and conf.shape == depth.shape
                assert conf.min() >= 0 and conf.max() <= 1
                assert np.all(conf[depth == 0] == 0)
    depth = _img(scenes["conf"], "start", "depth").astype(float)
    conf = np.load(scenes["conf"] / "start" / "conf" / "000.npy")
    edges = rz.depth_discontinuities(depth) & (depth > 0)
    interior = (depth > 0) & ~_near(edges, 4)
    assert conf[edges].mean() < 0.75 * conf[interior].mean()


def test_occluder_only_in_end_state_on_moving_part(scenes):
    occ, clean = scenes["occluder"], scenes["clean"]
    for kind in ("rgb", "depth", "mask"):
        for i in range(2):
            assert np.array_equal(_img(occ, "start", kind, i), _img(clean, "start", kind, i))
    gt = json.loads((occ / "gt.json").read_text())
    part = gt["realism"]["occluder"]["part_mask_id"]
    assert part in (2, 3)
    touched_border = False
    for i in range(2):
        d0, d1 = _img(clean, "end", "depth", i).astype(float), _img(occ, "end", "depth", i).astype(float)
        hand = (d1 > 0) & ((d0 == 0) | (d1 < d0))
        assert hand.sum() > 30
        assert np.all(_img(occ, "end", "mask", i)[hand] == 0)
        if i == gt["realism"]["occluder"]["found_in_view"]:
            assert (hand & (_img(clean, "end", "mask", i) == part)).sum() > 20
        touched_border |= bool(hand[0].any() or hand[-1].any() or hand[:, 0].any() or hand[:, -1].any())
    assert touched_border  # the forearm comes from outside the image


def test_jpeg_changes_but_keeps_the_image(scenes):
    a = _img(scenes["clean"], "start", "rgb").astype(float)
    b = _img(scenes["jpeg"], "start", "rgb").astype(float)
    assert not np.array_equal(a, b)
    mse = np.mean((a - b) ** 2)
    assert 10 * np.log10(255.0 ** 2 / mse) > 28
    assert np.array_equal(_img(scenes["jpeg"], "start", "depth"), _img(scenes["clean"], "start", "depth"))


def test_ragged_mask_changes_borders_only(scenes):
    label = _img(scenes["clean"], "end", "mask").astype(np.uint16)
    border = _label_border(label)
    frayed = 0
    events_seen = set()
    for seed in range(8):
        out, groups, events = rz.ragged_mask(label, 1.0, np.random.default_rng(seed), max_label=3)
        if not events:
            changed = out != label
            frayed += int(changed.sum())
            assert not np.any(changed & ~_near(border, math.ceil(rz.MASK_RAGGED_MAX_PX) + 1))
            assert groups == {int(i): int(i) for i in np.unique(out) if i}
    assert frayed > 0
    for seed in range(12):
        out, groups, events = rz.ragged_mask(label, 5.0, np.random.default_rng(seed), max_label=3)
        for e in events:
            kind = next(iter(e))
            events_seen.add(kind)
            if kind == "split":
                old, new = e["split"]
                assert new > 3 and groups[new] == groups[old] and (out == new).any()
            else:
                gone, _kept = e["merge"]
                assert not (out == gone).any() and gone not in groups
    assert events_seen == {"merge", "split"}


def test_ragged_masks_in_a_scene_keep_the_truth(tmp_path):
    gt = _render(tmp_path, Realism(mask_ragged=5), views=3)
    assert gt["gt_masks"] == "gt_mask/{state}/NNN.png"
    for state in ("start", "end"):
        for i, info in enumerate(gt["realism"]["views"][state]):
            truth = cv2.imread(str(tmp_path / "gt_mask" / state / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
            written = _img(tmp_path, state, "mask", i)
            assert truth.shape == written.shape and set(np.unique(truth)) <= {0, 1, 2, 3}
            for e in info.get("mask_events", []):
                if "split" in e:
                    old, new = e["split"]
                    assert gt["mask_maps"][state][i][str(new)] == old


def test_pose_noise_follows_the_bench_convention(scenes):
    cams = json.loads((scenes["pose"] / "cameras.json").read_text())
    gt = json.loads((scenes["pose"] / "gt.json").read_text())
    assert gt["pose_noise"] == {"deg": rz.POSE_NOISE_DEG, "translation": rz.POSE_NOISE_TRANSLATION}
    for entry, true in zip(cams["start"], gt["cameras"]["start"]):
        a, b = np.array(entry["cam_to_world"]), np.array(true)
        angle = math.degrees(math.acos(np.clip((np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2, -1, 1)))
        assert angle == pytest.approx(rz.POSE_NOISE_DEG, abs=1e-6)
        assert np.linalg.norm(a[:3, 3] - b[:3, 3]) == pytest.approx(rz.POSE_NOISE_TRANSLATION, abs=1e-9)


def test_same_seed_same_bytes(scenes, tmp_path):
    assert _hashes(scenes["realistic"]) == _hashes(scenes["realistic_again"])
    _render(tmp_path, PRESETS["realistic"], seed=1)
    other = _hashes(tmp_path)
    assert other["start/rgb/000.png"] != _hashes(scenes["realistic"])["start/rgb/000.png"]


def test_knob_streams_are_independent(scenes):
    """Turning one knob on does not change another knob's draws (one-factor-at-a-time benches)."""
    gt_w = json.loads((scenes["warp"] / "gt.json").read_text())
    gt_r = json.loads((scenes["realistic"] / "gt.json").read_text())
    for state in ("start", "end"):
        for a, b in zip(gt_w["realism"]["views"][state], gt_r["realism"]["views"][state]):
            assert a["warp_max"] == b["warp_max"]


def test_cli_realism_flags(capsys):
    from sparseart.cli import _parser, _realism_settings

    args = _parser().parse_args(["render", "obj", "scene", "--realism", "realistic", "--occluder", "0",
                                 "--depth-noise-level", "0.5"])
    r = _realism_settings(args)
    assert r.occluder == 0 and r.depth_noise == 0.5 and r.jpeg == 1
    assert _realism_settings(_parser().parse_args(["render", "o", "s"])).is_clean
    with pytest.raises(SystemExit) as stop:   # a level out of range is a usage error where it is parsed
        _parser().parse_args(["render", "o", "s", "--depth-warp", "9"])
    assert stop.value.code == 2 and "argument --depth-warp" in capsys.readouterr().err
