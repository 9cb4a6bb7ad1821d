"""Spread over seeds against numpy, plan validation, and the claim verdicts on hand-built tables."""

import math

import numpy as np
import pytest

from services.bench.aggregate import fmt, flow_table, spread
from services.bench.claims import check_claims
from services.bench.plan import BenchConfigError, plan_for, with_steps


def test_spread_matches_numpy_and_skips_missing():
    values = [0.5, 0.25, None, float("nan"), 1.0]
    s = spread(values)
    finite = np.array([0.5, 0.25, 1.0])
    assert s["n"] == 3 and s["values"] == [0.5, 0.25, 1.0]
    assert math.isclose(s["mean"], finite.mean()) and math.isclose(s["std"], finite.std())
    assert spread([None, float("nan")]) == {"mean": None, "std": None, "n": 0, "values": []}
    assert fmt(spread([0.5])) == "0.500" and fmt(spread([0.25, 0.75])) == "0.500 ± 0.250" and fmt(None) == "–"


def test_flow_table_takes_zero_motion_and_model_rows():
    per_seed = {"0": {"flow": {"contrastive": {"zero_motion": {"epe_l1_moving": 6.0}, "model": {"epe_l1_moving": 3.0}},
                               "regression": {"zero_motion": {"epe_l1_moving": 6.0}, "model": {"epe_l1_moving": 5.0}}}},
                "1": {"flow": {"contrastive": {"zero_motion": {"epe_l1_moving": 8.0}, "model": {"epe_l1_moving": 4.0}},
                               "regression": {"zero_motion": {"epe_l1_moving": 8.0}, "model": {"epe_l1_moving": 5.0}}}}}
    rows = flow_table(per_seed, ("regression", "contrastive"))
    assert rows["zero-motion"]["moving"]["mean"] == 7.0 and rows["contrastive"]["moving"]["mean"] == 3.5
    assert rows["regression"]["moving"]["std"] == 0.0 and rows["contrastive"]["full"]["mean"] is None
    assert "input volumes" not in rows   # only when the volume-flow stage ran


def test_flow_table_adds_the_input_volume_row_when_present():
    per_seed = {"0": {"flow": {"contrastive": {"zero_motion": {"epe_l1_moving": 6.0}, "model": {"epe_l1_moving": 3.0}},
                               "volume": {"zero_motion": {"epe_l1_moving": 6.0}, "model": {"epe_l1_moving": 2.0}}}},
                "1": {"flow": {"contrastive": {"zero_motion": {"epe_l1_moving": 8.0}, "model": {"epe_l1_moving": 4.0}},
                               "volume": {"zero_motion": {"epe_l1_moving": 8.0}, "model": {"epe_l1_moving": 1.0}}}}}
    rows = flow_table(per_seed, ("contrastive",))
    assert list(rows) == ["zero-motion", "contrastive", "input volumes"]
    assert rows["input volumes"]["moving"]["mean"] == 1.5 and rows["input volumes"]["moving"]["n"] == 2


def _s(x):
    return spread([x])


def _tables(c_few, r_few, n_few, c_all, n_all):
    det = {"random/finetuned": {"2": {"0.5": _s(n_few)}, "all": {"0.5": _s(n_all)}},
           "regression/finetuned": {"2": {"0.5": _s(r_few)}, "all": {"0.5": _s(0.5)}},
           "contrastive/finetuned": {"2": {"0.5": _s(c_few)}, "all": {"0.5": _s(c_all)}}}
    ret = {a: {d: {"p@1": _s(p)} for d in ("2d", "3d")} for a, p in (("random", 0.0), ("regression", 0.1), ("contrastive", 0.3))}
    flow = {"zero-motion": {"moving": _s(7.0), "full": _s(0.2)}, "regression": {"moving": _s(5.5), "full": _s(0.8)},
            "contrastive": {"moving": _s(3.3), "full": _s(0.3)}}
    mov = {"static": {"contrastive, GT egomotion": {"ap": _s(0.5)}, "2.5D Farneback": {"ap": _s(0.3)},
                      "regression, GT egomotion": {"ap": _s(0.2)}},
           "moving": {"contrastive, egomotion module": {"ap": _s(0.45)}, "contrastive, GT egomotion": {"ap": _s(0.5)},
                      "2.5D Farneback": {"ap": spread([])}}}
    occ = {"contrastive": {k: _s(v) for k, v in (("acc_occupied", 0.97), ("acc_free", 0.9), ("acc_all", 0.95))}}
    ego = {"model": {"rot_rad": _s(0.1), "trans_m": _s(0.04)}, "icp": {"rot_rad": _s(0.09), "trans_m": _s(0.04)}}
    return {"detection": det, "retrieval": ret, "flow": flow, "moving": mov, "occupancy": occ, "egomotion": ego}


def test_claim_verdicts_follow_their_criteria():
    claims = {c["id"]: c for c in check_claims(_tables(0.6, 0.5, 0.4, 0.7, 0.65), budgets=["2", "all"])}
    assert claims["detection_few_labels"]["holds"] is True
    assert claims["detection_more_labels"]["holds"] is True          # 0.65 > 0.4
    assert claims["detection_gain_low_data"]["holds"] is True        # 0.2 > 0.05
    assert claims["retrieval_2d"]["holds"] is True and claims["flow_vs_zero_motion"]["holds"] is True
    assert claims["moving_static_vs_2p5d"]["holds"] is True
    assert claims["moving_camera_stabilised"]["holds"] is None       # no 2.5D number in the moving split
    assert claims["occupancy_accuracy"]["holds"] is False            # free 0.90 < 0.95
    assert claims["egomotion_vs_icp"]["holds"] is True               # 0.1 ≤ 1.5·0.09, 0.04 ≤ 1.5·0.04
    assert "0.600" in claims["detection_few_labels"]["ours"]
    flipped = {c["id"]: c for c in check_claims(_tables(0.4, 0.5, 0.6, 0.7, 0.65), budgets=["2", "all"])}
    assert flipped["detection_few_labels"]["holds"] is False
    tie = _tables(0.6, 0.5, 0.4, 0.7, 0.65)
    tie["flow"]["contrastive"]["moving"] = _s(5.5 * (1 - 0.005))   # 0.5 % better: within the 1 % margin
    assert {c["id"]: c for c in check_claims(tie, budgets=["2", "all"])}["flow_contrastive_vs_regression"]["holds"] is False


def test_plan_rejects_bad_options():
    assert plan_for("tiny", quick=True).label_budgets == (2, None)
    with pytest.raises(BenchConfigError):
        plan_for("tiny", label_budgets=(50,))          # more than the 12 training records
    with pytest.raises(BenchConfigError):
        plan_for("tiny", seeds=(0, 0))
    with pytest.raises(BenchConfigError):
        with_steps(plan_for("tiny"), detector=0)
    with pytest.raises(BenchConfigError):
        plan_for("huge")
