"""Amodal boxes on hand-built partial surfaces: a known box, the faces a camera sees of it, voxelised
(the voxels the surface passes through: pad 0, core.moving.amodal rule 2); the amodal fit must recover
the box (3D IoU) where the visible fit cannot. The slow reference is the
surface built face by face with an explicit visibility test, and the known box itself."""

import math

import numpy as np
import pytest

from core.eval.iou3d import iou_3d
from core.moving.amodal import SizePrior, amodal_box, estimate_size_prior, split_oversized, visible_box

VOXEL = 0.25
CAR = (4.4, 1.6, 1.8)     # length, height, width (lx, ly, lz)


def visible_surface(box, viewpoint, *, voxel=VOXEL, step=0.05):
    """Voxel centres (M×3) of the faces of canonical `box` that face `viewpoint`, bottom excluded: each
    face sampled on a fine lattice, kept when its outward normal points at the camera."""
    x, y, z, lx, ly, lz, yaw = box
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])         # object -> frame
    half = np.array([lx, ly, lz]) / 2
    points = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            if axis == 1 and sign > 0:
                continue                                   # the bottom (+y) sits on the ground: never seen
            normal_obj = np.zeros(3)
            normal_obj[axis] = sign
            face_centre = np.array([x, y, z]) + R @ (normal_obj * half)
            if (R @ normal_obj) @ (np.asarray(viewpoint) - face_centre) <= 0:
                continue
            others = [a for a in range(3) if a != axis]
            u = np.arange(-half[others[0]], half[others[0]] + 1e-9, step)
            v = np.arange(-half[others[1]], half[others[1]] + 1e-9, step)
            uu, vv = np.meshgrid(u, v, indexing="ij")
            local = np.zeros((uu.size, 3))
            local[:, axis] = sign * half[axis]
            local[:, others[0]] = uu.ravel()
            local[:, others[1]] = vv.ravel()
            points.append(local @ R.T + np.array([x, y, z]))
    pts = np.concatenate(points)
    return np.unique(np.floor(pts / voxel), axis=0) * voxel + voxel / 2


def car(x=2.0, z=12.0, yaw=0.3):
    return np.array([x, 0.0, z, CAR[0], CAR[1], CAR[2], yaw])


PRIOR = SizePrior.from_size(CAR[0], CAR[2], CAR[1])


# Cameras at the car's mid-height (y = 0.3; its top is at −0.8) see no top face: only the vertical faces
# toward them. The car (yaw 0.3) has its length along (0.955, −0.296) and its width along (0.296, 0.955)
# in (x, z).
@pytest.mark.parametrize("viewpoint, name", [
    ((-7.55, 0.3, 14.96), "rear only"),     # 10 m behind it along its length: one short face
    ((-0.96, 0.3, 2.45), "side"),           # 10 m beside it: one long face
    ((-6.76, 0.3, 7.38), "corner"),         # an L of a long and a short face
    ((2.0, -4.0, 2.0), "from above"),       # sees the top too
])
def test_amodal_box_recovers_the_whole_car(viewpoint, name):
    truth = car()
    pts = visible_surface(truth, np.array(viewpoint))
    visible = visible_box(pts, voxel=VOXEL, pad=0.0)
    amodal = amodal_box(pts, viewpoint=np.array(viewpoint), prior=PRIOR, voxel=VOXEL, pad=0.0)
    iou_visible = iou_3d(visible[None], truth[None])[0, 0]
    iou_amodal = iou_3d(amodal[None], truth[None])[0, 0]
    assert iou_amodal >= 0.6, (name, iou_amodal, amodal)
    assert iou_amodal >= iou_visible - 1e-6, (name, iou_visible, iou_amodal)
    assert amodal[3] >= PRIOR.length - 1e-9 and amodal[5] >= PRIOR.width - 1e-9 and amodal[4] >= PRIOR.height - 1e-9


