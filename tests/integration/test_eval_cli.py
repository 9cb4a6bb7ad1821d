"""`n3dmap eval egomotion|flow|occupancy` as a real process on a tiny generated dataset and bundle.

The bundle holds freshly initialised modules (the commands are under test, not the training), so the
checks are about what the reports say: files exist, metrics.json has every row, the egomotion identity
row equals the records' true motion, and the flow zero-motion row equals an independent computation.
"""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from core.bundle import load_bundle, save_bundle
from core.data.ground_truth import gt_egomotion, gt_flow
from core.data.shards import ShardDataset, write_dataset
from core.eval.protocols.egomotion import LEARNED_ROW
from core.eval.protocols.occupancy import balanced_threshold, scores_by_threshold
from core.geometry import se3
from core.presets import TINY
from core.synthetic.generate import generate_record
from core.tasks.egomotion import EgomotionTask
from core.tasks.flow import FlowTask
from core.tasks.occupancy import OccupancyTask

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.integration, pytest.mark.slow]  # three CLI processes: minutes on a loaded 2-core box


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    records = [generate_record(TINY, seed=s, moving_ego=True) for s in (0, 1)]
    write_dataset(root / "data", records, split="test", preset_name="tiny", grid=TINY.grid.to_dict(),
                  generator={"moving_ego": True}, seed=0, shard_bytes=1 << 30)
    torch.manual_seed(0)
    modules = {"egomotion": EgomotionTask.from_preset(TINY).egomotion}
    flow_task, occ_task = FlowTask.from_preset(TINY), OccupancyTask.from_preset(TINY)
    modules.update(mapper=flow_task.mapper, flow=flow_task.flow, occupancy=occ_task.occupancy)
    save_bundle(root / "bundle", modules=modules, preset=TINY, provenance={"test": True}, metrics={})
    return root, records


def _run(root: Path, *args: str) -> dict:
    cmd = [sys.executable, "-m", "services.cli.main", "eval", *args, "--data", str(root / "data"),
           "--bundle", str(root / "bundle"), "--device", "cpu"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_eval_egomotion_report(setup):
    root, records = setup
    out = root / "ego_report"
    _run(root, "egomotion", "--out", str(out))
    assert (out / "report.md").is_file() and (out / "rotation_error_hist.png").is_file()
    m = json.loads((out / "metrics.json").read_text())["metrics"]
    assert set(m["egomotion"]) == {"model", LEARNED_ROW, "identity", "icp"}
    # the module's weightless last stage (point-to-TSDF) refines where its learned stages end
    assert m["egomotion"]["model"]["trans_err_m_mean"] < m["egomotion"][LEARNED_ROW]["trans_err_m_mean"]
    truth = [gt_egomotion(r, 0, 1)["ref0_T_ref1"].double() for r in records]
    expected_t = sum(float(T[:3, 3].norm()) for T in truth) / len(truth)
    expected_r = sum(float(se3.rotation_angle(T[:3, :3])) for T in truth) / len(truth)
    assert m["egomotion"]["identity"]["trans_err_m_mean"] == pytest.approx(expected_t, rel=1e-5)
    assert m["egomotion"]["identity"]["rot_err_rad_mean"] == pytest.approx(expected_r, rel=1e-4, abs=1e-6)
    # ICP on the clouds of a moving ego beats doing nothing on translation
    assert m["egomotion"]["icp"]["trans_err_m_mean"] < m["egomotion"]["identity"]["trans_err_m_mean"]
    assert "Egomotion evaluation" in (out / "report.md").read_text()


def test_eval_flow_report(setup):
    root, records = setup
    out = root / "flow_report"
    _run(root, "flow", "--out", str(out), "--max-records", "2")
    m = json.loads((out / "metrics.json").read_text())["metrics"]["flow"]
    assert set(m) == {"model", "model_filled", "model_raw", "zero_motion"}
    # on static voxels (true flow 0) the error is the kept flow: the filled gate keeps a superset of the
    # paper's gate's voxels and a subset of all
    static = [m[row]["epe_l1_static"] for row in ("model", "model_filled", "model_raw")]
    assert static[0] <= static[1] + 1e-6 and static[1] <= static[2] + 1e-6
    gts = [gt_flow(r, 0, TINY.grid) for r in records]
    l1 = torch.cat([g.abs().sum(0).flatten() for g in gts])
    moving = torch.cat([(g.norm(dim=0) > 1e-3).flatten() for g in gts])
    assert m["zero_motion"]["epe_l1_full"] == pytest.approx(float(l1.mean()), rel=1e-5)
    assert m["zero_motion"]["epe_l1_moving"] == pytest.approx(float(l1[moving].mean()), rel=1e-5)
    assert m["zero_motion"]["epe_l1_static"] < 1e-5  # background gt flow is 0 up to float rounding
    assert (out / "flow_bev.png").is_file()


def test_eval_occupancy_report_and_errors(setup):
    root, _ = setup
    out = root / "occ_report"
    _run(root, "occupancy", "--out", str(out), "--max-records", "1")
    m = json.loads((out / "metrics.json").read_text())["metrics"]["occupancy"]
    for k in ("acc_occupied", "acc_free", "acc_all", "iou_occupied"):
        assert m[k] is None or 0.0 <= m[k] <= 1.0
    assert m["voxels_occupied"] > 0 and m["voxels_free"] > 0
    assert (out / "occupancy_heightmap.png").is_file()
    bad = subprocess.run([sys.executable, "-m", "services.cli.main", "eval", "occupancy", "--data",
                          str(root / "missing"), "--bundle", str(root / "bundle"), "--out", str(root / "x")],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "missing" in bad.stderr and "Traceback" not in bad.stderr


def test_eval_occupancy_balanced_threshold_is_chosen_on_other_records(setup):
    """--balanced-on DIR picks the threshold on DIR's records, each view as the input in turn (the same rule
    and grid as bench paper), and scores --data with it; the records it scores may not be the ones it chose
    on."""
    root, records = setup
    val = root / "val"
    if not val.exists():
        write_dataset(val, [generate_record(TINY, seed=7, moving_ego=True)], split="val", preset_name="tiny",
                      grid=TINY.grid.to_dict(), generator={"moving_ego": True}, seed=7, shard_bytes=1 << 30)
    out = root / "occ_balanced"
    proc = _run(root, "occupancy", "--out", str(out), "--balanced-on", str(val))
    settings = json.loads((out / "metrics.json").read_text())["settings"]
    bundle = load_bundle(root / "bundle")
    expected = balanced_threshold(scores_by_threshold(bundle, list(ShardDataset(val)), input_views=None,
                                                      device="cpu"))
    assert settings["threshold"] == pytest.approx(expected)
    assert settings["threshold_chosen_on"]["data"] == str(val)
    assert f"threshold {expected:g} (balanced on {val})" in proc.stdout
    for argv, says in ((["--balanced-on", str(root / "data")], "other records than --data"),
                       (["--balanced-on", str(root / "nowhere")], "--balanced-on"),
                       (["--threshold", "1.5"], "--threshold"),
                       (["--threshold", "0.4", "--balanced-on", str(val)], "not allowed with")):
        bad = subprocess.run([sys.executable, "-m", "services.cli.main", "eval", "occupancy", "--data",
                              str(root / "data"), "--bundle", str(root / "bundle"), "--out", str(root / "y"),
                              *argv], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and says in bad.stderr and "Traceback" not in bad.stderr, (argv, bad.stderr)
