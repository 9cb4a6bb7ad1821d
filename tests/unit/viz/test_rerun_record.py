"""`n3dmap data preview --rerun`: the recording of one record, read back and compared with the record.

Records are built by hand (tests/unit/data/conftest.py::build_record: random poses, boxes, depth), so
every value checked here is one the test knows: camera poses and intrinsics, images, depth, boxes
(centres, half sizes, yaw, colours, track ids) and the motion arrows of the moving boxes, per step.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rerun")

import services.cli.main as cli_main  # noqa: E402
from core.data.shards import write_dataset  # noqa: E402
from services.viz import rerun_paths as paths  # noqa: E402
from tests.rrd_reading import Recording, array, mat3, rerun_cli, yaw_from_quaternions  # noqa: E402
from tests.unit.data.conftest import build_record  # noqa: E402

GRID = {"xmin": -16.0, "xmax": 16.0, "ymin": -4.0, "ymax": 4.0, "zmin": -16.0, "zmax": 16.0,
        "Z": 32, "Y": 8, "X": 32}


def _wrap(a):
    return np.angle(np.exp(1j * np.asarray(a)))


@pytest.fixture
def dataset(tmp_path):
    records = [build_record(T=3, V=2, H=4, W=6, K=4, seed=s) for s in range(3)]
    for r in records:
        r["box_moving"][:] = [True, False, True, False]
        r["box_valid"][:] = True
        r["box_valid"][1, 2] = False  # box 2 (moving) missing at t=1: no arrow t=0->1 nor t=1->2
    write_dataset(tmp_path / "d", records, split="val", preset_name="tiny", grid=GRID, generator={"source": "test"},
                  seed=1, shard_bytes=1 << 20)
    return tmp_path / "d", records


def _preview(capsys, *args) -> tuple[int, str, str]:
    code = cli_main.main(["data", "preview", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def test_recording_holds_cameras_images_depth_boxes_and_motion(capsys, dataset, tmp_path):
    data, records = dataset
    rrd = tmp_path / "out" / "preview.rrd"
    code, out, err = _preview(capsys, data, "--rerun", rrd, "--index", 1)
    assert code == 0, err
    assert f"wrote {rrd}" in out
    record = records[1]
    T, V, H, W, _ = record["rgb"].shape
    rec = Recording(rrd)

    assert array(rec.static(paths.WORLD, "ViewCoordinates:xyz")).reshape(-1).tolist() == [3, 2, 5]  # R, D, F
    assert array(rec.static(paths.WORLD_GRID, "Boxes3D:half_sizes"), 3).tolist() == [[16.0, 4.0, 16.0]]
    for v in range(V):
        assert np.allclose(mat3(rec.static(paths.camera_image(v), "Pinhole:image_from_camera")),
                           record["pix_T_cam"][v][:3, :3])
        assert array(rec.static(paths.camera_image(v), "Pinhole:resolution")).reshape(-1).tolist() == [W, H]
        rotation = rec.at(paths.camera(v), "Transform3D:mat3x3", paths.STEP)
        translation = rec.at(paths.camera(v), "Transform3D:translation", paths.STEP)
        images = rec.at(paths.camera_image(v), "Image:buffer", paths.STEP)
        depths = rec.at(paths.camera_image(v), "DepthImage:buffer", paths.STEP)
        assert sorted(rotation) == sorted(images) == sorted(depths) == list(range(T))
        for t in range(T):
            assert np.allclose(mat3(rotation[t]), record["world_T_cam"][t, v][:3, :3], atol=1e-6)
            assert np.allclose(array(translation[t]).reshape(-1), record["world_T_cam"][t, v][:3, 3], atol=1e-6)
            assert bytes(np.asarray(images[t][0], np.uint8)) == record["rgb"][t, v].tobytes()
            assert np.asarray(depths[t][0], np.uint8).tobytes() == record["depth"][t, v].tobytes()
    ref = rec.at(paths.WORLD_REF, "Transform3D:translation", paths.STEP)
    assert np.allclose([array(ref[t]).reshape(-1) for t in range(T)], record["world_T_ref"][:, :3, 3], atol=1e-6)

    centres = rec.at(paths.BOXES, "Boxes3D:centers", paths.STEP)
    halves = rec.at(paths.BOXES, "Boxes3D:half_sizes", paths.STEP)
    quats = rec.at(paths.BOXES, "Boxes3D:quaternions", paths.STEP)
    colours = rec.at(paths.BOXES, "Boxes3D:colors", paths.STEP)
    labels = rec.at(paths.BOXES, "Boxes3D:labels", paths.STEP)
    arrows_o = rec.at(paths.BOX_MOTION, "Arrows3D:origins", paths.STEP)
    arrows_v = rec.at(paths.BOX_MOTION, "Arrows3D:vectors", paths.STEP)
    assert sorted(centres) == sorted(arrows_v) == list(range(T))
    for t in range(T):
        k = np.flatnonzero(record["box_valid"][t])
        boxes = record["boxes"][t, k]
        assert np.allclose(array(centres[t], 3), boxes[:, :3], atol=1e-6)
        assert np.allclose(array(halves[t], 3), boxes[:, 3:6] / 2, atol=1e-6)
        assert np.allclose(_wrap(yaw_from_quaternions(quats[t]) - boxes[:, 6]), 0, atol=1e-5)
        expected_labels = [f"id {record['box_id'][j]}" + (" moving" if record["box_moving"][j] else "") for j in k]
        assert labels[t] == expected_labels
        rgba = np.asarray(colours[t], np.uint64)  # 0xRRGGBBAA
        red = (rgba >> 24) & 0xFF
        assert ((red == paths.MOVING_BOX[0]) == record["box_moving"][k]).all()
        # Motion: moving boxes valid at t and t+1 (box 0 always; box 2 never across t=1)
        m = [j for j in (0, 2) if t + 1 < T and record["box_valid"][t, j] and record["box_valid"][t + 1, j]]
        assert np.allclose(array(arrows_o[t], 3), record["boxes"][t, m, :3], atol=1e-6)
        assert np.allclose(array(arrows_v[t], 3), record["boxes"][t + 1, m, :3] - record["boxes"][t, m, :3] if m else
                           np.zeros((0, 3)), atol=1e-5)
    assert len(array(arrows_v[T - 1], 3)) == 0
    assert rerun_cli("rrd", "verify", str(rrd)).returncode == 0


def test_points_option_logs_the_back_projected_depth(capsys, dataset, tmp_path):
    data, records = dataset
    rrd = tmp_path / "points.rrd"
    code, _, err = _preview(capsys, data, "--rerun", rrd, "--points", "--index", -1)
    assert code == 0, err
    record = records[-1]
    rec = Recording(rrd)
    for v in range(record["rgb"].shape[1]):
        assert "DepthImage:buffer" not in rec.components(paths.camera_image(v))
        points = rec.at(paths.camera_points(v), "Points3D:positions", paths.STEP)
        K = record["pix_T_cam"][v]
        for t, value in points.items():
            xyz = array(value, 3)
            depth = record["depth"][t, v]
            assert len(xyz) == int((depth > 0).sum())
            # slow reference: project each point back to its pixel and compare the depth there
            u = np.rint(xyz[:, 0] / xyz[:, 2] * K[0, 0] + K[0, 2]).astype(int)
            vv = np.rint(xyz[:, 1] / xyz[:, 2] * K[1, 1] + K[1, 2]).astype(int)
            assert np.allclose(depth[vv, u], xyz[:, 2], atol=1e-5)


def _one_line_error(code, err, *fragments):
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("n3dmap data: error: "), (code, err)
    for f in fragments:
        assert str(f) in lines[0], lines[0]


def test_bad_inputs_are_one_line_errors(capsys, dataset, tmp_path):
    data, _ = dataset
    _one_line_error(*_preview(capsys, tmp_path / "nope", "--rerun", tmp_path / "a.rrd")[::2], "nope")
    _one_line_error(*_preview(capsys, data, "--rerun", tmp_path / "a.rrd", "--index", 7)[::2], "--index 7", "out of range")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_line_error(*_preview(capsys, data, "--rerun", blocker / "a.rrd")[::2], blocker / "a.rrd")
    _one_line_error(*_preview(capsys, data, "--rerun", tmp_path)[::2], "is a directory")
    _one_line_error(*_preview(capsys, data, "--rerun", tmp_path / "a.png")[::2], ".rrd")
    _one_line_error(*_preview(capsys, data)[::2], "--out", "--rerun")
    _one_line_error(*_preview(capsys, data, "--out", tmp_path / "p.png", "--points")[::2], "--points")
    assert not (tmp_path / "a.rrd").exists()  # failed runs leave no recording behind
