"""Spread over seeds against numpy, plan validation, and the claim verdicts on hand-built tables."""

import math

import numpy as np
import pytest

from core.eval.protocols.egomotion import LEARNED_ROW
from services.bench.aggregate import detection_draws_table, egomotion_table, fmt, flow_table, spread
from services.bench.evaluations import detection_over_draws
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


def _det(m33: float, m50: float | None, detections: int) -> dict:
    return {"map": {"0.33": m33, "0.5": m50}, "map_bev": {"0.33": m33 + 0.1, "0.5": None if m50 is None else m50 + 0.1},
            "gt_boxes": 7,
            "detections": detections, "frames": 4}


def test_a_row_over_label_draws_is_their_mean_and_keeps_each_draw():
    draws = [_det(0.9, 0.5, 10), _det(0.7, 0.8, 20), _det(0.8, 0.2, 30)]
    row = detection_over_draws(draws)
    assert math.isclose(row["map"]["0.5"], (0.5 + 0.8 + 0.2) / 3) and math.isclose(row["map"]["0.33"], 0.8)
    assert math.isclose(row["map_bev"]["0.5"], (0.6 + 0.9 + 0.3) / 3) and row["detections"] == 20
    assert row["draws"] == [d["map"] for d in draws] and row["gt_boxes"] == 7 and row["frames"] == 4


def test_a_draw_without_an_ap_leaves_that_iou_without_a_mean():
    # a draw's AP is None where the records hold no ground truth: the mean at that IoU is missing (a claim
    # reading it is undetermined), not the mean of the other draws, and the other IoUs keep theirs
    draws = [_det(0.9, 0.5, 10), _det(0.7, None, 20)]
    row = detection_over_draws(draws)
    assert row["map"]["0.5"] is None and math.isclose(row["map"]["0.33"], 0.8)
    assert row["draws"][1]["0.5"] is None


def test_draws_table_spreads_each_draw_over_seeds_and_the_claims_difference():
    def seed(c: list, g: list) -> dict:
        return {"detection": {"contrastive/finetuned/2": {"draws": [{"0.5": v} for v in c]},
                              "regression/finetuned/2": {"draws": [{"0.5": v} for v in g]}}}
    per_seed = {"0": seed([0.8, 0.6], [0.7, 0.7]), "1": seed([0.9, 0.5], [0.6, 0.8])}
    table = detection_draws_table(per_seed, [("regression", "finetuned"), ("contrastive", "finetuned")], "2", 2)
    assert [s["values"] for s in table["contrastive/finetuned"]] == [[0.8, 0.9], [0.6, 0.5]]
    diff = table["contrastive − regression (fine-tuned)"]
    assert np.allclose(diff[0]["values"], [0.1, 0.3]) and np.allclose(diff[1]["values"], [-0.1, -0.3])
    assert "contrastive − regression (frozen)" not in table  # no frozen rows ran
    # both modes: one difference per mode, each of its own rows
    for r, bump in zip(per_seed.values(), (0.05, -0.05)):
        for arm in ("contrastive", "regression"):
            r["detection"][f"{arm}/frozen/2"] = {"draws": [{"0.5": d["0.5"] + (bump if arm == "contrastive" else 0)}
                                                           for d in r["detection"][f"{arm}/finetuned/2"]["draws"]]}
    variants = [(a, m) for a in ("regression", "contrastive") for m in ("frozen", "finetuned")]
    table = detection_draws_table(per_seed, variants, "2", 2)
    frozen = table["contrastive − regression (frozen)"]
    assert np.allclose(frozen[0]["values"], [0.15, 0.25]) and np.allclose(frozen[1]["values"], [-0.05, -0.35])
    assert np.allclose(table["contrastive − regression (fine-tuned)"][0]["values"], [0.1, 0.3])
    # a seed without draws (a plan of one draw) leaves the cells empty rather than failing
    assert detection_draws_table({"0": {}}, [("random", "finetuned")], "2", 2)["random/finetuned"][1]["n"] == 0


def test_label_draws_apply_to_the_smallest_budget_and_must_fit_the_training_records():
    plan = plan_for("small")
    assert plan.label_draws == 4 and plan.draws_of(2) == 4 and plan.draws_of(8) == 1 and plan.draws_of(None) == 1
    assert plan_for("tiny").label_draws == 1 and plan_for("tiny", quick=True).label_draws == 2
    with pytest.raises(BenchConfigError, match="label_draws 9 .* budget 8 .* 64 training records"):
        plan_for("small", label_budgets=(8, None), label_draws=9)
    plan_for("small", label_budgets=(8, None), label_draws=8)          # 8 × 8 = 64 records: fits exactly
    assert plan_for("small", label_budgets=(None,)).draws_of(None) == 1  # every record labelled: one set
    with pytest.raises(BenchConfigError, match="label_draws must be >= 1"):
        plan_for("small", label_draws=0)


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


