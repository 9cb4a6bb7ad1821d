"""Importers: tiny files written here in each source format, imported, and checked against values
computed by hand in the test."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from core.data.importers.authors_npz import import_authors_npz
from core.data.importers.kitti import import_kitti
from core.data.importers.tum import TUM_DEPTH_CAMERA, import_tum, nearest, pair_one_to_one
from core.data.shards import ShardDataset
from core.errors import DataError


def _only_record(out):
    ds = ShardDataset(out, verify=True)
    assert len(ds) == 1
    return ds[0], ds


# ----------------------------------------------------------------------------- TUM

def _quat_z(angle):
    """(qx, qy, qz, qw) of a rotation by `angle` about z, and its matrix, by hand."""
    c, s = math.cos(angle), math.sin(angle)
    return (0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)), np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.fixture
def tum_dir(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg1_tiny"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    rgbs, depths = [], []
    for i, t in enumerate(["1.000000", "1.100000", "1.200000"]):
        rgb = rng.integers(0, 256, (4, 6, 3), dtype=np.uint8)
        Image.fromarray(rgb).save(root / "rgb" / f"{t}.png")
        rgbs.append(rgb)
    for t, base in [("1.005000", 5000), ("1.110000", 12500), ("1.250000", 100)]:
        raw = np.full((4, 6), base, np.uint16)
        raw[0, 0] = 0                                            # a missing return
        raw[3, 5] = 65535
        Image.fromarray(raw).save(root / "depth" / f"{t}.png")
        depths.append(raw)
    (root / "rgb.txt").write_text("# color images\n# file: 'x'\n# timestamp filename\n"
                                  "1.000000 rgb/1.000000.png\n1.100000 rgb/1.100000.png\n1.200000 rgb/1.200000.png\n")
    (root / "depth.txt").write_text("# depth maps\n1.005000 depth/1.005000.png\n1.110000 depth/1.110000.png\n"
                                    "1.250000 depth/1.250000.png\n")
    qa, Ra = _quat_z(0.0)
    qb, Rb = _quat_z(math.pi / 2)
    qc, Rc = _quat_z(math.pi / 6)
    (root / "groundtruth.txt").write_text(
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
        f"0.990 9 9 9 {' '.join(map(str, qa))}\n"
        f"1.004 1 2 3 {' '.join(map(str, qb))}\n"
        f"1.098 4 5 6 {' '.join(map(str, qc))}\n")
    return root, rgbs, depths, (Rb, [1, 2, 3]), (Rc, [4, 5, 6])


def test_tum_import(tmp_path, tum_dir):
    root, rgbs, depths, (R0, t0), (R1, t1) = tum_dir
    manifest = import_tum(root, tmp_path / "out", num_frames=2, intrinsics=(3.0, 3.5, 2.5, 1.5))
    assert manifest["generator"]["associated_frames"] == 2      # the 1.200 frame has no depth within 0.02 s
    rec, ds = _only_record(tmp_path / "out")
    assert ds.key(0) == "rgbd_dataset_freiburg1_tiny-000000"
    np.testing.assert_array_equal(rec["rgb"][:, 0], np.stack(rgbs[:2]))
    np.testing.assert_array_equal(rec["depth"][:, 0], np.stack(depths[:2]).astype(np.float32) / 5000.0)
    assert rec["depth"][0, 0, 0, 0] == 0.0 and rec["depth"][1, 0, 0, 1] == 2.5
    want_K = np.array([[3, 0, 2.5, 0], [0, 3.5, 1.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)
    np.testing.assert_array_equal(rec["pix_T_cam"][0], want_K)
    for t, (R, trans) in enumerate([(R0, t0), (R1, t1)]):
        want = np.eye(4)
        want[:3, :3], want[:3, 3] = R, trans
        np.testing.assert_allclose(rec["world_T_cam"][t, 0], want, atol=1e-6)
        np.testing.assert_allclose(rec["world_T_ref"][t], rec["world_T_cam"][0, 0])
    assert rec["boxes"].shape == (2, 0, 7) and rec["box_id"].shape == (0,)


def test_tum_errors(tmp_path, tum_dir):
    root = tum_dir[0]
    with pytest.raises(DataError, match="fewer than T=3"):
        import_tum(root, tmp_path / "out", num_frames=3)
    (root / "groundtruth.txt").write_text("1.0 1 2 3 0 0 0\n")
    with pytest.raises(DataError, match=r"groundtruth.txt:1: expected `timestamp tx ty tz qx qy qz qw`"):
        import_tum(root, tmp_path / "out")
    with pytest.raises(DataError, match="does not exist"):
        import_tum(tmp_path / "nope", tmp_path / "out")


def test_tum_counts_what_it_skips_and_refuses_what_it_cannot_read(tmp_path, tum_dir):
    root = tum_dir[0]
    manifest = import_tum(root, tmp_path / "out", num_frames=2, intrinsics=(3.0, 3.5, 2.5, 1.5))
    g = manifest["generator"]
    assert (g["rgb_frames"], g["dropped_no_depth"], g["dropped_no_pose"], g["windows_skipped_for_gaps"]) == (3, 1, 0, 0)
    # the default camera is the full-size 640×480 one: these 6×4 images need their own
    with pytest.raises(DataError, match=r"the frames are 6×4, but TUM's camera .* is for 640×480 .*--intrinsics"):
        import_tum(root, tmp_path / "out2")
    # and a camera given for other frames is caught by its principal point
    with pytest.raises(DataError, match=r"principal point \(319.5, 239.5\) lies outside the 6×4 images"):
        import_tum(root, tmp_path / "out2", intrinsics=(525.0, 525.0, 319.5, 239.5))
    renamed = root.rename(root.with_name("my_sequence"))
    # an 8-bit depth image would read as depths of at most 5 cm: refused, naming the file
    depth_file = renamed / "depth" / "1.005000.png"
    Image.fromarray(np.full((4, 6), 200, np.uint8)).save(depth_file)
    with pytest.raises(DataError, match=r"1.005000.png: depth must be a single-channel 16-bit PNG, got uint8"):
        import_tum(renamed, tmp_path / "out4", intrinsics=(3.0, 3.5, 2.5, 1.5))


def _tum_sequence(root, H: int, W: int):
    """Two H×W frames, still camera, depth 0.2–4 m: a TUM sequence directory at `root`."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(1)
    for t in ("1.000000", "1.100000"):
        Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(root / "rgb" / f"{t}.png")
        Image.fromarray(rng.integers(1000, 20000, (H, W), dtype=np.uint16)).save(root / "depth" / f"{t}.png")
    (root / "rgb.txt").write_text("1.000000 rgb/1.000000.png\n1.100000 rgb/1.100000.png\n")
    (root / "depth.txt").write_text("1.000000 depth/1.000000.png\n1.100000 depth/1.100000.png\n")
    (root / "groundtruth.txt").write_text("1.000 0 0 0 0 0 0 1\n1.100 0 0 0 0 0 0 1\n")
    return root


