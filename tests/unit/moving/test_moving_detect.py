"""Moving-object pipeline pieces: components vs flood fill, box fit, saliency, NMS, end to end."""

import itertools
import math
from collections import deque

import numpy as np
import pytest

from core.errors import ShapeError
from core.eval.iou3d import iou_3d
from core.geometry.grid import GridConfig
from core.moving.boxfit import fit_box_to_voxels, min_area_rectangle
from core.moving.components import component_indices, connected_components
from core.moving.detect_moving import detections_to_tensors, moving_objects_from_flow
from core.moving.nms import nms_bev
from core.moving.saliency import center_surround_score

GRID = GridConfig(xmin=-8, xmax=8, ymin=-2, ymax=2, zmin=0, zmax=16, Z=32, Y=8, X=32)  # 0.5 m voxels


def flood_fill_labels(mask, connectivity):
    """Slow reference: breadth-first flood fill with explicit neighbour offsets."""
    offsets = [d for d in itertools.product((-1, 0, 1), repeat=3)
               if any(d) and sum(map(abs, d)) <= {6: 1, 18: 2, 26: 3}[connectivity]]
    labels = np.zeros(mask.shape, dtype=int)
    count = 0
    for start in zip(*np.nonzero(mask)):
        if labels[start]:
            continue
        count += 1
        labels[start] = count
        queue = deque([start])
        while queue:
            p = queue.popleft()
            for d in offsets:
                q = tuple(a + b for a, b in zip(p, d))
                if all(0 <= c < s for c, s in zip(q, mask.shape)) and mask[q] and not labels[q]:
                    labels[q] = count
                    queue.append(q)
    return labels, count


@pytest.mark.parametrize("connectivity", [6, 18, 26])
def test_components_match_flood_fill(connectivity):
    rng = np.random.default_rng(connectivity)
    mask = rng.random((7, 6, 8)) < 0.3
    got, n = connected_components(mask, connectivity=connectivity)
    ref, m = flood_fill_labels(mask, connectivity)
    assert n == m
    # Same partition up to renaming: the label pairs are in one-to-one correspondence.
    pairs = set(zip(got[mask].tolist(), ref[mask].tolist()))
    assert len(pairs) == n and len({a for a, _ in pairs}) == n and len({b for _, b in pairs}) == n
    assert np.all((got == 0) == ~mask)
    for k, zyx in enumerate(component_indices(got, n), start=1):
        np.testing.assert_array_equal(zyx, np.argwhere(got == k))


def brute_force_min_area(points, steps=3600):
    """Slow reference: rectangle area at many orientations over [0, π/2)."""
    best = np.inf
    for a in np.arange(steps) * (math.pi / 2 / steps):
        u = np.array([math.cos(a), math.sin(a)])
        v = np.array([-u[1], u[0]])
        best = min(best, np.ptp(points @ u) * np.ptp(points @ v))
    return best


def test_min_area_rectangle_beats_brute_force_and_contains_points():
    rng = np.random.default_rng(3)
    for _ in range(5):
        pts = rng.normal(size=(40, 2)) * rng.uniform(0.3, 3, size=2) @ np.linalg.qr(rng.normal(size=(2, 2)))[0]
        centre, axis, extent = min_area_rectangle(pts)
        brute = brute_force_min_area(pts)
        assert extent[0] * extent[1] <= brute + 1e-9
        assert extent[0] * extent[1] >= brute * (1 - 1e-3)  # the sweep's grid is fine enough to get close
        perp = np.array([-axis[1], axis[0]])
        rel = pts - centre
        assert np.all(np.abs(rel @ axis) <= extent[0] / 2 + 1e-9)
        assert np.all(np.abs(rel @ perp) <= extent[1] / 2 + 1e-9)


def voxelise_box(box, grid):
    """Indices (z, y, x) of the voxels whose centres lie inside the canonical box."""
    zz, yy, xx = np.meshgrid(np.arange(grid.Z), np.arange(grid.Y), np.arange(grid.X), indexing="ij")
    centres = np.stack([xx, yy, zz], -1).reshape(-1, 3) * grid.voxel_size + np.array(grid.bounds_min) + grid.voxel_size / 2
    c, s = math.cos(box[6]), math.sin(box[6])
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    inside = np.all(np.abs((centres - box[:3]) @ R) <= box[3:6] / 2, axis=1)
    return np.stack([zz.ravel(), yy.ravel(), xx.ravel()], -1)[inside], inside.reshape(grid.Z, grid.Y, grid.X)