def test_label_draws_travel_with_the_plan_and_an_earlier_plan_means_one(tmp_path):
    """A plan.json written before label draws existed trained one draw: the same plan as label_draws=1,
    and another draw count is refused without --rerun-changed (which then only adds stages)."""
    import json

    from services.bench.paper import _check_same_plan
    from services.bench.plan import BenchConfig

    two = plan_for("tiny", quick=True)
    assert BenchConfig.from_dict(json.loads(json.dumps(two.to_dict()))).label_draws == 2
    old = plan_for("tiny", quick=True, label_draws=1).to_dict()
    del old["label_draws"]                                    # an earlier n3dmap's plan
    assert BenchConfig.from_dict(old).label_draws == 1
    path = tmp_path / "work" / "plan.json"
    path.parent.mkdir()
    path.write_text(json.dumps(old))
    _check_same_plan(path, plan_for("tiny", quick=True, label_draws=1))
    path.write_text(json.dumps(old))
    with pytest.raises(BenchConfigError, match="label_draws"):
        _check_same_plan(path, two)


def test_ray_workers_share_each_detectors_labels_and_never_outnumber_them():
    """With N Ray workers a detector's labelled records are sharded N ways, so its per-worker batch is at
    most one share (2 labels on 2 workers: 1 each, a run-wide batch of 2 as in one process); more
    workers than the smallest budget's records are refused when the plan is made, not at its first
    detector stage after the pretraining."""
    preset_batch = 2                          # the small preset's
    in_process, two = plan_for("small"), plan_for("small", workers=2)
    three = plan_for("small", workers=3, label_budgets=(4, 8, None))
    # the slow obvious rule: the largest batch b <= preset_batch with b * workers <= labelled records
    for plan in (in_process, two, three):
        for budget in plan.label_budgets:
            records = plan.budget_records(budget)
            workers = max(1, plan.workers)
            expected = max(b for b in range(1, preset_batch + 1) if b * workers <= records)
            assert plan.detector_batch_size(budget, preset_batch) == expected, (plan.workers, budget)
    assert in_process.detector_batch_size(2, preset_batch) == 2 and two.detector_batch_size(2, preset_batch) == 1
    assert plan_for("small", workers=2, batch_size=4).detector_batch_size(8, preset_batch) == 4


def test_a_rerun_with_other_workers_is_refused_only_where_a_detector_would_train_differently(tmp_path):
    """The worker count is no part of a plan's identity, except that Ray workers share out each detector's
    labels: 2 labels on 2 workers train with one record per worker and step, so a run continued with
    another count would mix detectors of both kinds; 4 labels on 2 workers keep the batch of 2."""
    import json

    from services.bench.paper import _check_same_plan

    path = tmp_path / "work" / "plan.json"
    path.parent.mkdir()
    path.write_text(json.dumps(plan_for("tiny", quick=True).to_dict()))          # budgets 2 and all, in-process
    with pytest.raises(BenchConfigError, match="workers"):
        _check_same_plan(path, plan_for("tiny", quick=True, workers=2))
    _check_same_plan(path, plan_for("tiny", quick=True))                         # the same count: fine
    path.write_text(json.dumps(plan_for("tiny", quick=True, label_budgets=(4, None), label_draws=1).to_dict()))
    _check_same_plan(path, plan_for("tiny", quick=True, label_budgets=(4, None), label_draws=1, workers=2))
    with pytest.raises(BenchConfigError, match="workers 3: the smallest label budget labels 2"):
        plan_for("small", workers=3, label_budgets=(2, None))
    with pytest.raises(BenchConfigError, match="labels 64 record"):                # every budget is "all"
        plan_for("small", workers=65, label_budgets=(None,))


def test_egomotion_table_lists_the_models_rows_first_and_spreads_each_over_seeds():
    def seed(model: float, learned: float | None) -> dict:
        methods = {"identity": {"rot_err_rad_mean": 0.01, "trans_err_m_mean": 0.8, "pairs": 32},
                   "icp": {"rot_err_rad_mean": 0.0001, "trans_err_m_mean": 0.003, "pairs": 32},
                   "model": {"rot_err_rad_mean": model, "trans_err_m_mean": 0.002, "pairs": 32}}
        if learned is not None:
            methods[LEARNED_ROW] = {"rot_err_rad_mean": learned, "trans_err_m_mean": 0.03, "pairs": 32}
        return {"egomotion": {"methods": methods}}
    table = egomotion_table({"0": seed(0.0002, 0.002), "1": seed(0.0004, 0.004)})
    assert list(table) == ["model", LEARNED_ROW, "icp", "identity"]
    assert table["model"]["rot_rad"]["mean"] == pytest.approx(0.0003)
    assert table[LEARNED_ROW]["trans_m"]["values"] == [0.03, 0.03]
    # a seed without the row (a module without a last stage) leaves it out of that seed's spread
    assert egomotion_table({"0": seed(0.0002, None), "1": seed(0.0004, 0.004)})[LEARNED_ROW]["rot_rad"]["values"] == [0.004]
