"""Depth confidence (``{state}/conf/NNN.npy``, design section 2; issue 13 item 4): the loader reads
and checks it, lifting carries it into the pointmaps and labelled clouds, low-confidence points are
left out, and the joint fit weights matched pairs by it. Absent confidence changes nothing."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import write_tiny_scene
from scipy.spatial.transform import Rotation
from synthetic import box_surface

from sparseart.cli import main
from sparseart.io.scene import load_scene
from sparseart.joints.config import FitConfig
from sparseart.joints.fit import fit_joint
from sparseart.joints.optimise import confidence_pair_weights, pair_weights
from sparseart.joints.part import clear_cache, prepare_part
from sparseart.lift import labels as lift_labels
from sparseart.lift.labels import build_labelled_cloud
from sparseart.lift.rgbd import pointmap_from_depth
from sparseart.types import SceneError

H, W = 30, 40


def _conf_map(seed: int = 0) -> np.ndarray:
    """A float32 map with a low-confidence band in columns 0-4 and 0.5-1 elsewhere."""
    rng = np.random.default_rng(seed)
    conf = rng.uniform(0.5, 1.0, (H, W)).astype(np.float32)
    conf[:, :5] = 0.05
    return conf


def _scene_with_conf(root: Path, views: int = 2) -> Path:
    write_tiny_scene(root, views=views)
    for state in ("start", "end"):
        (root / state / "conf").mkdir()
        for i in range(views):
            np.save(root / state / "conf" / f"{i:03d}.npy", _conf_map(i))
    return root


# ---------------------------------------------------------------------- loader


def test_loader_reads_conf_as_float64(tmp_path: Path) -> None:
    scene = load_scene(_scene_with_conf(tmp_path / "scene"))
    for frame in scene.all_frames:
        assert frame.depth_confidence is not None
        assert frame.depth_confidence.dtype == np.float64 and frame.depth_confidence.shape == (H, W)
        np.testing.assert_array_equal(frame.depth_confidence, _conf_map(frame.index).astype(np.float64))
        assert frame.confidence_path.name == f"{frame.index:03d}.npy"


def test_loader_without_conf_leaves_none(tmp_path: Path) -> None:
    scene = load_scene(write_tiny_scene(tmp_path / "scene"))
    assert all(f.depth_confidence is None for f in scene.all_frames)


def _bad(array) -> callable:
    def mutate(root: Path) -> str:
        np.save(root / "start" / "conf" / "001.npy", array)
        return "start/conf/001.npy"
    return mutate


def _remove(rel: str, culprit: str):
    def mutate(root: Path) -> str:
        path = root / rel
        if path.is_dir():
            for child in path.iterdir():
                child.unlink()
            path.rmdir()
        else:
            path.unlink()
        return culprit
    return mutate


def _not_npy(root: Path) -> str:
    (root / "start" / "conf" / "001.npy").write_bytes(b"not an array")
    return "start/conf/001.npy"


BAD = {
    "nan": (_bad(np.full((H, W), np.nan, np.float32)), "non-finite"),
    "inf": (_bad(np.where(np.eye(H, W) > 0, np.inf, 0.5).astype(np.float32)), "non-finite"),
    "above_one": (_bad(np.full((H, W), 1.2, np.float32)), "[0, 1]"),
    "negative": (_bad(np.full((H, W), -0.01, np.float64)), "[0, 1]"),
    "wrong_shape": (_bad(np.ones((H, W + 1), np.float32)), "does not match depth"),
    "transposed": (_bad(np.ones((W, H), np.float32)), "does not match depth"),
    "int_dtype": (_bad(np.ones((H, W), np.int32)), "dtype"),
    "unreadable": (_not_npy, "not a valid .npy"),
    "missing_one_view": (_remove("start/conf/001.npy", "start/conf"), "no depth confidence"),
    "missing_one_state": (_remove("end/conf", "end/rgb/000.png"), "depth confidence"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_conf_is_one_line_naming_file_and_field(name: str, tmp_path: Path) -> None:
    root = _scene_with_conf(tmp_path / "scene")
    mutate, phrase = BAD[name]
    culprit = mutate(root)
    with pytest.raises(SceneError) as error:
        load_scene(root)
    message = str(error.value)
    assert "\n" not in message
    assert culprit in message, message
    assert phrase in message, message
    if name not in ("unreadable", "int_dtype"):
        assert "confidence" in message, message


def test_conf_without_depth_is_an_error(tmp_path: Path) -> None:
    root = _scene_with_conf(tmp_path / "scene")
    for state in ("start", "end"):
        for path in (root / state / "depth").iterdir():
            path.unlink()
        (root / state / "depth").rmdir()
    with pytest.raises(SceneError, match=r"start/conf/000\.npy: depth confidence without depth"):
        load_scene(root, require_depth=False)


def test_cli_bad_conf_exits_2_and_writes_nothing(tmp_path: Path, capfd) -> None:
    root = _scene_with_conf(tmp_path / "scene")
    _bad(np.full((H, W), 2.0, np.float32))(root)
    out = tmp_path / "out"
    capfd.readouterr()
    assert main(["run", str(root), "--out", str(out)]) == 2
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "start/conf/001.npy" in err[0] and "depth confidence" in err[0], err
    assert not out.exists()


# ---------------------------------------------------------------------- lift and labelled clouds


def _state_cloud(root: Path, min_confidence=None, state: str = "start"):
    scene = load_scene(root)
    frames = scene.frames(state)
    pointmaps = [pointmap_from_depth(f, reject_flying_pixels=False) for f in frames]
    return frames, pointmaps, build_labelled_cloud(state, frames, pointmaps, min_confidence=min_confidence)


def test_conf_reaches_pointmap_and_labelled_cloud(tmp_path: Path) -> None:
    frames, pointmaps, cloud = _state_cloud(_scene_with_conf(tmp_path / "scene"), min_confidence=0.0)
    for frame, pointmap in zip(frames, pointmaps):
        np.testing.assert_array_equal(pointmap.confidence, frame.depth_confidence.reshape(-1) * pointmap.valid)
    assert len(cloud) == sum(int(p.valid.sum()) for p in pointmaps)       # threshold 0: nothing dropped
    expected = np.array([frames[f].depth_confidence.reshape(-1)[p] for f, p in zip(cloud.frame_index,
                                                                                  cloud.pixel_index)])
    assert cloud.confidence.dtype == np.float64
    np.testing.assert_array_equal(cloud.confidence, expected)
    assert cloud.confidence.min() == pytest.approx(0.05)


@pytest.mark.parametrize("threshold", [0.15, 0.3])
def test_low_confidence_points_are_dropped(tmp_path: Path, threshold: float) -> None:
    root = _scene_with_conf(tmp_path / "scene")
    _, _pointmaps, everything = _state_cloud(root, min_confidence=0.0)
    _, _, kept = _state_cloud(root, min_confidence=threshold)
    assert kept.confidence.min() >= threshold
    low = everything.confidence < threshold
    assert low.sum() >= 2 * H * 5                          # at least the 5 low columns of both views
    assert len(kept) == len(everything) - low.sum()
    assert not np.isin(kept.pixel_index % W, np.arange(5)).any()
    np.testing.assert_array_equal(kept.points, everything.points[~low])


def test_default_threshold_keeps_every_point(tmp_path: Path) -> None:
    """Dropping is off by default (``DEPTH_CONFIDENCE_MIN`` = 0: it hurt on the rendered scenes)."""
    root = _scene_with_conf(tmp_path / "scene")
    _, pointmaps, default = _state_cloud(root)
    assert lift_labels.DEPTH_CONFIDENCE_MIN == 0.0
    assert len(default) == sum(int(p.valid.sum()) for p in pointmaps)
    assert FitConfig().confidence_weights is False


def test_absent_conf_changes_nothing(tmp_path: Path) -> None:
    root = write_tiny_scene(tmp_path / "scene", views=2)
    _frames, pointmaps, cloud = _state_cloud(root)
    assert len(cloud) == sum(int(p.valid.sum()) for p in pointmaps) == 2 * H * W
    np.testing.assert_array_equal(cloud.confidence, np.ones(len(cloud)))
    # a threshold of 1 cannot drop anything either: only frames WITH a map are thresholded
    _, _, strict = _state_cloud(root, min_confidence=1.0)
    np.testing.assert_array_equal(strict.points, cloud.points)


# ---------------------------------------------------------------------- the fit


def _door(seed: int = 0, n: int = 3000, low: float = 0.01):
    """A door slab (1 x 0.1 x 1.2 box surface) turning 30 deg about z through the origin; the end
    points above z = 0.8 (a third) are pushed 4 cm along +y (a depth warp) and given confidence
    ``low``."""
    rng = np.random.default_rng(seed)
    start = box_surface([1.0, 0.1, 1.2], [0.5, 0.05, 0.6], n, rng)[0]
    rotation = Rotation.from_rotvec([0, 0, np.radians(30)]).as_matrix()
    end = box_surface([1.0, 0.1, 1.2], [0.5, 0.05, 0.6], n, rng)[0] @ rotation.T
    end_conf = np.ones(len(end))
    warped = end[:, 2] > 0.8
    end[warped, 1] += 0.04
    end_conf[warped] = low
    return start, end, np.ones(len(start)), end_conf


WEIGHTED = {"uncertainty_resamples": 0, "half_samples": 0, "confidence_weights": True}


def test_pair_weights_follow_confidence() -> None:
    start, end, start_conf, end_conf = _door()
    config = FitConfig.for_budget("fast", **WEIGHTED)
    plain = prepare_part(start, end, config, cache=False)
    weighted = prepare_part(start, end, config, cache=False, start_confidence=start_conf, end_confidence=end_conf)
    off = prepare_part(start, end, replace(config, confidence_weights=False), cache=False,
                       start_confidence=start_conf, end_confidence=end_conf)
    assert plain.match.start_confidence is None and off.match.end_confidence is None
    sample = weighted.match
    np.testing.assert_array_equal(sample.start, plain.match.start)     # same samples, confidence carried along
    np.testing.assert_array_equal(sample.end, plain.match.end)
    assert weighted.chamfer.end_confidence is not None and weighted.screen.end_confidence is not None
    rows = np.arange(200)
    cols = np.arange(200)
    base = pair_weights("revolute", sample.start[rows], sample.end[cols], 0.1)
    assert confidence_pair_weights(base, plain.match, rows, cols) is base
    scaled = confidence_pair_weights(base, sample, rows, cols)
    assert scaled.mean() == pytest.approx(base.mean())
    low = sample.end_confidence[cols] < 0.5
    assert 0 < low.sum() < len(rows)
    ratio = scaled / base
    np.testing.assert_allclose(ratio[low] / ratio[~low].mean(), np.sqrt(0.01), rtol=1e-9)


def test_all_one_confidence_fits_identically() -> None:
    start, end, _, _ = _door(seed=1)
    config = FitConfig.for_budget("fast", **WEIGHTED)
    ones = {"start_confidence": np.ones(len(start)), "end_confidence": np.ones(len(end))}
    plain_part = prepare_part(start, end, config, cache=False)
    ones_part = prepare_part(start, end, config, cache=False, **ones)
    for name in ("match", "chamfer", "screen"):
        assert getattr(ones_part, name).start_confidence is None        # all ones = not given
        np.testing.assert_array_equal(getattr(ones_part, name).start, getattr(plain_part, name).start)
        np.testing.assert_array_equal(getattr(ones_part, name).end, getattr(plain_part, name).end)
    plain = fit_joint(start, end, "revolute", config=config)
    clear_cache()
    with_ones = fit_joint(start, end, "revolute", config=replace(config, seed=0), **ones)
    np.testing.assert_allclose(with_ones.axis, plain.axis, rtol=0, atol=1e-8)   # summation-order noise only
    np.testing.assert_allclose(with_ones.origin, plain.origin, rtol=0, atol=1e-8)


def test_fit_down_weights_low_confidence_points() -> None:
    start, end, start_conf, end_conf = _door()
    config = FitConfig.for_budget("fast", **WEIGHTED)

    def axis_error(estimate) -> float:
        return float(np.degrees(np.arccos(min(1.0, abs(estimate.axis[2])))))

    ignored = fit_joint(start, end, "revolute", config=config)
    used = fit_joint(start, end, "revolute", config=config, start_confidence=start_conf, end_confidence=end_conf)
    off = fit_joint(start, end, "revolute", config=replace(config, confidence_weights=False),
                    start_confidence=start_conf, end_confidence=end_conf)
    assert axis_error(ignored) > 3.0                       # the warp tilts the axis ...
    assert axis_error(used) < 0.7 * axis_error(ignored), (axis_error(used), axis_error(ignored))   # ... less
    np.testing.assert_allclose(off.axis, ignored.axis, rtol=0, atol=1e-8)  # switched off: confidences ignored


def test_fit_rejects_bad_confidence() -> None:
    start, end, start_conf, _ = _door()
    config = FitConfig(confidence_weights=True)
    with pytest.raises(ValueError, match="end_confidence"):
        prepare_part(start, end, config, cache=False, start_confidence=start_conf,
                     end_confidence=np.full(len(end), np.nan))
    with pytest.raises(ValueError, match="start_confidence"):
        prepare_part(start, end, config, cache=False, start_confidence=start_conf[:-1])


def test_measurable_motion_needs_a_gain_beyond_sampling() -> None:
    """Issue 61: a motion that lays no more of the part onto the other state than no motion does
    is not a measurement; a clear gain is, and the bar shrinks with more points."""
    from sparseart.joints.reliability import measurable_motion

    assert not measurable_motion(0.93, 0.935, 233, 229)      # a noisy floor's fitted 10 cm slide
    assert not measurable_motion(0.976, 0.974, 1322, 1290)   # a still box under 1 % noise
    assert measurable_motion(0.996, 0.097, 1500, 1500)       # the door, turned 37 deg
    assert measurable_motion(0.885, 0.273, 1500, 1500)       # the faucet handle
    assert not measurable_motion(0.95, 0.92, 40, 40) and measurable_motion(0.95, 0.92, 4000, 4000)
    assert not measurable_motion(1.0, 1.0, 1500, 1500) and not measurable_motion(0.9, 0.1, 0, 10)