@pytest.mark.parametrize("yaw", [0.0, 0.4, -1.1, 1.5])
def test_box_fit_recovers_rotated_box_within_a_voxel(yaw):
    truth = np.array([1.3, 0.2, 8.1, 4.5, 1.6, 2.1, yaw])
    zyx, _ = voxelise_box(truth, GRID)
    fit = fit_box_to_voxels(zyx, GRID)
    v = GRID.voxel_size
    assert np.all(np.abs(fit[:3] - truth[:3]) <= v)
    assert np.all(np.abs(fit[3:6] - truth[3:6]) <= v)
    assert abs(math.remainder(fit[6] - yaw, math.pi)) < 0.25  # a box is the same under yaw + π
    assert iou_3d(fit[None], truth[None])[0, 0] > 0.6


def test_box_fit_puts_the_longer_side_first():
    truth = np.array([0.0, 0.0, 8.0, 2.0, 1.0, 5.0, 0.3])  # given width > length
    fit = fit_box_to_voxels(voxelise_box(truth, GRID)[0], GRID)
    assert fit[3] > fit[5] and -math.pi / 2 <= fit[6] < math.pi / 2
    assert iou_3d(fit[None], truth[None])[0, 0] > 0.6


def test_nms_keeps_the_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 5, 4, 2, 2, 0.0],
                      [0.3, 0, 5.1, 4, 2, 2, 0.1],   # overlaps box 0 heavily, higher score
                      [6, 0, 5, 4, 2, 2, 0.0],       # far away
                      [0, 0, 5, 4, 2, 2, 1.5]])      # crosses box 1 at a right angle: IoU ≈ 1/3
    scores = np.array([0.5, 0.9, 0.2, 0.4])
    assert nms_bev(boxes, scores, 0.5).tolist() == [1, 3, 2]
    assert nms_bev(boxes, scores, 0.2).tolist() == [1, 2]
    assert nms_bev(np.zeros((0, 7)), np.zeros(0), 0.5).tolist() == []


def test_center_surround_score_interior_moving_shell_static():
    box = np.array([0.0, 0.0, 8.0, 3.0, 1.5, 2.0, 0.5])
    _, inside = voxelise_box(box, GRID)
    occupied = np.ones(GRID.shape_zyx, dtype=bool)
    assert center_surround_score(inside, box, GRID, weight=occupied, shell_margin=1.0) == pytest.approx(1.0)
    assert center_surround_score(np.ones(GRID.shape_zyx), box, GRID, weight=occupied, shell_margin=1.0) == pytest.approx(0.0)
    assert center_surround_score(np.zeros(GRID.shape_zyx), box, GRID, shell_margin=1.0) == pytest.approx(0.0)


def scene_with_block(box):
    """Occupancy: a ground slab (bottom voxel row) plus the voxelised block."""
    _, block = voxelise_box(box, GRID)
    occupancy = block.astype(np.float32)
    occupancy[:, -1, :] = 1.0
    return block, occupancy


def surface_voxels(box, grid, step: float = 0.05):
    """Slow, obvious: the voxels that hold a point of the box's surface, sampled every `step` metres on
    each of its six faces (what voxels holding depth points of a whole object are)."""
    c, s = math.cos(box[6]), math.sin(box[6])
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    half = np.asarray(box[3:6]) / 2
    marked = np.zeros(grid.shape_zyx, dtype=bool)
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        u = np.arange(-half[others[0]], half[others[0]] + 1e-9, step)
        v = np.arange(-half[others[1]], half[others[1]] + 1e-9, step)
        for side in (-1.0, 1.0):
            for a in u:
                for b in v:
                    local = np.zeros(3)
                    local[axis], local[others[0]], local[others[1]] = side * half[axis], a, b
                    x, y, z = R @ local + box[:3]
                    ix, iy, iz = (int(math.floor((p - lo) / grid.voxel_size))
                                  for p, lo in zip((x, y, z), grid.bounds_min))
                    if 0 <= ix < grid.X and 0 <= iy < grid.Y and 0 <= iz < grid.Z:
                        marked[iz, iy, ix] = True
    return marked


