"""Spread over seeds against numpy, plan validation, and the claim verdicts on hand-built tables."""

import math

import numpy as np
import pytest

from services.bench.aggregate import fmt, flow_table, spread
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


def test_flow_table_adds_the_other_gates_rows_after_the_gated_ones():
    def scores(gated, filled=None, raw=None):
        out = {"zero_motion": {"epe_l1_moving": 6.0}, "model": {"epe_l1_moving": gated}}
        if filled is not None:
            out.update(model_filled={"epe_l1_moving": filled}, model_raw={"epe_l1_moving": raw})
        return out

    per_seed = {"0": {"flow": {"regression": scores(5.0, 4.0, 3.0), "contrastive": scores(3.0, 3.5, 3.5),
                               "volume": scores(2.0)}},
                "1": {"flow": {"regression": scores(5.0), "contrastive": scores(4.0, 2.5, 1.5), "volume": scores(1.0)}}}
    rows = flow_table(per_seed, ("regression", "contrastive"))
    assert list(rows) == ["zero-motion", "regression", "contrastive", "input volumes",
                          "regression, filled gate", "regression, no gate", "contrastive, filled gate",
                          "contrastive, no gate"]   # no other-gate rows for the volume flow: no seed has them
    assert rows["regression, no gate"]["moving"]["values"] == [3.0] and rows["regression"]["moving"]["n"] == 2
    assert rows["contrastive, filled gate"]["moving"]["mean"] == 3.0 and rows["contrastive, no gate"]["moving"]["mean"] == 2.5


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
    with pytest.raises(BenchConfigError, match="precision"):
        plan_for("tiny", precision="fp16")


def test_precision_travels_with_the_plan_and_a_rerun_must_match_it(tmp_path):
    """`bench paper --precision bf16` reaches every stage through the plan (seed workers rebuild it from
    plan.json); a plan.json written before the option means fp32, and a rerun with bf16 into it is refused."""
    import json

    from services.bench.paper import _check_same_plan
    from services.bench.plan import BenchConfig

    bf16 = plan_for("tiny", quick=True, precision="bf16")
    assert BenchConfig.from_dict(json.loads(json.dumps(bf16.to_dict()))).precision == "bf16"
    path = tmp_path / "plan.json"
    old = plan_for("tiny", quick=True).to_dict()
    del old["precision"]                                  # an earlier n3dmap's plan
    path.write_text(json.dumps(old))
    _check_same_plan(path, plan_for("tiny", quick=True))  # fp32: the same plan
    path.write_text(json.dumps(old))
    with pytest.raises(BenchConfigError, match="precision"):
        _check_same_plan(path, bf16)
