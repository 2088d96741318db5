"""Rigid registration is a pure function of its input (issue 18, determinism): open3d's threaded
reductions change ICP results in the last bits from call to call unless open3d runs on one thread
(sparseart.geometry.o3d.serial)."""
from __future__ import annotations

import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sparseart.geometry.icp import _o3d_cloud, icp_polish, register_rigid, tukey_icp
from sparseart.geometry.o3d import open3d, serial
from sparseart.parallel import in_parallel


def _pair(seed: int = 1, n: int = 2000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An anisotropic blob and a rotated, shifted, noisy copy ((N, 3) float64 each) and the true
    (4, 4) source -> target."""
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(n, 3)) * [1.0, 0.6, 0.3]
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_rotvec([0.2, 0.1, -0.3]).as_matrix()
    truth[:3, 3] = [0.1, 0.2, 0.0]
    target = source @ truth[:3, :3].T + truth[:3, 3] + rng.normal(scale=0.01, size=source.shape)
    return source, target, truth


def test_serial_limits_open3d_to_one_thread_and_restores_the_limit():
    o3d = open3d()
    before = o3d.utility.get_max_threads()
    with serial():
        assert o3d.utility.get_max_threads() == 1
        with serial():
            assert o3d.utility.get_max_threads() == 1
        assert o3d.utility.get_max_threads() == 1
    assert o3d.utility.get_max_threads() == before


def test_tukey_icp_gives_bit_identical_transforms():
    """Unpinned, 2 TBB threads gave 11-46 distinct results in 40-60 calls on this input."""
    source, target, truth = _pair()
    source_cloud, target_cloud = _o3d_cloud(source), _o3d_cloud(target, radius=0.2)
    results = [tukey_icp(source_cloud, target_cloud, np.eye(4), (0.5, 0.2, 0.05)) for _ in range(20)]
    assert len({r.tobytes() for r in results}) == 1
    assert np.abs(results[0] - truth).max() < 0.01
    polished = {icp_polish(source, target, results[0], 0.05).tobytes() for _ in range(5)}
    assert len(polished) == 1


def test_register_rigid_with_features_and_colours_is_reproducible():
    """All hypotheses, the FPFH + RANSAC one (forced) and the coloured polish: same input, same
    transform and correspondences, bit for bit."""
    source, target, truth = _pair(seed=2, n=1500)
    colours = np.clip(0.5 + 0.3 * source / np.abs(source).max(axis=0), 0.0, 1.0)
    runs = [register_rigid(source, target, colours, colours, fpfh_below=1.01, seed=3) for _ in range(3)]
    assert "fpfh" in [h["name"] for h in runs[0].diagnostics["hypotheses"]]
    assert len({r.transform.tobytes() for r in runs}) == 1
    assert len({r.correspondences.tobytes() for r in runs}) == 1
    assert np.abs(runs[0].transform - truth).max() < 0.02


def test_register_rigid_gives_the_same_bits_with_threads_as_without(monkeypatch):
    """The hypotheses refined side by side (sparseart.parallel) give what a sequential run gives."""
    import sparseart.parallel as parallel

    source, target, _ = _pair(seed=4, n=1500)
    colours = np.clip(0.5 + 0.3 * source / np.abs(source).max(axis=0), 0.0, 1.0)
    runs = {}
    for threads in (1, 4):
        monkeypatch.setattr(parallel, "PARALLEL_THREADS", threads)
        result = register_rigid(source, target, colours, colours, fpfh_below=1.01, seed=5)
        runs[threads] = (result.transform.tobytes(), result.correspondences.tobytes(),
                         [(h["name"], h["inlier_fraction"], h["rmse"]) for h in result.diagnostics["hypotheses"]])
    assert runs[1] == runs[4]


def test_serial_holds_one_thread_while_any_thread_is_inside():
    """Threads entering and leaving serial() in any order: open3d stays on one thread until the
    last one leaves, then gets its limit back (a thread leaving first must not lift it)."""
    o3d = open3d()
    before = o3d.utility.get_max_threads()
    inside, leave_first, seen = threading.Barrier(2), threading.Event(), []

    def first():
        with serial():
            inside.wait()
        leave_first.set()

    def second():
        with serial():
            inside.wait()
            leave_first.wait()
            seen.append(o3d.utility.get_max_threads())

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen == [1]
    assert o3d.utility.get_max_threads() == before


def test_in_parallel_keeps_the_order_and_raises_the_first_error():
    assert in_parallel(lambda x: x * x, range(20)) == [x * x for x in range(20)]

    def boom(x):
        if x == 3:
            raise ValueError("three")
        return x

    with pytest.raises(ValueError, match="three"):
        in_parallel(boom, range(8))


def test_the_fpfh_ransac_gives_the_same_transform_from_threads_as_alone():
    """open3d's generator is process-wide: without one call at a time, RANSACs run side by side
    in threads (the labeler's pair registrations do) drew from each other's sequence and 4-8 of
    16 gave another transform than the same call alone."""
    from concurrent.futures import ThreadPoolExecutor

    from sparseart.geometry.icp import _fpfh_hypothesis

    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (3000, 3)) * [1.0, 0.6, 0.3]
    points = points[np.abs(points[:, 2]) > 0.2]                 # two slabs
    turn = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    moved = points @ turn.T + 0.1 + rng.normal(0, 0.01, points.shape)
    source, target = _o3d_cloud(points, radius=0.2), _o3d_cloud(moved, radius=0.2)
    alone = _fpfh_hypothesis(source, target, 0.05, 0)
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda _: _fpfh_hypothesis(source, target, 0.05, 0), range(16)))
    assert all(np.array_equal(t, alone) for t in together)