@pytest.mark.parametrize("yaw", [0.0, 0.5, math.pi / 2])
def test_surface_voxels_take_their_centres_box_unpadded(yaw):
    """Flow predicted over voxels that hold depth points marks every voxel the surface passes through; their
    centres scatter ± half a voxel about it, so the unpadded box of centres fits the object and padding
    by one voxel (right for voxels whose centres lie inside) inflates it."""
    truth = np.array([-1.2, 0.6, 7.4, 4.0, 1.5, 2.0, yaw])
    surface = surface_voxels(truth, GRID)
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    flow[0][surface] = 1.0
    ious = {}
    for meaning in ("surface", "centres"):
        (found,) = moving_objects_from_flow(flow, surface.astype(np.float32), GRID, threshold=0.5, min_voxels=5,
                                            dt=0.1, moving_voxels=meaning)
        ious[meaning] = iou_3d(found["box_ref"][None], truth[None])[0, 0]
    assert ious["surface"] > 0.6 and ious["surface"] > ious["centres"] + 0.1, ious


def test_unknown_moving_voxel_meaning_is_named():
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    with pytest.raises(ValueError, match="moving_voxels"):
        moving_objects_from_flow(flow, None, GRID, threshold=0.5, min_voxels=5, dt=0.1, moving_voxels="inside")


def test_one_moving_rotated_block_gives_one_box_with_velocity():
    truth = np.array([-1.2, 0.6, 7.4, 4.0, 1.5, 2.0, 0.6])
    block, occupancy = scene_with_block(truth)
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    flow[0][block], flow[2][block] = 1.2, -0.6                      # voxels per step along x and z
    flow[:, ~occupancy.astype(bool)] = 0.3 * np.random.default_rng(0).standard_normal((3, int((occupancy == 0).sum())))
    found = moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1,
                                     moving_voxels="centres")
    assert len(found) == 1
    det = found[0]
    assert iou_3d(det["box_ref"][None], truth[None])[0, 0] > 0.6
    assert det["score"] == pytest.approx(1.0)
    np.testing.assert_allclose(det["velocity_ref"], [1.2 * 0.5 / 0.1, 0.0, -0.6 * 0.5 / 0.1], atol=1e-6)
    assert det["num_voxels"] == int(block.sum())
    packed = detections_to_tensors([found, []])
    assert packed["boxes"].shape == (2, 1, 7) and packed["valid"].tolist() == [[True], [False]]
    np.testing.assert_allclose(packed["velocities"][0, 0].numpy(), det["velocity_ref"], rtol=1e-6)


def test_zero_flow_finds_nothing_and_noise_below_threshold_is_ignored():
    _, occupancy = scene_with_block(np.array([0.0, 0.6, 8.0, 4.0, 1.5, 2.0, 0.2]))
    zero = np.zeros((3,) + GRID.shape_zyx)
    assert moving_objects_from_flow(zero, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1) == []
    small = 0.2 * np.ones((3,) + GRID.shape_zyx)  # magnitude 0.35 < 0.5 everywhere
    assert moving_objects_from_flow(small, None, GRID, threshold=0.5, min_voxels=5, dt=0.1) == []


def test_voxels_that_cannot_move_are_left_out_of_the_component():
    """The moving block sits on the ground slab, whose voxels the flow (wrongly) moves too: without
    `can_move` they join the block's component and its box reaches into the slab; with the slab
    excluded the box is the block's own."""
    truth = np.array([0.0, 0.6, 8.0, 4.0, 1.5, 2.0, 0.0])
    block, occupancy = scene_with_block(truth)
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    under = np.zeros_like(block)
    under[:, -1, :] = block.any(axis=1)           # the slab row right under the block
    flow[0][block | under] = 1.0
    (bleeding,) = moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1)
    can_move = np.ones(GRID.shape_zyx, dtype=bool)
    can_move[:, -1, :] = False
    (clean,) = moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1, can_move=can_move)
    assert clean["num_voxels"] == int(block.sum()) < bleeding["num_voxels"]
    assert iou_3d(clean["box_ref"][None], truth[None])[0, 0] > iou_3d(bleeding["box_ref"][None], truth[None])[0, 0]
    with pytest.raises(ShapeError, match="can_move"):
        moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1, can_move=can_move[:, :1])


