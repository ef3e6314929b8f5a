"""Classes from 2D masks and ground from geometry (`occdata labels --image-masks`, the flat class): the
kernels against their numpy twins, hand-worked occlusion and votes, the mask files' validation."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from reference.labels_paint import depth_buffer_reference, visible_reference

from occdata.errors import OccDataError
from occdata.formats.imagemasks import IGNORE, MaskClasses, load_mask_classes, mask_path, read_mask
from occdata.labels.flat import SceneGround, fill_flat, fold_votes, on_ground, tiered_majority, uncover
from occdata.labels.heights import GroundMap, HeightOffsets
from occdata.labels.kernels import NO_LABEL, vote_voxels
from occdata.labels.paint import ImageMasks, depth_buffer, paint_camera, visible_points

N = 17  # Occ3D's semantic classes
FREE = 17


# ------------------------------------------------------------------------------------------------
# numba == numpy twin
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("seed", "radius"), [(0, 0), (1, 1), (2, 2)])
def test_paint_kernels_match_twins(seed: int, radius: int) -> None:
    rng = np.random.default_rng(seed)
    n_u, n_v, n = 13, 9, 400
    cu, cv = rng.integers(0, n_u, n), rng.integers(0, n_v, n)
    depth = rng.uniform(1.0, 40.0, n)
    buf = depth_buffer(cu, cv, depth, n_u, n_v)
    ref = depth_buffer_reference(cu, cv, depth, n_u, n_v)
    np.testing.assert_array_equal(buf, ref)
    assert np.isinf(buf).any() or n >= n_u * n_v  # some cells are empty or all are filled
    got = visible_points(cu, cv, depth, buf, radius, 0.3, 0.05)
    np.testing.assert_array_equal(got, visible_reference(cu, cv, depth, buf, radius, 0.3, 0.05))
    assert got.any() and not got.all()


# ------------------------------------------------------------------------------------------------
# hand-worked occlusion: camera at the origin looking along +z, f = 100 px, 200 x 100 image
# ------------------------------------------------------------------------------------------------
K = np.array([[100.0, 0.0, 99.5], [0.0, 100.0, 49.5], [0.0, 0.0, 1.0]])


def _mask() -> np.ndarray:
    mask = np.full((100, 200), 15, np.uint8)  # manmade everywhere ...
    mask[:, 150:] = IGNORE  # ... but the right quarter, whose id maps to no class
    return mask


def test_point_behind_a_wall_casts_no_vote() -> None:
    # A wall at z = 5 m across x in [-1, 1] (pixels 80..119), a 10 cm grid of its points; one point behind
    # it at z = 10 (pixel 99.5 + 100 * 0.2 / 10 = 101.5 -> 102), one beside it at x = 3, z = 10 (pixel 129.5).
    xs = np.arange(-1.0, 1.01, 0.1)
    ys = np.arange(-0.5, 0.51, 0.1)
    wall = np.array([[x, y, 5.0] for x in xs for y in ys])
    behind, beside, right = [0.2, 0.0, 10.0], [3.0, 0.0, 10.0], [8.0, 0.0, 10.0]
    pts = np.vstack([wall, [behind, beside, right, [0.0, 0.0, -3.0]]])
    cls = paint_camera(pts, K, _mask(), ImageMasks(Path(".")))
    assert (cls[: len(wall)] == 15).all()  # the wall is the visible surface
    assert cls[len(wall)] == NO_LABEL  # hidden by the wall: 5 m deeper than its neighbourhood
    assert cls[len(wall) + 1] == 15  # beside the wall: nothing nearer around pixel 130
    assert cls[len(wall) + 2] == NO_LABEL  # pixel 179.5: an ignored id
    assert cls[len(wall) + 3] == NO_LABEL  # behind the camera


def test_tolerance_keeps_a_slanted_surface() -> None:
    # Two points 0.2 m apart in depth in one cell: both within 0.3 m + 5 % of the nearer one.
    pts = np.array([[0.0, 0.0, 10.0], [0.01, 0.0, 10.2], [0.02, 0.0, 11.0]])
    cls = paint_camera(pts, K, _mask(), ImageMasks(Path(".")))
    assert cls.tolist() == [15, 15, NO_LABEL]  # 11.0 > 10 + 0.3 + 0.5


# ------------------------------------------------------------------------------------------------
# the two-tier vote, ties stated
# ------------------------------------------------------------------------------------------------
def _keys(voxel: int, classes: list[int], n: int) -> np.ndarray:
    return np.array([voxel * n + c for c in classes], np.int64)


def test_tiered_majority_by_hand() -> None:
    shape = (1, 1, 4)
    votes = [
        _keys(0, [4, 4, 7, 7], 2 * N),  # tier-1 tie 4 : 7 -> the lower class, 4
        _keys(1, [16, N + 0, N + 0, N + 0], 2 * N),  # one mask vote beats three geometric ones
        _keys(2, [N + 11, N + 11, N + 11, N + 0], 2 * N),  # geometry alone: flat 3 : others 1
    ]
    sem, by_geometry = tiered_majority(votes, shape, N, FREE)
    assert sem[0, 0].tolist() == [4, 16, 11, FREE]
    assert by_geometry[0, 0].tolist() == [False, False, True, False]
    folded = np.concatenate(fold_votes(votes, N))
    assert sorted((folded % N).tolist()) == sorted([4, 4, 7, 7, 16, 0, 0, 0, 11, 11, 11, 0])
    assert (folded // N).tolist() == [0] * 4 + [1] * 4 + [2] * 4


def test_uncover_gives_a_walls_foot_its_class() -> None:
    # Columns of 4 voxels; something covers a flat voxel when the 2 voxels above it are not flat.
    # Column 0: flat at z0 under a wall (15) at z1-z2; its own votes 11 x3, 0 x1, 16 x1: the other votes
    #   tie 0 : 16 -> the lower class, 0 (not the wall above: its own points decide).
    # Column 1: flat at z0 under a car (4) at z1-z2, no other votes in z0 -> the class above, 4.
    # Column 2: flat at z0, free above -> stays flat. Column 3: flat under flat -> stays.
    # Column 4: flat at z0 and z1 under a pole (15) at z2-z3, no other votes -> 15 from the top down.
    # Column 5: flat at z0 under one voxel of others (ground noise), free above it -> stays flat.
    sem = np.full((6, 1, 4), FREE, np.uint8)
    sem[:, 0, 0] = 11
    sem[0, 0, 1:3], sem[1, 0, 1:3], sem[3, 0, 1] = 15, 4, 11
    sem[4, 0, 1], sem[4, 0, 2:4] = 11, 15
    sem[5, 0, 1] = 0

    def key(i: int, k: int, c: int) -> int:
        return (i * 4 + k) * N + c

    votes = [np.array([key(0, 0, 11)] * 3 + [key(0, 0, 0), key(0, 0, 16), key(1, 0, 11)], np.int64)]
    out = uncover(sem, votes, N, 11, FREE)
    assert out[:, 0, 0].tolist() == [0, 4, 11, 11, 15, 11]
    assert out[4, 0].tolist() == [15, 15, 15, 15]
    assert (np.delete(out, 4, axis=0)[:, 0, 1:] == np.delete(sem, 4, axis=0)[:, 0, 1:]).all()


def test_on_ground() -> None:
    # One 0.5 m column at x, y in [0, 0.5) with ground at z = 0.1, its 2 m column at 0.3; a slot 0.05 m
    # too high at t = 0. The 2 m map stands in where the 0.5 m one saw nothing (x = 1.2).
    fine = GroundMap(np.array([0], np.int64), np.array([0.1]), 0.5)
    coarse = GroundMap(np.array([0], np.int64), np.array([0.3]), 2.0)
    heights = HeightOffsets(np.array([0, 1_000_000], np.int64), np.array([0.05, 0.05]))
    ground = SceneGround(heights, fine, coarse)
    pts = np.array([[0.2, 0.2, 0.2], [0.2, 0.2, 0.4], [0.2, 0.2, 0.3], [1.2, 1.2, 0.4], [3.0, 3.0, 0.1]])
    # aligned heights over the ground: 0.05, 0.25, 0.15 (0.5 m map), 0.05 (2 m map), no ground seen
    assert on_ground(pts, 0, ground, 0.2).tolist() == [True, False, True, True, False]


def test_scene_ground_fit() -> None:
    # Two slots seeing a plane at z = 0 (the second 0.1 m too high) and a wall from z = 0 to 3 m at
    # x = 10: every column's ground is the plane's height once the slot's error is taken off.
    xs, ys = np.meshgrid(np.arange(0.05, 12.0, 0.25), np.arange(0.05, 4.0, 0.25))
    plane = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    wall = np.array([[10.05, y, z] for y in np.arange(0.05, 4.0, 0.25) for z in np.arange(0.0, 3.0, 0.1)])
    pts = np.vstack([plane, wall])
    shifted = pts + [0.0, 0.0, 0.1]
    heights = HeightOffsets(np.array([0, 500_000], np.int64), np.array([0.0, 0.1]))
    ground = SceneGround.fit([(np.zeros(3), pts, 0), (np.zeros(3), shifted, 500_000)], heights)
    z = ground.height_under(pts)
    # The wall's columns too: their lowest surface is its foot (the mean of z = 0, 0.1, 0.2 and the plane).
    assert np.abs(z[: len(plane)][plane[:, 0] < 9.9]).max() < 1e-9 and np.abs(z).max() < 0.1
    # The wall's foot (z = 0, 0.1, 0.2) is within 0.2 m of it: flat points (`uncover` gives its voxel back).
    assert on_ground(wall, 0, ground, 0.2).sum() == 3 * len(np.arange(0.05, 4.0, 0.25))


def test_vote_voxels_carries_tier_two_classes() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.1, 0.1, 0.1]])
    keys = vote_voxels(pts, np.array([N + 11, 4], np.uint8), np.eye(4), np.zeros(3), 0.4,
                       np.array([1, 1, 1], np.int64), 2 * N)
    sem, _ = tiered_majority([keys], (1, 1, 1), N, FREE)
    assert sem.item() == 4


# ------------------------------------------------------------------------------------------------
# mask files
# ------------------------------------------------------------------------------------------------
def test_mask_path_layout() -> None:
    got = mask_path(Path("/m"), "samples/CAM_FRONT/x.jpg")
    assert got == Path("/m/samples/CAM_FRONT/x.png")


def test_mask_classes_mapping_and_errors(tmp_path: Path) -> None:
    good = tmp_path / "classes.json"
    good.write_text(json.dumps({"0": "driveable_surface", "7": "car", "9": "ignore"}))
    lut = load_mask_classes(good).lut
    assert (lut[0], lut[7], lut[9], lut[3]) == (11, 4, IGNORE, IGNORE)
    assert MaskClasses.occ3d().lut[:18].tolist() == [*range(17), IGNORE]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"1": "road"}))
    with pytest.raises(OccDataError, match="unknown class 'road'"):
        load_mask_classes(bad)
    bad.write_text(json.dumps({"300": "car"}))
    with pytest.raises(OccDataError, match="not an integer 0..255"):
        load_mask_classes(bad)
    bad.write_text("[1, 2]")
    with pytest.raises(OccDataError, match="expected a JSON object"):
        load_mask_classes(bad)


def test_read_mask_errors(tmp_path: Path) -> None:
    path = tmp_path / "m.png"
    with pytest.raises(OccDataError, match="is missing"):
        read_mask(path, 8, 4, MaskClasses.occ3d())
    cv2.imwrite(str(path), np.full((4, 8), 16, np.uint8))
    assert (read_mask(path, 8, 4, MaskClasses.occ3d()) == 16).all()
    with pytest.raises(OccDataError, match="is 8x4, its image 16x4"):
        read_mask(path, 16, 4, MaskClasses.occ3d())
    cv2.imwrite(str(path), np.zeros((4, 8, 3), np.uint8))
    with pytest.raises(OccDataError, match="single-channel"):
        read_mask(path, 8, 4, MaskClasses.occ3d())


def test_fill_flat_takes_the_masks_ground_next_to_it() -> None:
    # Layer z1 of a 7 x 1 strip: x0-x1 painted sidewalk (13), x2 painted road (11), x3-x6 flat by geometry
    # (11). Within 2 voxels: x3 sees 13 x1 (x1), 11 x1 (x2) -> tie to the lower class, 11; x4 sees only
    # x2's 11 -> 11; x5, x6 see no painted voxel -> stay. A geometric non-flat voxel is never touched.
    sem = np.full((7, 1, 3), FREE, np.uint8)
    sem[:, 0, 1] = [13, 13, 11, 11, 11, 11, 11]
    by_geometry = np.zeros(sem.shape, bool)
    by_geometry[3:, 0, 1] = True
    out = fill_flat(sem, by_geometry, 11)
    assert out[:, 0, 1].tolist() == [13, 13, 11, 11, 11, 11, 11]
    sem[2, 0, 1] = 13  # now x3 sees 13 x2, x4 sees 13 x1 (x2), x5 none
    out = fill_flat(sem, by_geometry, 11)
    assert out[:, 0, 1].tolist() == [13, 13, 13, 13, 13, 11, 11]
    sem[6, 0, 0] = 14  # one layer down counts too: x6 now sees painted terrain below it (and x5 too)
    sem[4, 0, 2] = 0  # a geometric `others` voxel is never touched
    by_geometry[4, 0, 2] = True
    out = fill_flat(sem, by_geometry, 11)
    assert out[:, 0, 1].tolist() == [13, 13, 13, 13, 13, 14, 14] and out[4, 0, 2] == 0


# ------------------------------------------------------------------------------------------------
# end to end: a small synthetic world with its truth masks, lidarseg dropped
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """1 scene x 3 keyframes at 192x108 with its image masks beside it, its lidarseg table removed."""
    from occdata.synth import SynthConfig, synthesize

    folder = tmp_path_factory.mktemp("paint")
    root = synthesize(SynthConfig(out=folder / "world", scenes=1, samples=3, seed=5, width=192, height=108,
                                  progress=False, image_masks=folder / "masks"))
    (root / "v1.0-mini" / "lidarseg.json").unlink()
    return root


def _masks(world: Path) -> Path:
    """The world's masks (`synth --image-masks`: written beside it)."""
    return world.parent / "masks"