def test_rear_view_grows_away_from_the_camera_by_exactly_the_missing_length():
    # An axis-aligned rear face at z = 10 (voxel centres spanning 1.25 m in x, 1 voxel thick), camera at
    # the origin looking down +z, ground at y = 0.
    xs = np.arange(-0.75, 0.75, VOXEL) + VOXEL / 2
    ys = np.arange(-1.0, 0.0, VOXEL) + VOXEL / 2
    pts = np.array([[x, y, 10.0 + VOXEL / 2] for x in xs for y in ys])
    prior = SizePrior.from_size(4.0, 2.0, 1.5)
    box = amodal_box(pts, viewpoint=np.zeros(3), prior=prior, voxel=VOXEL, pad=0.0, ground_y=0.0)
    # the face is the width (seen whole, 1.25 m < 0.75 × 2 m: grown to 2 m on both ends, since the camera
    # looks straight across it); the length (4 m) grows from the face away from the camera; the height
    # reaches down to the ground from the visible top (−0.875: 0.875 m, short of 0.75 × 1.5 m): grown to 1.5
    assert box[3] == pytest.approx(4.0) and box[5] == pytest.approx(2.0) and box[4] == pytest.approx(1.5)
    near_face = 10.0 + VOXEL / 2                          # the centres of the face's voxels
    assert box[2] - box[3] / 2 == pytest.approx(near_face) and box[0] == pytest.approx(0.0)
    assert box[1] == pytest.approx(-0.75)                 # standing on y = 0, 1.5 m tall
    assert abs(abs(box[6]) - math.pi / 2) < 1e-9          # length runs along z
    # a side seen at nearly the prior's size is taken as whole, and without a ground the height stays
    wide = np.array([[x, y, 10.0 + VOXEL / 2] for x in np.arange(-0.875, 0.9, VOXEL) for y in ys])
    box = amodal_box(wide, viewpoint=np.zeros(3), prior=prior, voxel=VOXEL, pad=0.0)
    assert box[5] == pytest.approx(1.75) and box[4] == pytest.approx(0.75)
    # a plane further below the top than any object is tall (a tilted frame): no anchoring either
    box = amodal_box(wide, viewpoint=np.zeros(3), prior=prior, voxel=VOXEL, pad=0.0, ground_y=5.0)
    assert box[4] == pytest.approx(0.75) and box[1] == pytest.approx(-0.5)


def test_a_component_bigger_than_the_prior_keeps_its_size():
    big = car()
    big[3:6] = (5.5, 1.8, 2.2)                            # larger than the prior, within its maxima
    viewpoint = np.array([-6.76, 0.3, 7.38])
    pts = visible_surface(big, viewpoint)
    box = amodal_box(pts, viewpoint=viewpoint, prior=PRIOR, voxel=VOXEL, pad=0.0)
    assert box[3] >= 5.4 and iou_3d(box[None], big[None])[0, 0] >= 0.6


def test_two_cars_bumper_to_bumper_are_split_and_a_wall_is_dropped():
    viewpoint = np.array([-8.0, 0.3, 13.3])
    a, b = car(z=11.0, yaw=-math.pi / 2), car(z=15.6, yaw=-math.pi / 2)   # length along z, 0.2 m apart
    pts = np.concatenate([visible_surface(a, viewpoint), visible_surface(b, viewpoint)])
    pieces, dropped = split_oversized(pts, PRIOR, voxel=VOXEL, pad=0.0)
    assert len(pieces) == 2 and dropped == 0
    assert sorted(np.concatenate(pieces).tolist()) == list(range(len(pts)))   # every point in one piece
    centres = sorted(pts[p, 2].mean() for p in pieces)
    assert centres[0] == pytest.approx(11.0, abs=0.6) and centres[1] == pytest.approx(15.6, abs=0.6)
    wall = np.array([[x, y, 20.0] for x in np.arange(-10, 10, VOXEL) for y in np.arange(-3, 0, VOXEL)])
    pieces, dropped = split_oversized(wall, PRIOR, voxel=VOXEL, pad=0.0)
    assert pieces == [] and dropped == len(wall)          # 3 m tall: no piece fits a car's maxima
    single = visible_surface(car(), viewpoint)
    pieces, dropped = split_oversized(single, PRIOR, voxel=VOXEL, pad=0.0)
    assert len(pieces) == 1 and np.array_equal(pieces[0], np.arange(len(single))) and dropped == 0


