"""Label-generation kernels: each numba kernel agrees with its numpy twin, and both with hand-worked values."""

from __future__ import annotations

import numpy as np
from reference.labels_kernels import nearest_labels_reference, points_in_boxes_reference, vote_voxels_reference

from occdata.labels.kernels import NO_LABEL, majority, nearest_labels, points_in_boxes, vote_voxels


def _box(cx: float, cy: float, cz: float, yaw: float) -> np.ndarray:
    """`T_box_from_world` of a box centred at (cx, cy, cz) with heading `yaw`."""
    c, s = np.cos(yaw), np.sin(yaw)
    T_world_from_box = np.array([[c, -s, 0, cx], [s, c, 0, cy], [0, 0, 1, cz], [0, 0, 0, 1.0]])
    return np.linalg.inv(T_world_from_box)


def test_points_in_boxes_by_hand_and_twin() -> None:
    T = np.stack([_box(0, 0, 0, np.pi / 4), _box(10, 0, 1, 0.0)])
    half = np.array([[2.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    pts = np.array([
        [1.4, 1.4, 0.0],   # along the rotated length axis, 1.98 m from the centre: inside box 0
        [1.4, -1.4, 0.0],  # along the rotated width axis, 1.98 m > 1.0: outside
        [10.5, 0.5, 1.9],  # inside box 1
        [10.5, 0.5, 2.1],  # above box 1
        [11.0, 1.0, 2.0],  # on box 1's corner (closed volume): inside
    ])
    got = points_in_boxes(pts, T, half)
    assert got.tolist() == [0, -1, 1, -1, 1]
    rng = np.random.default_rng(0)
    many = rng.uniform(-3, 12, (5000, 3))
    np.testing.assert_array_equal(points_in_boxes(many, T, half), points_in_boxes_reference(many, T, half))


def test_overlapping_boxes_first_wins() -> None:
    T = np.stack([_box(0, 0, 0, 0.0), _box(0.5, 0, 0, 0.0)])
    half = np.ones((2, 3))
    pts = np.array([[0.8, 0, 0], [1.2, 0, 0]])
    assert points_in_boxes(pts, T, half).tolist() == [0, 1]
    assert points_in_boxes_reference(pts, T, half).tolist() == [0, 1]


def test_vote_majority_by_hand() -> None:
    shape = np.array([2, 2, 2])
    lower = np.zeros(3)
    # Voxel (0, 0, 0): classes 1, 2, 2 -> 2. Voxel (1, 1, 1): 3, 1 (tie) -> 1. One point outside; class 5
    # is skipped (>= 4 classes). Voxel (1, 0, 0) gets 3 in the first list and 2, 2 in the second -> 2.
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3], [1.5, 1.5, 1.5], [1.6, 1.6, 1.6],
                    [2.5, 0.1, 0.1], [0.5, 0.5, 1.5], [1.2, 0.1, 0.1]])
    cls = np.array([1, 2, 2, 3, 1, 1, 5, 3], np.uint8)
    first = vote_voxels(pts, cls, np.eye(4), lower, 1.0, shape, 4)
    assert sorted(first.tolist()) == sorted([1, 2, 2, 7 * 4 + 3, 7 * 4 + 1, 4 * 4 + 3])  # (flat, class) keys
    second = vote_voxels(np.array([[1.1, 0.2, 0.3], [1.9, 0.9, 0.9]]), np.array([2, 2], np.uint8), np.eye(4),
                         lower, 1.0, shape, 4)
    out = majority([first, second], (2, 2, 2), 4, 17)
    assert out[0, 0, 0] == 2 and out[1, 1, 1] == 1 and out[1, 0, 0] == 2
    assert (out == 17).sum() == 5


def test_vote_twin_agrees_with_a_transform() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(-5, 5, (20000, 3))
    cls = rng.integers(0, 20, len(pts)).astype(np.uint8)  # >= 17 skipped
    T = _box(0.3, -0.7, 0.2, 0.6)
    shape = np.array([20, 24, 8])
    lower = np.array([-4.0, -4.8, -1.6])
    a = vote_voxels(pts, cls, T, lower, 0.4, shape, 17)
    b = vote_voxels_reference(pts, cls, T, lower, 0.4, shape, 17)
    np.testing.assert_array_equal(a, b)
    assert len(a) > 1000
    # majority against a dense count table, argmax's first maximum (the lowest class on a tie)
    counts = np.zeros((int(shape.prod()), 17), np.int64)
    np.add.at(counts, (a // 17, a % 17), 1)
    dense = np.where(counts.max(1) > 0, counts.argmax(1), 17).reshape(tuple(shape))
    np.testing.assert_array_equal(majority([a[:5000], a[5000:]], tuple(shape), 17, 17), dense)


def test_nearest_labels_by_hand_and_twin() -> None:
    ref = np.array([[0.0, 0, 0], [1.0, 0, 0], [5.0, 5, 5]])
    cls = np.array([3, 4, 5], np.uint8)
    q = np.array([[0.4, 0, 0], [0.6, 0, 0], [5.0, 5.0, 5.49], [2.0, 0, 0], [0.5, 0, 0]])
    got = nearest_labels(q, ref, cls, 0.5)
    # 2.0 is 1.0 from its nearest: NO_LABEL; 0.5 is equally near both: the first reference wins.
    assert got.tolist() == [3, 4, 5, NO_LABEL, 3]
    rng = np.random.default_rng(2)
    ref = rng.uniform(-10, 10, (3000, 3))
    cls = rng.integers(0, 17, len(ref)).astype(np.uint8)
    q = rng.uniform(-11, 11, (2000, 3))
    for radius in (0.3, 1.0, 2.5):
        got = nearest_labels(q, ref, cls, radius)
        np.testing.assert_array_equal(got, nearest_labels_reference(q, ref, cls, radius))
    assert nearest_labels(q, ref[:0], cls[:0], 1.0).tolist() == [NO_LABEL] * len(q)