def test_half_size_frames_need_their_own_camera(tmp_path):
    """A 320×240 copy passes the principal-point check with the full-size camera (319.5 < 320, 239.5 < 240),
    so the default camera checks the frames' size; the scaled camera imports them."""
    root = _tum_sequence(tmp_path / "half", 240, 320)
    with pytest.raises(DataError, match=r"the frames are 320×240, but TUM's camera .* is for 640×480"):
        import_tum(root, tmp_path / "out", num_frames=2)
    manifest = import_tum(root, tmp_path / "out", num_frames=2, intrinsics=(262.5, 262.5, 159.5, 119.5))
    assert manifest["generator"]["intrinsics"] == [262.5, 262.5, 159.5, 119.5]


def test_a_full_size_frame_of_any_sequence_unprojects_as_the_tum_page_says(tmp_path):
    """Without --intrinsics every sequence (whatever its directory's name) gets the camera of TUM's calibration
    page, on which "the conversion from the 2D images to 3D point clouds is the same for all datasets": the
    page's loop, written out here for a row and a column of pixels, against core.geometry's unprojection."""
    import torch

    from core.geometry.camera import depth_to_points

    root = _tum_sequence(tmp_path / "rgbd_dataset_freiburg3_anything", 480, 640)
    manifest = import_tum(root, tmp_path / "out", num_frames=2)
    assert manifest["generator"]["intrinsics"] == [525.0, 525.0, 319.5, 239.5]
    rec, _ = _only_record(tmp_path / "out")
    assert TUM_DEPTH_CAMERA == (525.0, 525.0, 319.5, 239.5)
    depth = rec["depth"][0, 0]                                                      # H×W metres
    xyz, valid = depth_to_points(torch.from_numpy(depth)[None], torch.from_numpy(rec["pix_T_cam"]))
    xyz = xyz[0].reshape(480, 640, 3).numpy()                                       # H×W×3
    assert valid.all()
    focal_length, center_x, center_y = 525.0, 319.5, 239.5
    for v, u in [(v, 17) for v in range(0, 480, 7)] + [(301, u) for u in range(0, 640, 7)]:
        d = depth[v, u]
        want = ((u - center_x) * d / focal_length, (v - center_y) * d / focal_length, d)
        np.testing.assert_allclose(xyz[v, u], want, rtol=1e-6, atol=1e-7)