def test_size_prior_from_unlabelled_components_lands_near_the_true_size():
    rng = np.random.default_rng(0)
    extents = []
    true = []
    for _ in range(60):
        size = (rng.uniform(3.8, 5.0), rng.uniform(1.4, 1.9), rng.uniform(1.6, 2.1))
        true.append(size)
        box = np.array([rng.uniform(-6, 6), 0.0, rng.uniform(8, 20), *size, rng.uniform(-math.pi, math.pi)])
        angle = rng.uniform(0, 2 * math.pi)
        viewpoint = np.array([box[0] + 10 * math.cos(angle), 0.3, box[2] + 10 * math.sin(angle)])
        pts = visible_surface(box, viewpoint)
        extents.append(visible_box(pts, voxel=VOXEL, pad=0.0)[3:6])
    prior = estimate_size_prior(np.array(extents))
    true = np.array(true)
    assert prior.length == pytest.approx(true[:, 0].mean(), rel=0.15)
    assert prior.width == pytest.approx(true[:, 2].mean(), rel=0.2)
    assert prior.height == pytest.approx(true[:, 1].mean(), rel=0.2)
    assert prior.max_length == pytest.approx(1.6 * prior.length)


def test_l_shape_rectangle_puts_both_legs_of_an_l_on_edges():
    """Two edges of a 4 × 2 m rectangle turned 25°: the L-shape fit recovers 25°, the sides and the centre.
    (For an L the minimum-area rectangle is ambiguous: along a leg and along the hypotenuse both have
    area 8, and on voxelised cars it picked the hypotenuse — test_amodal_box_recovers_the_whole_car.)"""
    from core.moving.boxfit import l_shape_rectangle

    a = math.radians(25)
    u, v = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    legs = np.concatenate([np.outer(np.linspace(0, 4, 41), u), np.outer(np.linspace(0, 2, 21), v)])
    centre, axis, extent = l_shape_rectangle(legs, floor=0.02)
    angle = math.degrees(math.atan2(axis[1], axis[0])) % 90
    assert min(abs(angle - 25), abs(angle - 115 % 90)) <= 1.0
    assert sorted(extent) == pytest.approx([2.0, 4.0], abs=0.1)
    assert centre == pytest.approx(2 * u + 1 * v, abs=0.1)


def test_size_prior_rejects_nonsense():
    with pytest.raises(ValueError):
        SizePrior(length=1.0, width=2.0, height=1.0, max_length=1.0, max_width=2.0, max_height=1.0)
    with pytest.raises(ValueError):
        SizePrior(length=2.0, width=1.0, height=1.0, max_length=1.0, max_width=1.0, max_height=1.0)
    with pytest.raises(Exception):
        estimate_size_prior(np.zeros((0, 3)))


def test_a_strip_of_a_long_side_takes_its_heading_from_coherent_flow():
    """Part of a car's long side (1.5 m of it, along z) is seen through a gap: by shape alone it fits the
    prior's width better (a whole end face), so the length goes across it; moving along z, the heading
    puts the length along the strip, and the box matches the car."""
    truth = np.array([0.0, -0.8, 10.0, 4.0, 1.6, 1.8, math.pi / 2])        # length along z, side at x = −0.9
    zs = np.arange(9.0, 10.5, VOXEL) + VOXEL / 2
    ys = np.arange(-1.5, 0.0, VOXEL) + VOXEL / 2
    pts = np.array([[-0.9 - VOXEL / 2, y, z] for z in zs for y in ys])      # the side's voxel centres
    prior = SizePrior.from_size(4.0, 1.8, 1.6)
    camera = np.array([-10.0, -0.8, 9.75])                                   # beside the car, looking along +x
    by_shape = amodal_box(pts, viewpoint=camera, prior=prior, voxel=VOXEL, pad=0.0, ground_y=0.0)
    by_heading = amodal_box(pts, viewpoint=camera, prior=prior, voxel=VOXEL, pad=0.0, ground_y=0.0,
                            heading=np.array([0.0, 1.0]))
    assert abs(by_shape[6]) < 1e-9                                           # length across the strip
    assert abs(abs(by_heading[6]) - math.pi / 2) < 1e-9                      # length along z
    assert iou_3d(by_heading[None], truth[None])[0, 0] > 0.5 > iou_3d(by_shape[None], truth[None])[0, 0]


