"""Plain dataclasses exchanged between pipeline stages.

Conventions used everywhere in sparseart:

* Geometry is float64. Points are ``(N, 3)`` arrays in the *scene frame*: the world frame of
  ``cameras.json`` for posed scenes, else the OpenCV frame of ``start/rgb/000.png``.
* Cameras follow OpenCV (x right, y down, z forward). ``K`` is ``(3, 3)``; ``cam_to_world`` is a
  ``(4, 4)`` rigid transform mapping camera coordinates to the scene frame.
* Pixel index ``k`` of an ``H x W`` image is row-major: pixel ``(k // W, k % W)``.
* Motion semantics (design section 3): a point ``x`` of a movable part at start moves to
  ``origin + R(axis, angle) (x - origin)`` (revolute) or ``x + distance * axis`` (prismatic).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .errors import SceneError  # noqa: F401 - re-exported: the types' home names it too

StateName = Literal["start", "end"]
JointType = Literal["revolute", "prismatic"]
JOINT_TYPES: tuple[str, ...] = ("revolute", "prismatic")
STATES: tuple[str, ...] = ("start", "end")


@dataclass
class Camera:
    """Pinhole camera of one image.

    K: (3, 3) float64 intrinsics in pixels.
    cam_to_world: (4, 4) float64 rigid transform camera -> scene frame, or None when unknown.
    width, height: image size in pixels.
    """

    K: np.ndarray
    width: int
    height: int
    cam_to_world: np.ndarray | None = None


@dataclass
class Frame:
    """One image of one state, as read from the scene folder.

    rgb: (H, W, 3) uint8.
    depth: (H, W) float64 metres (0 = invalid) or None.
    mask: (H, W) int64 label image (0 = background) or None. Ids are local to this image.
    depth_confidence: (H, W) float64 in [0, 1], the per-pixel confidence of the depth
        (``conf/NNN.npy``: a reconstructor's depth_conf or a sensor's quality map), or None
        (unknown: every valid depth pixel counts fully).
    """

    state: str
    index: int
    rgb_path: Path
    rgb: np.ndarray
    depth: np.ndarray | None = None
    mask: np.ndarray | None = None
    camera: Camera | None = None
    depth_path: Path | None = None
    mask_path: Path | None = None
    depth_confidence: np.ndarray | None = None
    confidence_path: Path | None = None

    @property
    def image(self) -> str:
        """The image as the scene folder names it, ``STATE/rgb/NAME`` (reports and warnings)."""
        return f"{self.state}/rgb/{self.rgb_path.name}"

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.rgb.shape[0]), int(self.rgb.shape[1])


@dataclass
class Scene:
    """A validated scene folder (design section 2)."""

    root: Path
    start: list[Frame]
    end: list[Frame]
    depth_scale: float = 1000.0
    warnings: list[str] = field(default_factory=list)

    def frames(self, state: str) -> list[Frame]:
        return self.start if state == "start" else self.end

    @property
    def all_frames(self) -> list[Frame]:
        return [*self.start, *self.end]

    @property
    def has_depth(self) -> bool:
        return all(f.depth is not None for f in self.all_frames)

    @property
    def has_masks(self) -> bool:
        return all(f.mask is not None for f in self.all_frames)

    @property
    def posed(self) -> bool:
        """True when every image of both states has a cam_to_world."""
        return all(f.camera is not None and f.camera.cam_to_world is not None for f in self.all_frames)


@dataclass
class Pointmap:
    """Per-pixel 3D points of one frame, in the scene frame.

    points: (H*W, 3) float64, row-major pixel order; invalid pixels hold NaN.
    valid: (H*W,) bool.
    confidence: (H*W,) float64 in [0, 1].
    depth: optional (H, W) float64 depth along the optical axis (frame units, 0 = invalid) for
        depth-aware mask boundaries when the frame has no depth image (a reconstructor's output).
    """

    state: str
    frame_index: int
    height: int
    width: int
    points: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray
    depth: np.ndarray | None = None  # (H, W) float64 along the optical axis (0 = invalid), when known


@dataclass
class LabelledCloud:
    """All valid points of one state, concatenated over its frames.

    points: (N, 3) float64, scene frame.
    colors: (N, 3) float64 RGB in [0, 1].
    segment: (N,) int64 segment id, unique within the state (frame-local mask ids are remapped so
        that ids from different frames never collide); -1 = no mask / background.
    frame_index: (N,) int64 index of the frame each point came from.
    pixel_index: (N,) int64 row-major pixel index k in its frame.
    confidence: (N,) float64 in [0, 1].
    segment_source: segment id -> (frame index, mask id in that frame's mask image).
    """

    state: str
    points: np.ndarray
    colors: np.ndarray
    segment: np.ndarray
    frame_index: np.ndarray
    pixel_index: np.ndarray
    confidence: np.ndarray
    segment_source: dict[int, tuple[int, int]] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def mask_ids(self) -> np.ndarray:
        """(N,) int64 mask id of each point (0 where the point has no segment from a mask). O(N)."""
        segments, inverse = np.unique(self.segment, return_inverse=True)
        lookup = np.array([self.segment_source.get(int(s), (0, 0))[1] for s in segments], dtype=np.int64)
        return lookup[inverse.reshape(-1)]

    def subset(self, keep: np.ndarray) -> "LabelledCloud":
        """A new cloud with only the points where ``keep`` (bool (N,) or index array) selects."""
        return LabelledCloud(
            state=self.state,
            points=self.points[keep],
            colors=self.colors[keep],
            segment=self.segment[keep],
            frame_index=self.frame_index[keep],
            pixel_index=self.pixel_index[keep],
            confidence=self.confidence[keep],
            segment_source=dict(self.segment_source),
        )


@dataclass
class PartSpec:
    """One rigid part. Part 0 is the static base by convention."""

    id: int
    role: Literal["static", "movable"]
    joint_type: str | None = None  # prior from the labeler: "revolute", "prismatic" or None
    parent: int | None = None


@dataclass
class PartLabels:
    """Labeler output: which points belong to which part, in each state.

    start_part / end_part: (N_start,) / (N_end,) int64 part id per point of each state's
        LabelledCloud; -1 = not assigned (background, outlier, unsure).
    start_segment_to_part / end_segment_to_part: segment id -> part id, when decided per segment.
    initial_motion: part id -> (4, 4) float64 start->end rigid transform estimated by the labeler
        (evidence for the fitter; may be absent).
    type_prior: part id -> "revolute" | "prismatic" read off the motion; a hint, not a decision
        (unlike ``PartSpec.joint_type``, it does not skip the fitter's classification).
    alternative_motions: part id -> other (4, 4) start->end motions that explain the part's points
        about as well as ``initial_motion`` (symmetric parts); the pipeline fits from each.
    confidence: part id -> the labeler's trust in the part's pairing across the states, in [0, 1]
        (1 when absent): look-alike parts whose pairing the other way round costs almost as much
        get less; the joint's confidence is multiplied by it (:func:`~sparseart.joints.candidates.fit_parts`).
    diagnostics: the labeler's own report (pairing costs, runner-up, consistency; JSON-able).
    """

    parts: list[PartSpec]
    start_part: np.ndarray
    end_part: np.ndarray
    start_segment_to_part: dict[int, int] = field(default_factory=dict)
    end_segment_to_part: dict[int, int] = field(default_factory=dict)
    initial_motion: dict[int, np.ndarray] = field(default_factory=dict)
    type_prior: dict[int, str] = field(default_factory=dict)
    alternative_motions: dict[int, list[np.ndarray]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    confidence: dict[int, float] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)

    @property
    def movable(self) -> list[PartSpec]:
        return [p for p in self.parts if p.role == "movable"]


@dataclass
class JointEstimate:
    """A fitted joint, in the frame of the points it was fitted on.

    axis: (3,) float64 unit vector. origin: (3,) float64 point on the axis (revolute: the point
    nearest the part centre; prismatic: the part centre at start). angle: radians (revolute),
    distance: frame units (prismatic); the other is None. slide: for revolute joints, the
    translation along the axis that the screw decomposition found (frame units; ideally 0).
    transform: (4, 4) float64 start->end rigid motion implied by the joint.
    uncertainty: {"axis_deg": float, "origin": float, "angle": float (rad) | "distance": float}.
    residual: RMS distance of matched pairs after the fit (frame units).
    confidence: in [0, 1].
    """

    type: str
    axis: np.ndarray
    origin: np.ndarray
    angle: float | None
    distance: float | None
    transform: np.ndarray
    uncertainty: dict[str, float]
    residual: float
    confidence: float
    slide: float = 0.0
    warnings: list[str] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)


@dataclass
class StageRecord:
    name: str
    ran: bool
    seconds: float
    why: str


@dataclass
class PartResult:
    """One part of the result: its spec, how many points it had, its joint (movable parts) and,
    after ``--refine``, the refinement (``sparseart.refine.api.PartRefinement``: Gaussians, views)."""

    spec: PartSpec
    n_points: int
    joint: JointEstimate | None = None
    refinement: Any = None


@dataclass
class Articulation:
    """The pipeline's result; serialised to articulation.json (design section 3).

    start_cloud / end_cloud / labels are kept for exports (PLY, pictures) and robot code.
    registration: how the views and the states were brought into one frame (per view: registered,
        how, inliers, residual, scale; per state alignment: method, inliers, rmse; see
        :func:`sparseart.align.scene.registration_report`); empty when unknown.
    cameras: state -> the :class:`Camera` of each frame (list position = ``frame_index`` of the
        clouds; None where a frame has none), for the surface fusion of the exports
        (:mod:`sparseart.sim.surfaces`); empty for clouds given without images.
    """

    frame_kind: str
    frame_reference: str
    units: str
    parts: list[PartResult]
    stages: list[StageRecord]
    warnings: list[str]
    start_cloud: LabelledCloud | None = None
    end_cloud: LabelledCloud | None = None
    labels: PartLabels | None = None
    registration: dict = field(default_factory=dict)
    cameras: dict[str, list[Camera | None]] = field(default_factory=dict)

    @property
    def joints(self) -> list[tuple[PartResult, JointEstimate]]:
        return [(p, p.joint) for p in self.parts if p.joint is not None]