def test_a_depth_frame_pairs_with_one_rgb_frame_closest_first():
    """TUM's associate.py: candidate pairs within max_dt, closest first, each frame used once — against a slow
    reference that tries every pairing."""
    import itertools

    rgb = np.array([1.033, 1.066, 1.100, 1.140])
    depth = np.array([1.050, 1.101, 1.300])
    got = pair_one_to_one(rgb, depth, 0.02)
    assert list(got) == [-1, 0, 1, -1]        # 1.050 goes to 1.066 (16 ms), not to 1.033 (17 ms) as well
    rng = np.random.default_rng(3)
    for _ in range(50):
        a, b = np.sort(rng.uniform(0, 1, 5)), np.sort(rng.uniform(0, 1, 4))
        got = pair_one_to_one(a, b, 0.15)
        assert len({j for j in got if j >= 0}) == (got >= 0).sum()          # each b at most once
        pairs = sorted((abs(b[j] - a[i]), i, j) for i, j in itertools.product(range(5), range(4))
                       if abs(b[j] - a[i]) <= 0.15)
        want, used_a, used_b = np.full(5, -1), set(), set()
        for _, i, j in pairs:                                                  # greedy, written out
            if i not in used_a and j not in used_b:
                want[i] = j
                used_a.add(i)
                used_b.add(j)
        np.testing.assert_array_equal(got, want)


def test_a_window_across_a_gap_is_skipped_and_counted(tmp_path):
    """Poses missing for 2 s (a motion-capture outage): the window across it would hold two steps 2 s apart beside
    others 0.1 s apart, and a record carries no timestamps to show it."""
    root = tmp_path / "rgbd_dataset_freiburg2_gap"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    stamps = [1.0, 1.1, 1.2, 1.3, 3.3, 3.4, 3.5, 3.6]
    for t in stamps:
        Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(root / "rgb" / f"{t:.6f}.png")
        Image.fromarray(np.full((4, 6), 5000, np.uint16)).save(root / "depth" / f"{t:.6f}.png")
    (root / "rgb.txt").write_text("".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in stamps))
    (root / "depth.txt").write_text("".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in stamps))
    (root / "groundtruth.txt").write_text("".join(f"{t:.6f} {t} 0 0 0 0 0 1\n" for t in stamps))
    manifest = import_tum(root, tmp_path / "out", num_frames=2, stride=1, intrinsics=(3.0, 3.0, 2.5, 1.5))
    g = manifest["generator"]
    assert g["windows_skipped_for_gaps"] == 1 and manifest["num_records"] == 6     # 7 windows, one across 1.3→3.3
    assert g["largest_step_s"] == pytest.approx(0.1) and g["gap_s"] == pytest.approx(0.15)
    positions = [ShardDataset(tmp_path / "out")[i]["world_T_cam"][:, 0, 0, 3] for i in range(6)]
    assert all(abs(p[1] - p[0] - 0.1) < 1e-5 for p in positions)