def test_coherent_heading_against_the_resultant_written_out():
    from core.moving.detect_moving import HEADING_COHERENCE, coherent_heading

    rng = np.random.default_rng(0)
    coherent = 0
    for trial in range(50):
        flow = rng.normal(size=(3, 12)) + rng.uniform(0, 3) * np.array([[1.0], [0.0], [0.5]])  # 3×N
        # slow, obvious: the resultant length over the mean length of the bird's-eye vectors
        vectors = [np.array([flow[0, i], flow[2, i]]) for i in range(flow.shape[1])]
        resultant = np.linalg.norm(sum(vectors)) / len(vectors)
        mean_length = sum(np.linalg.norm(v) for v in vectors) / len(vectors)
        heading = coherent_heading(flow)
        if resultant >= HEADING_COHERENCE * mean_length:
            expected = sum(vectors) / np.linalg.norm(sum(vectors))
            assert heading is not None and np.allclose(heading, expected)
            coherent += 1
        else:
            assert heading is None
    assert 0 < coherent < 50                                                 # both branches were met
    assert coherent_heading(np.zeros((3, 4))) is None
    one_way = np.tile(np.array([[2.0], [5.0], [-2.0]]), (1, 6))               # all parallel, any vertical part
    assert np.allclose(coherent_heading(one_way), np.array([1.0, -1.0]) / math.sqrt(2))


def test_a_swollen_component_shrinks_to_the_box_slack_about_its_centre():
    # A component that fits the maxima (rule 1: 6.5 × 3.5 m < 1.6 × 4.4 m) but is wider and longer than
    # any car: the top of a 6.5 × 3.5 m slab of voxel centres, as flow spilled around a car would leave.
    # Slow reference: the box written out — each side min(seen, 1.25 × prior), centred where the slab is.
    xs = np.arange(0.0, 6.5, VOXEL) + VOXEL / 2
    zs = np.arange(10.0, 13.5, VOXEL) + VOXEL / 2
    pts = np.array([[x, -1.0, z] for x in xs for z in zs])
    heading = np.array([1.0, 0.0])                        # coherent flow along +x: the length is along x
    box = amodal_box(pts, viewpoint=np.array([3.25, -1.0, 0.0]), prior=PRIOR, voxel=VOXEL, pad=0.0, heading=heading)
    seen_length, seen_width = xs[-1] - xs[0], zs[-1] - zs[0]          # 6.25, 3.25 between voxel centres
    assert seen_length > 1.25 * PRIOR.length and seen_width > 1.25 * PRIOR.width
    assert box[3] == pytest.approx(1.25 * PRIOR.length) and box[5] == pytest.approx(1.25 * PRIOR.width)
    assert box[0] == pytest.approx(xs.mean()) and box[2] == pytest.approx(zs.mean())
    assert abs(box[6]) < 1e-9                             # length along x
    # a looser slack keeps more of it; a slack of 1 is the prior itself; below 1 is refused
    loose = SizePrior.from_size(CAR[0], CAR[2], CAR[1])
    loose = SizePrior(**{**loose.to_dict(), "box_slack": 1.5})
    box = amodal_box(pts, viewpoint=None, prior=loose, voxel=VOXEL, pad=0.0, heading=heading)
    assert box[3] == pytest.approx(seen_length) and box[5] == pytest.approx(1.5 * PRIOR.width)
    tight = SizePrior(**{**loose.to_dict(), "box_slack": 1.0})
    box = amodal_box(pts, viewpoint=None, prior=tight, voxel=VOXEL, pad=0.0, heading=heading)
    assert box[3] == pytest.approx(PRIOR.length) and box[5] == pytest.approx(PRIOR.width)
    with pytest.raises(ValueError, match="box_slack"):
        SizePrior(**{**loose.to_dict(), "box_slack": 0.9})
