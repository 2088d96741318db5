"""Small parts slid along the static body's axes, sought after the motion layers without masks
(labelers/small_slides.py): a wire rack slid out of an open box is found with its slide; a
layer's fringe, a piece a layer's own motion explains, and a static shelf read as moved are not
parts."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial import cKDTree

from sparseart.labelers.motion_layers import MotionLayer
from sparseart.labelers.small_slides import small_slides

SPACING = 0.01
RADIUS = 0.03                 # inlier radius; the hit radius is half of it
SLIDE = np.array([-0.43, 0.0, 0.0])   # not a multiple of the wire pitch: cross wires land on gaps


def _grid(u: np.ndarray, v: np.ndarray, plane) -> np.ndarray:
    a, b = np.meshgrid(u, v, indexing="ij")
    return plane(a.ravel(), b.ravel())


def _box() -> np.ndarray:
    """The open box [0, 1]^3 without its x = 0 face (an oven with its door open), (N, 3)."""
    s = np.arange(0.0, 1.0 + 1e-9, 2 * SPACING)
    faces = [_grid(s, s, lambda a, b: np.stack([np.ones_like(a), a, b], axis=1)),
             _grid(s, s, lambda a, b: np.stack([a, np.zeros_like(a), b], axis=1)),
             _grid(s, s, lambda a, b: np.stack([a, np.ones_like(a), b], axis=1)),
             _grid(s, s, lambda a, b: np.stack([a, b, np.zeros_like(a)], axis=1)),
             _grid(s, s, lambda a, b: np.stack([a, b, np.ones_like(a)], axis=1))]
    return np.concatenate(faces)


def _rack(z: float = 0.5) -> np.ndarray:
    """A wire rack in the plane z: wires along x every 0.1 in y, cross wires every 0.1 in x that
    reach the box's side walls (its rails)."""
    along = np.arange(0.1, 0.9 + 1e-9, SPACING)
    across = np.arange(0.0, 1.0 + 1e-9, SPACING)
    pitch = np.arange(0.1, 0.9 + 1e-9, 0.1)
    wires = [np.stack([along, np.full_like(along, y), np.full_like(along, z)], axis=1) for y in pitch]
    wires += [np.stack([np.full_like(across, x), across, np.full_like(across, z)], axis=1) for x in pitch]
    return np.unique(np.round(np.concatenate(wires), 6), axis=0)


def _ratings(start: np.ndarray, end: np.ndarray, end_moved: np.ndarray, static: np.ndarray):
    """What small_slides reads of the motion layers' ratings, on plain clouds (no views)."""
    static_tree = cKDTree(start[static])
    context = SimpleNamespace(frame=np.eye(3), radius=RADIUS, diameter=2.0, start_views=[])
    return SimpleNamespace(context=context, start=SimpleNamespace(points=start), end=SimpleNamespace(points=end),
                           end_moved=end_moved, end_unseen=np.zeros(len(end_moved), dtype=bool),
                           radius=0.5 * RADIUS, start_all=cKDTree(start), end_all=cKDTree(end),
                           static_tree=lambda: static_tree)


def _scene(door_end=None, layer_motion=None):
    """Box + rack slid by SLIDE + a door layer: a plate far away (``door_end``: its end points
    instead; ``layer_motion``: its motion, else the plate's shift)."""
    box, rack = _box(), _rack()
    door = _grid(np.arange(0.0, 0.6, 2 * SPACING), np.arange(0.0, 0.6, 2 * SPACING),
                 lambda a, b: np.stack([np.full_like(a, -1.5), a, b], axis=1))
    if door_end is None:
        door_end = door + [0.0, 0.0, -1.0]
    start = np.concatenate([box, rack, door])
    end = np.concatenate([box, rack + SLIDE, door_end])
    n_box, n_rack = len(box), len(rack)
    moved = cKDTree(start).query(end[n_box:n_box + n_rack])[0] > 4 * SPACING
    end_moved = np.concatenate([n_box + np.flatnonzero(moved), np.arange(n_box + n_rack, len(end))])
    transform = np.eye(4)
    if layer_motion is not None:
        transform = layer_motion
    else:
        transform[2, 3] = -1.0
    layer = MotionLayer(transform, 0.0, np.arange(n_box + n_rack, len(start)), np.arange(n_box + n_rack, len(end)))
    return _ratings(start, end, end_moved, np.arange(n_box)), [layer], n_box, n_rack