def test_nearest_matches_brute_force():
    rng = np.random.default_rng(1)
    stamps = np.sort(rng.uniform(0, 10, 50))
    queries = rng.uniform(-1, 11, 200)
    got = nearest(stamps, queries, 0.05)
    for q, g in zip(queries, got):
        d = np.abs(stamps - q)
        assert g == (int(np.argmin(d)) if d.min() <= 0.05 else -1)


# ----------------------------------------------------------------------------- KITTI

VELO_TO_CAM = np.array([[0, -1, 0, 0.0], [0, 0, -1, -0.08], [1, 0, 0, -0.27]])   # velo x fwd, y left, z up
FX, CX, CY, T2X = 4.0, 3.0, 2.0, 0.06


def _write_kitti(root):
    tr = root / "training"
    for d in ("image_2", "velodyne", "calib", "label_2"):
        (tr / d).mkdir(parents=True)
    (root / "ImageSets").mkdir()
    (root / "ImageSets" / "train.txt").write_text("000000\n")
    (root / "ImageSets" / "val.txt").write_text("000001\n")
    rgb = np.arange(5 * 8 * 3, dtype=np.uint8).reshape(5, 8, 3)
    Image.fromarray(rgb).save(tr / "image_2" / "000000.png")
    P2 = np.array([[FX, 0, CX, FX * T2X], [0, FX, CY, 0], [0, 0, 1, 0]])
    P0 = np.array([[FX, 0, CX, 0], [0, FX, CY, 0], [0, 0, 1, 0]])
    fmt = lambda m: " ".join(f"{v:.12e}" for v in np.ravel(m))
    (tr / "calib" / "000000.txt").write_text(
        f"P0: {fmt(P0)}\nP1: {fmt(P0)}\nP2: {fmt(P2)}\nP3: {fmt(P0)}\nR0_rect: {fmt(np.eye(3))}\n"
        f"Tr_velo_to_cam: {fmt(VELO_TO_CAM)}\nTr_imu_to_velo: {fmt(VELO_TO_CAM)}\n")
    # Points chosen in the cam2 frame (pixel = (FX·x/z + CX, FX·y/z + CY)), then taken back to velodyne.
    cam2 = np.array([[0, 0, 5], [0, 0, 8], [2, 1, 4], [-1, -1, 2], [0, 0, -3]], np.float64)
    rect0 = cam2 - [T2X, 0, 0]
    cam_T_velo = np.vstack([VELO_TO_CAM, [0, 0, 0, 1]])
    velo = (np.linalg.inv(cam_T_velo) @ np.c_[rect0, np.ones(5)].T).T[:, :3]
    np.c_[velo, np.ones(5)].astype(np.float32).tofile(tr / "velodyne" / "000000.bin")
    (tr / "label_2" / "000000.txt").write_text(
        "Car 0.00 0 -1.57 10.0 20.0 30.0 40.0 1.50 1.60 4.00 1.00 2.00 10.00 0.30\n"
        "DontCare -1 -1 -10 0.0 0.0 1.0 1.0 -1 -1 -1 -1000 -1000 -1000 -10\n"
        "Pedestrian 0.00 1 0.2 1 2 3 4 1.80 0.60 0.80 -2.00 1.70 7.00 -1.00\n")
    return rgb