def _labels(root: Path, out: Path, *extra: str) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
    from click.testing import CliRunner

    from cli.occdata_cli import main

    r = CliRunner().invoke(main, ["labels", "--root", str(root), "--out", str(out), "--no-progress", "--workers", "1",
                                  *extra])
    assert r.exit_code == 0, r.output
    from occdata.nuscenes import load_nuscenes

    gen, truth = [], []
    for s in load_nuscenes(root, None).samples:
        with np.load(out / s.scene_name / s.token / "labels.npz", allow_pickle=False) as z:
            gen.append(z["semantics"])
        with np.load(root / "gts" / s.scene_name / s.token / "labels.npz", allow_pickle=False) as z:
            truth.append(z["semantics"])
    return gen, truth, json.loads((out / "labels.json").read_text())


def _accuracy(gen: list[np.ndarray], truth: list[np.ndarray]) -> float:
    both = [(g != FREE) & (t != FREE) for g, t in zip(gen, truth, strict=True)]
    same = sum(int((b & (g == t)).sum()) for b, g, t in zip(both, gen, truth, strict=True))
    return same / sum(int(b.sum()) for b in both)


@pytest.mark.slow
def test_masks_and_ground_on_a_synthetic_world(world: Path, tmp_path: Path) -> None:
    plain, truth, _ = _labels(world, tmp_path / "plain", "--ground-class", "0")
    ground, _, meta_g = _labels(world, tmp_path / "ground")
    painted, _, meta_p = _labels(world, tmp_path / "masks", "--image-masks", str(_masks(world)))
    flat = [np.isin(t, [11, 12, 13, 14]) & (g != FREE) for g, t in zip(ground, truth, strict=True)]
    found = sum(int((f & np.isin(g, [11])).sum()) for f, g in zip(flat, ground, strict=True))
    assert found / sum(int(f.sum()) for f in flat) > 0.85  # the ground from geometry alone
    # The box path's old labels: the boxes' categories (1-10), every other point `others`.
    assert set(np.unique(np.concatenate([p.ravel() for p in plain])).tolist()) <= {*range(11), FREE}
    assert _accuracy(painted, truth) > 0.85 > 0.5 > _accuracy(ground, truth) > _accuracy(plain, truth)
    assert {13, 15, 16} <= set(np.unique(np.concatenate([p.ravel() for p in painted])).tolist())
    assert meta_g["options"]["ground_class"] == 11 and "flat ground" in meta_g["classes"]
    assert meta_p["options"]["image_masks"]["classes"] == "Occ3D ids" and "image masks" in meta_p["classes"]