def test_a_rack_slid_out_of_an_open_box_is_found_with_its_slide():
    ratings, layers, n_box, n_rack = _scene()
    found = small_slides(ratings, layers)
    assert len(found) == 1
    transform, partners, hits = found[0].transform, found[0].start, found[0].end
    assert np.allclose(transform[:3, 3], SLIDE, atol=ratings.radius)
    rack_start = np.arange(n_box, n_box + n_rack)
    assert np.isin(partners, rack_start).mean() > 0.9 and len(partners) > 100
    assert np.all((hits >= n_box) & (hits < n_box + n_rack))


def test_a_layers_fringe_is_no_part():
    """The door's end points a plate just under the rack's protruding end (within an inlier
    radius): those leftovers are the door layer's fringe, not a part."""
    plate = _grid(np.arange(-0.4, 0.0, SPACING), np.arange(0.0, 1.0, SPACING),
                  lambda a, b: np.stack([a, b, np.full_like(a, 0.5 - 0.5 * RADIUS)], axis=1))
    ratings, layers, _, _ = _scene(door_end=plate)
    assert small_slides(ratings, layers) == []


def test_a_piece_a_layers_motion_explains_is_that_layers():
    transform = np.eye(4)
    transform[:3, 3] = SLIDE
    ratings, layers, _, _ = _scene(layer_motion=transform)
    assert small_slides(ratings, layers) == []


def test_a_static_shelf_read_as_moved_is_no_part():
    """Two static shelves alike, 0.3 apart; the lower one's end points read as moved (a
    misregistered state). Slid up 0.3 they land on the upper shelf, but the upper shelf's places
    are still filled in the end: nothing left them."""
    box = _box()
    shelf = _grid(np.arange(0.1, 0.9, SPACING), np.arange(0.1, 0.9, SPACING),
                  lambda a, b: np.stack([a, b, np.full_like(a, 0.3)], axis=1))
    door = _grid(np.arange(0.0, 0.6, 2 * SPACING), np.arange(0.0, 0.6, 2 * SPACING),
                 lambda a, b: np.stack([np.full_like(a, -1.5), a, b], axis=1))
    start = np.concatenate([box, shelf, shelf + [0.0, 0.0, 0.3], door])
    end = np.concatenate([box, shelf, shelf + [0.0, 0.0, 0.3], door + [0.0, 0.0, -1.0]])
    n = len(box)
    end_moved = np.concatenate([np.arange(n, n + len(shelf)), np.arange(n + 2 * len(shelf), len(end))])
    ratings = _ratings(start, end, end_moved, np.arange(n))
    door_idx = np.arange(n + 2 * len(shelf), len(start))
    transform = np.eye(4)
    transform[2, 3] = -1.0
    assert small_slides(ratings, [MotionLayer(transform, 0.0, door_idx, door_idx)]) == []


def test_a_piece_away_from_the_static_body_is_no_slid_part():
    """The same rack floating clear of the box (no wire within two inlier radii of a wall): a
    slide's part sits in its slot, so this is no slid part (a fragment of a turning lid, carried
    by a slide onto another fragment of it, came out as a second part)."""
    ratings, layers, n_box, n_rack = _scene()
    ratings.static_tree = lambda: cKDTree(ratings.start.points[:n_box] + [0.0, 0.0, 3.0])
    assert small_slides(ratings, layers) == []


def test_no_search_where_the_states_disagree_where_nothing_moved():
    """The same scene with every end point of the box jittered by a third of an inlier radius
    (rough depth): a point far from the other state is no sign of motion there, and the search
    does not run (on robot-shaped renders it had made 46 parts of table and wall patches)."""
    ratings, layers, n_box, _ = _scene()
    jitter = np.random.default_rng(0).normal(0.0, RADIUS / 3.0, size=(n_box, 3))
    ratings.end.points = ratings.end.points.copy()
    ratings.end.points[:n_box] += jitter
    ratings.end_all = cKDTree(ratings.end.points)
    assert small_slides(ratings, layers) == []


def test_a_slide_another_length_lays_as_well_is_trusted_less():
    """The rack's wire grid is periodic: slid one pitch further (or four), its protruding end lands
    on the start rack as well, so the slide found has rivals laying as much and the labeler's trust
    in it drops to its floor; a slide without a rival keeps full trust."""
    from sparseart.labelers.small_slides import LEAST_TRUST, SlidPart

    ratings, layers, _, _ = _scene()
    (found,) = small_slides(ratings, layers)
    assert found.rival > 0.9 and found.trust() == LEAST_TRUST
    assert SlidPart(np.eye(4), np.arange(3), np.arange(3), rival=0.5).trust() == 1.0
    assert 0.3 < SlidPart(np.eye(4), np.arange(3), np.arange(3), rival=0.9).trust() < 1.0