def test_size_prior_splits_blocks_merged_end_to_end_and_completes_a_partial_one():
    """Two 4 m blocks bumper to bumper (one component) come out as two boxes with a size prior, one long
    box without; a block seen only in its near half grows back to its length away from the camera."""
    from core.moving.amodal import SizePrior

    prior = SizePrior.from_size(4.0, 2.0, 1.5)
    a, b = np.array([0.0, 0.6, 6.0, 4.0, 1.5, 2.0, math.pi / 2]), np.array([0.0, 0.6, 10.0, 4.0, 1.5, 2.0, math.pi / 2])
    block_a, occupancy = scene_with_block(a)
    block_b, _ = scene_with_block(b)
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    flow[2][block_a | block_b] = 1.0
    occupancy = np.maximum(occupancy, (block_a | block_b).astype(occupancy.dtype))
    (merged,) = moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1,
                                         moving_voxels="centres")
    assert merged["box_ref"][3] > 7.5                       # one 8 m box
    split = moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1, size_prior=prior,
                                     moving_voxels="centres", viewpoints=np.array([[0.0, -3.0, -4.0]]))
    assert len(split) == 2
    ious = iou_3d(np.stack([d["box_ref"] for d in split]), np.stack([a, b]))
    assert ious.max(axis=0).min() > 0.6                      # each block matched by a box

    # Only the near half (z < 6) of block a is seen moving; the camera is at z = −4, looking down +z.
    near = block_a.copy()
    centres_z = (np.arange(GRID.Z) + 0.5) * GRID.voxel_size + GRID.zmin
    near[centres_z >= 6.0] = False
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    flow[2][near] = 1.0
    (visible,) = moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1,
                                          moving_voxels="centres")
    (whole,) = moving_objects_from_flow(flow, occupancy, GRID, threshold=0.5, min_voxels=5, dt=0.1, size_prior=prior,
                                        moving_voxels="centres", viewpoints=np.array([[0.0, -3.0, -4.0]]))
    assert visible["box_ref"][3] < 2.5 and whole["box_ref"][3] == pytest.approx(4.0)
    assert iou_3d(whole["box_ref"][None], a[None])[0, 0] > 0.6 > iou_3d(visible["box_ref"][None], a[None])[0, 0]


def test_box_grows_away_from_the_camera_that_saw_the_component_not_the_nearest_one():
    """The near half (z < 6) of a 4 m block was seen by a camera at z = −4; a camera at z = 12 is nearer to
    those voxels but saw none of them. With `seen_by` the box grows to +z (away from the camera that saw
    it) and matches the block; by the nearest camera alone it would grow to −z."""
    from core.moving.amodal import SizePrior

    prior = SizePrior.from_size(4.0, 2.0, 1.5)
    truth = np.array([0.0, 0.6, 6.0, 4.0, 1.5, 2.0, math.pi / 2])
    block, occupancy = scene_with_block(truth)
    near = block.copy()
    centres_z = (np.arange(GRID.Z) + 0.5) * GRID.voxel_size + GRID.zmin
    near[centres_z >= 6.0] = False
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    flow[2][near] = 1.0
    views = np.array([[0.0, -3.0, -4.0], [0.0, -3.0, 12.0]])
    seen_by = np.stack([near, np.zeros_like(near)])                  # V×Z×Y×X: only camera 0 saw it
    kwargs = dict(threshold=0.5, min_voxels=5, dt=0.1, size_prior=prior, moving_voxels="centres", viewpoints=views)
    (nearest,) = moving_objects_from_flow(flow, occupancy, GRID, **kwargs)
    (seen,) = moving_objects_from_flow(flow, occupancy, GRID, seen_by=seen_by, **kwargs)
    assert seen["box_ref"][2] == pytest.approx(6.0, abs=0.3) and nearest["box_ref"][2] < 5.0
    assert iou_3d(seen["box_ref"][None], truth[None])[0, 0] > 0.6 > iou_3d(nearest["box_ref"][None], truth[None])[0, 0]
    with pytest.raises(ShapeError, match="seen_by"):
        moving_objects_from_flow(flow, occupancy, GRID, seen_by=seen_by[:1], **kwargs)


def hysteresis_reference(magnitude, occupied, low, high):
    """Slow, obvious: flood-fill the voxels above `low` outward from every voxel above `high`."""
    weak = (magnitude > low) & occupied
    labels, _ = flood_fill_labels(weak, 26)
    seeds = {int(labels[p]) for p in zip(*np.nonzero(weak & (magnitude > high)))}
    return np.isin(labels, sorted(seeds)) & weak