def test_image_mask_errors_are_one_line(world: Path, tmp_path: Path) -> None:
    from click.testing import CliRunner

    from cli.occdata_cli import main

    masks = tmp_path / "masks"
    shutil.copytree(_masks(world), masks)
    victim = sorted(masks.rglob("*.png"))[0]
    victim.unlink()
    r = CliRunner().invoke(main, ["labels", "--root", str(world), "--out", str(tmp_path / "a"), "--no-progress",
                                  "--workers", "1", "--image-masks", str(masks)])
    assert r.exit_code != 0 and f"image mask {victim} is missing" in r.output and "Traceback" not in r.output
    table = tmp_path / "classes.json"
    table.write_text(json.dumps({"3": "lorry"}))
    r = CliRunner().invoke(main, ["labels", "--root", str(world), "--out", str(tmp_path / "b"), "--no-progress",
                                  "--image-masks", str(_masks(world)), "--mask-classes", str(table)])
    assert r.exit_code != 0 and "unknown class 'lorry'" in r.output and "Traceback" not in r.output


def test_one_badly_aligned_slot_does_not_sink_the_ground() -> None:
    # Three slots see a plane at z = 0; the third one 0.4 m too low, its height error unknown (0). The
    # median of the three per column is the plane; carving's lowest surface would be -0.4 m.
    xs, ys = np.meshgrid(np.arange(0.05, 6.0, 0.25), np.arange(0.05, 6.0, 0.25))
    plane = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    heights = HeightOffsets(np.array([0, 1, 2], np.int64), np.zeros(3))
    slots = [(np.zeros(3), plane, 0), (np.zeros(3), plane, 1), (np.zeros(3), plane - [0.0, 0.0, 0.4], 2)]
    ground = SceneGround.fit(slots, heights)
    assert np.abs(ground.height_under(plane)).max() < 1e-9
    assert on_ground(plane + [0.0, 0.0, 0.1], 0, ground, 0.2).all()
