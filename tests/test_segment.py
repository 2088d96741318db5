"""Segmenters: built-in rule-based (purity on rendered PartNet frames, edge cases), SAM ONNX adapter
(against tiny exact models from tests/sam_builders.py), make_segmenter / segment_scene."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import PARTNET_DIR, TINY_K, requires_partnet
from sam_builders import build_decoder, build_encoder
from sparseart.lift.labels import build_labelled_cloud
from sparseart.lift.rgbd import pointmap_from_depth
from sparseart.io.scene import load_scene
from sparseart.segment import make_segmenter, segment_scene, segmentation_quality
from sparseart.segment.onnx_sam import SamSegmenter, box_nms, paint_masks, stability_scores
from sparseart.segment.rules import RuleOptions, RuleSegmenter, depth_jumps, segment_image
from sparseart.types import Camera, Frame, SceneError

PURITY_OBJECTS = ("drawer_26525", "microwave_7128", "oven_7201")


def _frame(rgb: np.ndarray, depth: np.ndarray | None = None, K=TINY_K) -> Frame:
    height, width = rgb.shape[:2]
    camera = Camera(K=np.asarray(K, dtype=np.float64), width=width, height=height) if depth is not None else None
    return Frame(state="start", index=0, rgb_path=Path("start/rgb/000.png"), rgb=rgb, depth=depth, camera=camera)


# --------------------------------------------------------------------------- quality measure


def test_segmentation_quality_counts_mixed_segments_and_leaks():
    truth = np.zeros((4, 6), np.int64)
    truth[:, :3], truth[:, 3:] = 1, 2
    perfect = truth * 5
    assert segmentation_quality(perfect, truth) == pytest.approx(
        {"segments": 2, "purity": 1.0, "coverage": 1.0, "leakage": 0.0, "background_in_segments": 0.0})
    one = np.ones_like(truth)
    quality = segmentation_quality(one, truth)
    assert quality["purity"] == pytest.approx(0.5) and quality["leakage"] == pytest.approx(1.0)
    shifted = truth.copy()
    shifted[:, 3] = 1  # column 3 (true part 2) joins segment 1
    quality = segmentation_quality(shifted, truth)
    assert quality["purity"] == pytest.approx(20 / 24)
    assert quality["leakage"] == pytest.approx(1.0)  # every boundary pair now lies inside segment 1


# --------------------------------------------------------------------------- built-in on PartNet


@pytest.fixture(scope="module")
def rendered_frames(tmp_path_factory):
    if not PARTNET_DIR.is_dir():
        pytest.skip("shared PartNet data missing")
    from sparseart.datasets.partnet import render_partnet_scene

    frames = {}
    for name in PURITY_OBJECTS:
        scene_dir = tmp_path_factory.mktemp("segment") / name
        render_partnet_scene(PARTNET_DIR / name, scene_dir, views=1, seed=0)
        frames[name] = load_scene(scene_dir).all_frames
    return frames


@requires_partnet
def test_builtin_segments_lie_on_one_part(rendered_frames):
    segmenter = RuleSegmenter()
    for name, frames in rendered_frames.items():
        for frame in frames:
            truth = frame.mask
            labels = segmenter.segment(frame)
            quality = segmentation_quality(labels, truth)
            where = f"{name} {frame.state}"
            assert quality["purity"] >= 0.97, where
            assert 3 <= quality["segments"] <= 60, where
            assert quality["coverage"] == 1.0, where  # every pixel with depth is segmented
            assert quality["background_in_segments"] == 0.0, where  # depth 0 is background
            # the floor is not trivially met: one segment over the object fails it
            assert segmentation_quality((truth > 0).astype(np.int64), truth)["purity"] < 0.97, where


# --------------------------------------------------------------------------- built-in edge cases


def test_builtin_uniform_plane_is_one_segment_without_background():
    frame = _frame(np.full((30, 40, 3), 128, np.uint8), np.full((30, 40), 1.0))
    labels = RuleSegmenter().segment(frame)
    assert labels.dtype == np.int64 and labels.shape == (30, 40)
    assert set(np.unique(labels)) == {1}


def test_builtin_separates_a_step_in_depth_and_keeps_background():
    depth = np.full((40, 60), 2.0)
    depth[:, 30:] = 1.9  # a 10 cm step, same colour on both sides
    depth[:5] = 0.0  # invalid rows = background
    labels = segment_image(np.full((40, 60, 3), 90, np.uint8), depth, np.asarray(TINY_K, float))
    assert np.all(labels[:5] == 0)
    left, right = labels[5:, :29], labels[5:, 31:]
    assert np.all(left > 0) and np.all(right > 0)
    assert set(np.unique(left)).isdisjoint(np.unique(right))


def test_builtin_colour_only_without_depth():
    rgb = np.zeros((30, 40, 3), np.uint8)
    rgb[:, :20] = (200, 30, 30)
    rgb[:, 20:] = (30, 30, 200)
    labels = RuleSegmenter().segment(_frame(rgb))
    assert np.all(labels > 0)  # no depth: no background
    assert set(np.unique(labels[:, :19])).isdisjoint(np.unique(labels[:, 21:]))


def test_builtin_all_invalid_depth_gives_background_only():
    labels = RuleSegmenter().segment(_frame(np.full((20, 20, 3), 50, np.uint8), np.zeros((20, 20))))
    assert labels.shape == (20, 20) and not labels.any()


def test_builtin_tiny_image_and_bad_inputs():
    labels = RuleSegmenter().segment(_frame(np.full((3, 3, 3), 10, np.uint8), np.ones((3, 3))))
    assert labels.shape == (3, 3) and np.all(labels > 0)
    with pytest.raises(ValueError, match="000.png.*RGB image"):
        RuleSegmenter().segment(_frame(np.zeros((10, 10), np.uint8)))
    with pytest.raises(ValueError, match="too small"):
        RuleSegmenter().segment(_frame(np.zeros((1, 5, 3), np.uint8)))
    with pytest.raises(ValueError, match="depth 4x4 does not match"):
        RuleSegmenter().segment(_frame(np.zeros((10, 10, 3), np.uint8), np.ones((4, 4))))
    with pytest.raises(ValueError, match="merge_colour"):
        RuleOptions(merge_colour=-1.0)


def test_depth_jumps_ignore_slanted_planes():
    # inverse depth affine in u: a steep plane has large steps between neighbours but no jump
    u = np.arange(50, dtype=np.float64)
    depth = np.tile(1.0 / (0.2 + 0.01 * u), (5, 1))
    jumps = depth_jumps(depth, focal=40.0, jump_pixels=1.5, jump_relative=0.5)
    assert not jumps.any()
    depth[:, 25:] += 0.2
    assert depth_jumps(depth, focal=40.0, jump_pixels=1.5, jump_relative=0.5).any()


# --------------------------------------------------------------------------- make_segmenter / segment_scene


def test_make_segmenter_specs_and_errors(tmp_path):
    assert make_segmenter("builtin", max_segments=10).options.max_segments == 10
    assert make_segmenter("given").name == "given"
    with pytest.raises(ValueError, match="unknown segmenter spec 'magic'"):
        make_segmenter("magic")
    with pytest.raises(ValueError, match="expected 'sam:ENCODER.onnx,DECODER.onnx'"):
        make_segmenter("sam:only_one.onnx")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['grid'\]"):
        make_segmenter("builtin", grid=3)
    with pytest.raises(ValueError, match="encoder model file not found"):
        make_segmenter(f"sam:{tmp_path / 'missing.onnx'},{tmp_path / 'also.onnx'}")


def test_segment_scene_sets_masks_for_label_transfer(tiny_scene):
    scene = load_scene(tiny_scene)
    for frame in scene.all_frames:
        frame.mask = None
    segment_scene(scene, make_segmenter("builtin"))
    assert scene.has_masks
    for frame in scene.all_frames:  # the tiny scene: grey left half, red right half, plane at 1 m
        assert set(np.unique(frame.mask[:, :19])).isdisjoint(np.unique(frame.mask[:, 21:]))
    pointmaps = [pointmap_from_depth(frame) for frame in scene.start]
    cloud = build_labelled_cloud("start", scene.start, pointmaps)
    assert len(cloud.segment_source) >= 2 and (cloud.segment >= 0).mean() > 0.8


def test_segment_scene_is_all_or_nothing(tiny_scene):
    scene = load_scene(tiny_scene)
    before = [frame.mask.copy() for frame in scene.all_frames]

    class FailsOnEnd:
        name = "fails"

        def segment(self, frame):
            if frame.state == "end":
                raise ValueError(f"{frame.rgb_path}: boom")
            return np.ones(frame.shape, np.int64)

    with pytest.raises(ValueError, match="boom"):
        segment_scene(scene, FailsOnEnd())
    assert all(np.array_equal(f.mask, m) for f, m in zip(scene.all_frames, before))

    class WrongShape:
        name = "wrong"

        def segment(self, frame):
            return np.ones((2, 2), np.int64)

    with pytest.raises(ValueError, match="returned shape"):
        segment_scene(scene, WrongShape())


def test_given_segmenter_needs_masks(tmp_path):
    from conftest import write_tiny_scene

    scene = load_scene(write_tiny_scene(tmp_path / "s", masks=False))
    with pytest.raises(SceneError, match="segmenter 'given' needs a mask image"):
        segment_scene(scene, make_segmenter("given"))
    masked = load_scene(write_tiny_scene(tmp_path / "m"))
    original = masked.start[0].mask.copy()
    segment_scene(masked, make_segmenter("given"))
    assert np.array_equal(masked.start[0].mask, original)


# --------------------------------------------------------------------------- SAM adapter


@pytest.fixture(scope="module")
def sam_models(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sam")
    return {"encoder": build_encoder(folder / "encoder.onnx"),
            "decoder": build_decoder(folder / "decoder.onnx"),
            "decoder_single": build_decoder(folder / "decoder_single.onnx", batched=False),
            "folder": folder}


COLOURS = {(200, 200, 200): None, (255, 0, 0): (slice(5, 20), slice(5, 30)),
           (0, 0, 255): (slice(25, 45), slice(10, 40)), (0, 160, 0): (slice(10, 40), slice(45, 60))}


def _colour_image() -> np.ndarray:
    rgb = np.full((48, 64, 3), 200, np.uint8)
    for colour, where in COLOURS.items():
        if where is not None:
            rgb[where] = colour
    return rgb


@pytest.mark.parametrize("decoder", ["decoder", "decoder_single"])
def test_sam_grid_gives_one_segment_per_colour(sam_models, decoder, monkeypatch):
    segmenter = SamSegmenter(sam_models["encoder"], sam_models[decoder])
    assert segmenter.batched == (decoder == "decoder")
    calls = []
    original = SamSegmenter._decode
    monkeypatch.setattr(SamSegmenter, "_decode",
                        lambda self, e, p, h, w: calls.append(len(p)) or original(self, e, p, h, w))
    segmenter.options = type(segmenter.options)(points_per_side=8, points_per_batch=16)
    rgb = _colour_image()
    labels = segmenter.segment(_frame(rgb))
    assert calls == ([16] * 4 if decoder == "decoder" else [1] * 64)
    seen = set()
    for colour in COLOURS:
        ids = np.unique(labels[np.all(rgb == colour, axis=2)])
        assert ids.size == 1 and ids[0] > 0, colour
        seen.add(int(ids[0]))
    assert len(seen) == 4 and set(np.unique(labels)) == seen


def test_sam_iou_and_stability_filters(sam_models):
    frame = _frame(_colour_image())
    only_unstable = make_segmenter(f"sam:{sam_models['encoder']},{sam_models['decoder']}",
                                   points_per_side=4, pred_iou_thresh=0.96)
    assert not only_unstable.segment(frame).any()  # the 0.99-IoU masks are all unstable
    keep_unstable = make_segmenter(f"sam:{sam_models['encoder']},{sam_models['decoder']}",
                                   points_per_side=4, pred_iou_thresh=0.96, stability_thresh=0.0)
    assert keep_unstable.segment(frame).any()
    assert stability_scores(np.array([[[2.0, 0.5, -0.5, -2.0]]]), 1.0) == pytest.approx([1 / 3])


def test_sam_depth_background_and_prompts(sam_models):
    rgb = _colour_image()
    depth = np.ones(rgb.shape[:2])
    depth[:, :32] = 0.0  # left half has no depth: background, no prompts there
    segmenter = make_segmenter(f"sam:{sam_models['encoder']},{sam_models['decoder']}", points_per_side=8)
    labels = segmenter.segment(_frame(rgb, depth))
    assert not labels[:, :32].any() and labels[:, 32:].all()


def test_nms_and_painting_order():
    big = np.zeros((10, 10), bool)
    big[1:9, 1:9] = True
    small = np.zeros((10, 10), bool)
    small[3:5, 3:5] = True
    masks = np.stack([small, big, big.copy()])
    keep = box_nms(masks, np.array([0.9, 0.8, 0.95]), 0.7)
    assert sorted(keep.tolist()) == [0, 2]  # the duplicate big mask with the lower score goes
    labels = paint_masks(masks[keep])
    assert len(np.unique(labels[small])) == 1 and labels[small][0] != labels[2, 2]  # small on top
    assert labels[0, 0] == 0


def test_sam_model_errors(sam_models, tmp_path):
    folder = sam_models["folder"]
    renamed = build_decoder(folder / "renamed.onnx", names={"point_coords": "coords"})
    with pytest.raises(ValueError, match=r"lacks inputs \['point_coords'\]; it has .*coords"):
        SamSegmenter(sam_models["encoder"], renamed)
    sam2 = build_decoder(folder / "sam2.onnx", names={"image_embeddings": "image_embed"})
    with pytest.raises(ValueError, match="a SAM2 decoder"):
        SamSegmenter(sam_models["encoder"], sam2)
    wrong_output = build_encoder(folder / "features.onnx", output_name="features")
    with pytest.raises(ValueError, match="do not include 'image_embeddings'"):
        SamSegmenter(wrong_output, sam_models["decoder"])
    four_channels = build_decoder(folder / "four.onnx", embed_channels=4)
    with pytest.raises(ValueError, match="mismatched encoder/decoder pair"):
        SamSegmenter(sam_models["encoder"], four_channels)
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="junk.onnx: SAM decoder: not a valid ONNX model"):
        SamSegmenter(sam_models["encoder"], junk)


# ---------------------------------------------------------------------- fragmented part masks (issue 61)


def test_effective_segments_counts_similar_pieces_not_specks() -> None:
    from sparseart.segment.base import effective_segments

    halves = np.repeat(np.array([[1, 2]]), 4, axis=0).repeat(8, axis=1)       # two equal parts
    assert effective_segments(halves) == pytest.approx(2.0)
    blocks = (np.arange(64).reshape(8, 8) + 1)                                  # 64 one-pixel ids
    assert effective_segments(blocks) == pytest.approx(64.0)
    frayed = np.ones((100, 100), np.int64)
    frayed[0, :20] = np.arange(2, 22)                                           # 20 specks on one part
    assert effective_segments(frayed) < 1.01
    assert effective_segments(np.zeros((4, 4), np.int64)) == 0.0
    valid = np.zeros((8, 8), bool)
    valid[:, :4] = True                                                         # depth on the left half only
    assert effective_segments(np.where(np.arange(8)[None, :] < 4, 1, 2).repeat(8, 0), valid) == pytest.approx(1.0)


def test_fragmented_frames_name_checkerboards_not_part_masks() -> None:
    from sparseart.segment.base import MAX_EFFECTIVE_SEGMENTS, fragmented_frames

    rows, cols = np.mgrid[0:120, 0:160]
    parts = np.where(cols < 60, 1, np.where(rows < 60, 2, 3))
    checker = (rows // 16) * 10 + cols // 16 + 1
    depth = np.ones((120, 160))

    def frame(mask, index):
        return Frame(state="start", index=index, rgb_path=Path(f"rgb/{index:03d}.png"),
                     rgb=np.zeros((120, 160, 3), np.uint8), depth=depth, mask=mask)

    found = fragmented_frames([frame(parts, 0), frame(checker, 1), frame(None, 2)])
    assert [f.index for f, _ in found] == [1]
    assert found[0][1] > MAX_EFFECTIVE_SEGMENTS
    assert MAX_EFFECTIVE_SEGMENTS >= 3 * 3.1   # the corpus' part masks stay far below it