def test_hysteresis_keeps_weak_voxels_connected_to_a_strong_one_and_nothing_else():
    """A block whose flow is above the threshold in its front half only, one below it everywhere, and
    random magnitudes: the moving voxels are the flood fill from the strong voxels through the weak ones."""
    truth = np.array([-1.2, 0.6, 7.4, 4.0, 1.5, 2.0, 0.6])
    block, occupancy = scene_with_block(truth)
    centres_z = (np.arange(GRID.Z) + 0.5) * GRID.voxel_size + GRID.zmin
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    flow[2][block] = 0.3                                        # weak: above 0.5 × 0.5, below the threshold
    front = block & (centres_z < 7.4)[:, None, None]
    flow[2][front] = 0.8                                        # strong
    other = np.array([4.0, 0.6, 12.0, 2.0, 1.5, 2.0, 0.0])
    lonely, _ = scene_with_block(other)                         # weak everywhere: never seeded
    flow[2][lonely] = 0.3
    occupancy = np.maximum(occupancy, lonely.astype(occupancy.dtype))
    kwargs = dict(threshold=0.5, min_voxels=5, dt=0.1, moving_voxels="centres")
    (with_h,) = moving_objects_from_flow(flow, occupancy, GRID, hysteresis=0.5, **kwargs)
    (without,) = moving_objects_from_flow(flow, occupancy, GRID, hysteresis=1.0, **kwargs)
    assert with_h["num_voxels"] == int(block.sum()) and without["num_voxels"] == int(front.sum())
    assert iou_3d(with_h["box_ref"][None], truth[None])[0, 0] > iou_3d(without["box_ref"][None], truth[None])[0, 0]



@pytest.mark.parametrize("hysteresis", [0.3, 0.6, 1.0])
def test_moving_mask_is_the_flood_fill_from_the_strong_voxels(hysteresis):
    from core.moving.detect_moving import moving_mask

    rng = np.random.default_rng(1)
    magnitude = rng.random((9, 6, 10))
    candidates = rng.random((9, 6, 10)) < 0.6
    got = moving_mask(magnitude, candidates, threshold=0.9, hysteresis=hysteresis)
    expected = hysteresis_reference(magnitude, candidates, hysteresis * 0.9, 0.9)
    np.testing.assert_array_equal(got, expected)
    assert expected.sum() > ((magnitude > 0.9) & candidates).sum() or hysteresis == 1.0


def test_hysteresis_outside_zero_one_is_refused():
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    with pytest.raises(ValueError, match="hysteresis"):
        moving_objects_from_flow(flow, None, GRID, threshold=0.5, min_voxels=5, dt=0.1, hysteresis=0.0)


def test_a_one_layer_surface_gives_a_box_one_voxel_thick_not_flat():
    """Surface voxels in a single horizontal layer (a roof seen from above) have centres spanning 0 m
    vertically; unpadded, that box would be flat. It is one voxel thick, with or without a size prior."""
    from core.moving.amodal import SizePrior

    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    layer = np.zeros(GRID.shape_zyx, dtype=bool)
    layer[10:18, 3, 12:16] = True                                   # 4 m × 2 m, one voxel layer (y index 3)
    flow[0][layer] = 1.0
    kwargs = dict(threshold=0.5, min_voxels=5, dt=0.1, moving_voxels="surface")
    (visible,) = moving_objects_from_flow(flow, layer.astype(np.float32), GRID, **kwargs)
    (whole,) = moving_objects_from_flow(flow, layer.astype(np.float32), GRID,
                                        size_prior=SizePrior.from_size(4.0, 2.0, 1.5), **kwargs)
    assert visible["box_ref"][4] == pytest.approx(GRID.voxel_size)
    assert visible["box_ref"][3] == pytest.approx(3.5) and visible["box_ref"][5] == pytest.approx(1.5)
    assert whole["box_ref"][4] >= GRID.voxel_size - 1e-9


def test_a_component_slower_than_the_object_threshold_as_a_whole_is_dropped():
    """Two blocks whose voxels all pass the voxel threshold: one moves at 0.6 voxels per step, the other
    at 0.3 (its mean under object_threshold 0.4): only the first is a moving object."""
    fast_box, slow_box = np.array([-4.0, 0.6, 6.0, 2.0, 1.5, 2.0, 0.0]), np.array([4.0, 0.6, 10.0, 2.0, 1.5, 2.0, 0.0])
    fast, occupancy = scene_with_block(fast_box)
    slow, _ = scene_with_block(slow_box)
    flow = np.zeros((3,) + GRID.shape_zyx, dtype=np.float32)
    flow[0][fast], flow[0][slow] = 0.6, 0.3
    occupancy = np.maximum(occupancy, slow.astype(occupancy.dtype))
    kwargs = dict(threshold=0.25, min_voxels=5, dt=0.1, moving_voxels="centres")
    assert len(moving_objects_from_flow(flow, occupancy, GRID, object_threshold=0.0, **kwargs)) == 2
    (only,) = moving_objects_from_flow(flow, occupancy, GRID, object_threshold=0.4, **kwargs)
    assert only["box_ref"][0] == pytest.approx(-4.0, abs=0.3)