def test_kitti_import(tmp_path):
    rgb = _write_kitti(tmp_path / "kitti")
    import_kitti(tmp_path / "kitti", tmp_path / "out", split="train")
    rec, ds = _only_record(tmp_path / "out")
    assert ds.key(0) == "000000"
    np.testing.assert_array_equal(rec["rgb"][0, 0], rgb)
    want_depth = np.zeros((5, 8), np.float32)
    want_depth[2, 3] = 5.0          # (0,0,5) and the farther (0,0,8) share pixel (u=3, v=2): nearest wins
    want_depth[3, 5] = 4.0          # (2,1,4) -> u = 4·2/4 + 3 = 5, v = 4·1/4 + 2 = 3
    want_depth[0, 1] = 2.0          # (-1,-1,2) -> u = 1, v = 0; (0,0,-3) is behind the camera
    np.testing.assert_allclose(rec["depth"][0, 0], want_depth, atol=1e-5)
    np.testing.assert_allclose(rec["pix_T_cam"][0], [[FX, 0, CX, 0], [0, FX, CY, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    want_pose = np.eye(4)
    want_pose[0, 3] = -T2X          # world = rect cam0; cam2 sits t2 = 6 cm to its right: world_T_cam = [I | -t2]
    np.testing.assert_allclose(rec["world_T_cam"][0, 0], want_pose, atol=1e-6)
    np.testing.assert_array_equal(rec["world_T_ref"][0], np.eye(4))
    # Car: bottom centre (1, 2, 10), h 1.5 w 1.6 l 4 -> centre y = 2 - 0.75; DontCare dropped.
    np.testing.assert_allclose(rec["boxes"][0], [[1.0, 1.25, 10.0, 4.0, 1.5, 1.6, 0.3],
                                                 [-2.0, 0.8, 7.0, 0.8, 1.8, 0.6, -1.0]], atol=1e-6)
    assert rec["box_valid"].tolist() == [[True, True]] and rec["box_id"].tolist() == [0, 1]
    assert not rec["box_moving"].any()


def test_kitti_resize_and_errors(tmp_path):
    _write_kitti(tmp_path / "kitti")
    import_kitti(tmp_path / "kitti", tmp_path / "out", resize=(15, 24), classes=["Car"])
    rec, _ = _only_record(tmp_path / "out")
    assert rec["rgb"].shape == (1, 1, 15, 24, 3) and rec["boxes"].shape == (1, 1, 7)
    # ×3 with the pixel-centre convention: fx' = 3·fx = 12, cx' = 3·(cx + 0.5) - 0.5 = 10, cy' = 7
    np.testing.assert_allclose(rec["pix_T_cam"][0, :2, :3], [[12, 0, 10], [0, 12, 7]])
    want_depth = np.zeros((15, 24), np.float32)
    want_depth[7, 10] = 5.0         # (0,0,5) -> (u, v) = (10, 7)
    want_depth[10, 16] = 4.0        # (2,1,4) -> (12·0.5 + 10, 12·0.25 + 7)
    want_depth[1, 4] = 2.0          # (-1,-1,2) -> (-6 + 10, -6 + 7)
    np.testing.assert_allclose(rec["depth"][0, 0], want_depth, atol=1e-5)
    with pytest.raises(DataError, match="missing image"):
        import_kitti(tmp_path / "kitti", tmp_path / "val", split="val")
    with pytest.raises(DataError, match="not a KITTI object root"):
        import_kitti(tmp_path, tmp_path / "x")


# ----------------------------------------------------------------------------- authors' npz

# camR_T_origin for an origin with x forward, y left, z up and camR looking along origin x:
# camR x (right) = -origin y, camR y (down) = -origin z, camR z (forward) = origin x.
CAMR_R_ORIGIN = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], np.float64)


def _authors_file(path, *, yaw_deg=30.0):
    camR_T_origin = np.eye(4)
    camR_T_origin[:3, :3], camR_T_origin[:3, 3] = CAMR_R_ORIGIN, [0.0, 1.0, 0.0]
    origin_T_camR = np.linalg.inv(camR_T_origin)
    camR_T_camX1 = np.eye(4)
    camR_T_camX1[0, 3] = 1.0                                       # view 1: 1 m to the right of camR
    origin_T_camXs = np.stack([origin_T_camR, origin_T_camR @ camR_T_camX1])
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = 2.0, 2.0, 2.0, 1.0
    rgb = np.arange(2 * 4 * 5 * 3, dtype=np.uint8).reshape(2, 4, 5, 3)
    xyz = np.array([[[0, 0, 4], [1, 1, 2], [0, 0, 0]],            # (0,0,4) -> pixel (2, 1); (1,1,2) -> (3, 2)
                    [[0, 0, 0], [0, 0, 0], [-1, 0, 1]]], np.float32)  # padding rows; (-1,0,1) -> (0, 1)
    boxes = np.array([[1, 2, 3, 4, 1.5, 2, 0, 0, yaw_deg], [0, 0, 0, 0, 0, 0, 0, 0, 0]], np.float32)
    np.savez(path, pix_T_cams=np.stack([K, K]).astype(np.float32),
             origin_T_camXs=origin_T_camXs.astype(np.float32),
             origin_T_camRs=np.stack([origin_T_camR] * 2).astype(np.float32), rgb_camXs=rgb,
             xyz_camXs=xyz, boxlists=np.stack([boxes, boxes]),
             tidlists=np.array([[7, -1], [7, -1]], np.int64), scorelists=np.array([[1, 0], [1, 0]], np.float32))
    return rgb


def test_authors_npz_import(tmp_path):
    (tmp_path / "src").mkdir()
    rgb = _authors_file(tmp_path / "src" / "carla.000.npz")
    import_authors_npz(tmp_path / "src", tmp_path / "out")
    rec, ds = _only_record(tmp_path / "out")
    assert ds.key(0) == "carla_000"
    np.testing.assert_array_equal(rec["rgb"][0], rgb)
    want_depth = np.zeros((2, 4, 5), np.float32)
    want_depth[0, 1, 2], want_depth[0, 2, 3], want_depth[1, 1, 0] = 4.0, 2.0, 1.0
    np.testing.assert_array_equal(rec["depth"][0], want_depth)
    # world = camR: view 0 is camR itself, view 1 sits 1 m to its right.
    np.testing.assert_allclose(rec["world_T_cam"][0, 0], np.eye(4), atol=1e-6)
    want1 = np.eye(4)
    want1[0, 3] = 1.0
    np.testing.assert_allclose(rec["world_T_cam"][0, 1], want1, atol=1e-6)
    np.testing.assert_array_equal(rec["world_T_ref"][0], np.eye(4))
    # A yaw of +30° about the origin's z (up) is a rotation of -30° about camR's Y (down); the
    # authors' −π/2 offsets make the object's axes camR's axes at zero angles. Padding row zeroed.
    np.testing.assert_allclose(rec["boxes"][0], [[1, 2, 3, 4, 1.5, 2, -math.pi / 6], [0] * 7], atol=1e-6)
    assert rec["box_valid"].tolist() == [[True, False]] and rec["box_id"].tolist() == [7, -1]


def test_authors_npz_errors(tmp_path):
    _authors_file(tmp_path / "a.npz")
    with np.load(tmp_path / "a.npz") as z:
        d = {k: z[k] for k in z.files if k != "boxlists"}
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(DataError, match=r"bad.npz: key 'boxlists' is missing"):
        import_authors_npz(tmp_path / "bad.npz", tmp_path / "out")
    with pytest.raises(DataError, match="no .npz files"):
        import_authors_npz(tmp_path / "out", tmp_path / "out2")


@pytest.mark.parametrize("key", ["origin_T_camRs", "boxlists", "tidlists", "scorelists"])
def test_an_authors_sequence_file_is_refused_not_fused_as_one_instant(tmp_path, key):
    """The authors' sequence files have the same keys with S time steps (a reference camera and boxes per step);
    read as one instant (entry 0 of each) they would fuse frames of different times as simultaneous views."""
    _authors_file(tmp_path / "a.npz")
    with np.load(tmp_path / "a.npz") as z:
        d = {k: z[k].copy() for k in z.files}
    if key == "origin_T_camRs":
        d[key][1, 0, 3] += 5.0                    # camR moved 5 m at step 1
    elif key == "boxlists":
        d[key][1, 0, 0] += 5.0                    # the box moved to x + 5 at step 1
    else:
        d[key][1, 0] = -7 if key == "tidlists" else 0.5
    np.savez(tmp_path / "seq.npz", **d)
    with pytest.raises(DataError, match=rf"seq.npz: key '{key}' differs between entry 0 and entry 1"):
        import_authors_npz(tmp_path / "seq.npz", tmp_path / "out")
