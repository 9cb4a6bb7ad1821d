"""The strict judge: each case the honest-verdicts rules name, with the verdict it must give.

The slow, obvious reference here is the rule written out by hand per case; `check_claims` is checked
on per-seed results built by hand, so every number a verdict rests on is visible in the test.
"""

import math

import pytest

from services.bench.claims import check_claims
from services.bench.judge import (
    FAILS, FLOORS, HOLDS, NOT_JUDGED, UNDETERMINED, AtLeast, Better, Positive, RatioAtMost, WithinOf, derive, judge,
)

AP, EPE, GAIN = FLOORS["ap"], FLOORS["epe"], FLOORS["gain"]


def seeds(**columns):
    """seeds(a=[...], b=[...]) -> {"0": {"a": .., "b": ..}, "1": ...} (one list entry per seed)."""
    n = len(next(iter(columns.values())))
    return {str(i): {k: v[i] for k, v in columns.items()} for i in range(n)}


def test_every_seed_agreeing_by_the_floor_holds():
    v = judge([Better("c", "r", AP)], seeds(c=[0.60, 0.62, 0.58], r=[0.55, 0.57, 0.55]))
    assert (v.holds, v.verdict) == (True, HOLDS)
    assert v.outcomes == {"0": ["agree"], "1": ["agree"], "2": ["agree"]}


def test_vacuous_near_zero_comparison_is_undetermined():
    # the old report's moving_camera_stabilised: 0.005 vs 0.001 — both below the AP floor of meaning
    v = judge([Better("ego", "2.5D", AP)], seeds(**{"ego": [0.005, 0.03, 0.04], "2.5D": [0.001, 0.0, 0.0]}))
    assert (v.holds, v.verdict) == (None, UNDETERMINED)
    assert "floor of meaning" in v.reason
    # two zeros are "within 0.1" of each other: vacuous too, not "holds"
    w = judge([WithinOf("a", "b", 0.1, AP)], seeds(a=[0.0, 0.01, 0.0], b=[0.0, 0.0, 0.02]))
    assert w.verdict == UNDETERMINED and w.outcomes["0"] == ["vacuous"]


def test_one_seed_disagreeing_does_not_hold():
    v = judge([Better("c", "r", AP)], seeds(c=[0.60, 0.62, 0.50], r=[0.55, 0.57, 0.55]))
    assert (v.holds, v.verdict) == (False, FAILS)
    assert "seed(s) 2" in v.reason and v.outcomes["2"] == ["disagree"]


def test_gap_below_the_floor_on_one_seed_does_not_hold():
    # right direction, but 0.01 < the 0.02 margin on seed 1
    v = judge([Better("c", "r", AP)], seeds(c=[0.60, 0.58, 0.60], r=[0.55, 0.57, 0.55]))
    assert v.verdict == FAILS and v.outcomes["1"] == ["disagree"]


def test_spread_larger_than_the_gap_does_not_hold():
    # the old report's detection_more_labels: 0.627 ± 0.014 vs 0.707 ± 0.105 "held" on means; per seed
    # the all-labels detector loses on one seed
    v = judge([Better("all", "few", AP)], seeds(all=[0.81, 0.60, 0.71], few=[0.64, 0.61, 0.63]))
    mean_all, mean_few = sum([0.81, 0.60, 0.71]) / 3, sum([0.64, 0.61, 0.63]) / 3
    assert mean_all - mean_few > 0.02          # the means alone would have said "holds"
    assert v.verdict == FAILS and v.outcomes["1"] == ["disagree"]


def test_negative_gain_does_not_hold_even_when_it_shrinks_less():
    # pretraining hurts at both budgets (gain −0.02 at few, −0.10 at all): "gain larger at few labels"
    # is true of the numbers, but there is no gain — the claim must not hold
    values = seeds(c_few=[0.50, 0.51, 0.49], n_few=[0.52, 0.53, 0.51], c_all=[0.60, 0.61, 0.59],
                   n_all=[0.70, 0.71, 0.69])
    derive(values, "gain_few", lambda c, n: c - n, "c_few", "n_few")
    derive(values, "gain_all", lambda c, n: c - n, "c_all", "n_all")
    v = judge([Positive("gain_few", AP, of=("c_few", "n_few")), Better("gain_few", "gain_all", GAIN)], values)
    assert v.verdict == FAILS
    assert all(row == ["disagree", "agree"] for row in v.outcomes.values())


def test_fewer_than_three_seeds_is_undetermined_whatever_they_show():
    v = judge([Better("c", "r", AP)], seeds(c=[0.9, 0.9], r=[0.1, 0.1]))
    assert (v.holds, v.verdict) == (None, UNDETERMINED) and "at least 3" in v.reason
    assert v.outcomes == {"0": ["agree"], "1": ["agree"]}   # still reported per seed


def test_quick_profile_gives_no_verdict():
    v = judge([Better("c", "r", AP)], seeds(c=[0.9, 0.9, 0.9], r=[0.1, 0.1, 0.1]), quick=True)
    assert (v.holds, v.verdict) == (None, NOT_JUDGED)


def test_missing_number_is_undetermined():
    v = judge([Better("c", "r", AP)], seeds(c=[0.9, None, 0.9], r=[0.1, 0.1, 0.1]))
    assert v.verdict == UNDETERMINED and "seed 1" in v.reason


def test_a_failing_seed_settles_it_whatever_else_is_missing():
    # seed 0 shows the other direction: "every seed agrees" is ruled out, whether or not seed 1 has its
    # number, and with two seeds as with three
    v = judge([Better("c", "r", AP)], seeds(c=[0.5, None, 0.9], r=[0.8, 0.1, 0.1]))
    assert (v.holds, v.verdict) == (False, FAILS) and v.outcomes["1"] == ["missing"]
    assert judge([Better("c", "r", AP)], seeds(c=[0.5, 0.9], r=[0.8, 0.1])).verdict == FAILS


def test_the_reason_names_each_conditions_own_failing_seeds():
    # seed 0 fails only the first condition, seeds 1 and 2 only the second
    values = seeds(c=[0.70, 0.90, 0.90], r=[0.80, 0.80, 0.80], n=[0.50, 0.85, 0.79])
    v = judge([Better("c", "r", AP), Better("r", "n", AP)], values)
    assert v.verdict == FAILS
    assert v.reason == "seed(s) 0 fail 'c > r by ≥ 0.02'; seed(s) 1, 2 fail 'r > n by ≥ 0.02'"


def test_lower_is_better_and_absolute_targets():
    assert judge([Better("c", "z", EPE)], seeds(c=[3.3, 3.5, 3.4], z=[7.0, 6.9, 7.1])).verdict == HOLDS
    assert judge([Better("c", "z", EPE)], seeds(c=[1.90, 1.85, 1.88], z=[1.89, 1.89, 1.89])).verdict == FAILS
    occ = seeds(occ=[0.97, 0.96, 0.951], free=[0.98, 0.99, 0.97])
    assert judge([AtLeast("occ", 0.95), AtLeast("free", 0.95)], occ).verdict == HOLDS
    occ["2"]["free"] = 0.949
    assert judge([AtLeast("occ", 0.95), AtLeast("free", 0.95)], occ).verdict == FAILS
    ego = seeds(m=[0.03, 0.035, 0.039], icp=[0.026, 0.026, 0.026])
    assert judge([RatioAtMost("m", "icp", 1.5)], ego).verdict == HOLDS
    ego["1"]["m"] = 0.04   # 0.04 > 1.5 × 0.026 = 0.039
    assert judge([RatioAtMost("m", "icp", 1.5)], ego).verdict == FAILS


def test_a_value_exactly_at_a_limit_passes_despite_float_round_off():
    """|0.3 − 0.4| is 0.10000000000000003 in floats: exactly the tolerance, so within it, as Better's margins
    allow; and numpy scalars are numbers."""
    import numpy as np

    near = seeds(m=[0.3, 0.3, 0.3], g=[0.4, 0.4, 0.4])
    assert judge([WithinOf("m", "g", 0.1, AP)], near).verdict == HOLDS
    near["1"]["m"] = 0.29
    assert judge([WithinOf("m", "g", 0.1, AP)], near).verdict == FAILS
    assert judge([RatioAtMost("m", "icp", 1.5)], seeds(m=[0.3, 0.3, 0.3], icp=[0.2, 0.2, 0.2])).verdict == HOLDS
    assert judge([AtLeast("occ", 0.95)], seeds(occ=[0.19 * 5] * 3)).verdict == HOLDS  # 0.9499999999999998
    typed = seeds(occ=[0.96, 0.97, 0.98])
    typed["0"]["occ"] = np.float32(0.96)
    assert judge([AtLeast("occ", 0.95)], typed).verdict == HOLDS


def _result(c_few, r_few, n_few, c_all, n_all, *, ret=(0.30, 0.10), epe=(3.3, 5.5, 7.0)):
    det = {"random/finetuned/2": n_few, "random/finetuned/all": n_all, "regression/finetuned/2": r_few,
           "regression/finetuned/all": 0.5, "contrastive/finetuned/2": c_few, "contrastive/finetuned/all": c_all}
    return {
        "detection": {k: {"map": {"0.5": v}} for k, v in det.items()},
        "retrieval": {arm: {d: {"p@1": p} for d in ("2d", "3d")}
                      for arm, p in (("contrastive", ret[0]), ("regression", ret[1]), ("random", 0.0))},
        "flow": {"contrastive": {"model": {"epe_l1_moving": epe[0]}, "zero_motion": {"epe_l1_moving": epe[2]}},
                 "regression": {"model": {"epe_l1_moving": epe[1]}}},
        "moving": {"static": {"contrastive, GT egomotion": {"ap": 0.5}, "2.5D Farneback": {"ap": 0.3},
                              "regression, GT egomotion": {"ap": 0.2}},
                   "moving": {"contrastive, egomotion module": {"ap": 0.005}, "contrastive, GT egomotion": {"ap": 0.0},
                              "2.5D Farneback": {"ap": 0.001}, "2.5D Farneback stabilised": {"ap": 0.002}}},
        # the claim reads the occupancy module; a pretraining head's better scores must not count
        "occupancy": {"contrastive, occupancy module, balanced threshold":
                      {"acc_occupied": 0.97, "acc_free": 0.90, "acc_all": 0.95, "threshold": 0.4},
                      "contrastive, occupancy module, threshold 0.5": {"acc_occupied": 0.99, "acc_free": 0.99},
                      "contrastive, pretraining head": {"acc_occupied": 0.99, "acc_free": 0.99, "acc_all": 0.99}},
        "egomotion": {"methods": {"model": {"rot_err_rad_mean": 0.1, "trans_err_m_mean": 0.04},
                                  "icp": {"rot_err_rad_mean": 0.09, "trans_err_m_mean": 0.04},
                                  "untrained module": {"rot_err_rad_mean": 0.5, "trans_err_m_mean": 0.4}}},
    }


def test_check_claims_judges_per_seed_results():
    per_seed = {"0": _result(0.60, 0.50, 0.40, 0.70, 0.65), "1": _result(0.62, 0.52, 0.41, 0.71, 0.66),
                "2": _result(0.61, 0.51, 0.39, 0.72, 0.64)}
    claims = {c["id"]: c for c in check_claims(per_seed, budgets=["2", "all"])}
    assert claims["detection_few_labels"]["verdict"] == HOLDS
    assert claims["detection_more_labels"]["verdict"] == HOLDS
    assert claims["detection_gain_low_data"]["verdict"] == HOLDS      # gains 0.2 at 2, 0.05 at all
    assert claims["retrieval_2d"]["verdict"] == HOLDS and claims["flow_vs_zero_motion"]["verdict"] == HOLDS
    assert claims["flow_contrastive_vs_regression"]["verdict"] == HOLDS
    assert claims["moving_static_vs_2p5d"]["verdict"] == HOLDS
    assert claims["moving_camera_stabilised"]["verdict"] == UNDETERMINED   # 0.005 / 0.000 / 0.001: vacuous
    assert claims["occupancy_accuracy"]["verdict"] == FAILS               # free 0.90 < 0.95
    assert claims["egomotion_vs_icp"]["verdict"] == HOLDS                 # 0.1 ≤ 1.5·0.09, 0.04 ≤ 1.5·0.04
    few = claims["detection_few_labels"]
    assert few["per_seed"]["1"] == {"contrastive": 0.62, "regression": 0.52, "random": 0.41}
    assert "0.610 ± 0.008 [0.600, 0.620, 0.610]" in few["ours"]           # mean ± std beside each seed
    assert few["holds"] is True and claims["moving_camera_stabilised"]["holds"] is None


def test_detection_claims_read_the_papers_protocol_frozen_pretrained_arms_and_random_end_to_end():
    # fine-tuned, contrastive leads; frozen (the paper's protocol: features frozen after pretraining),
    # regression leads: the claim reads the frozen rows, and random init's end-to-end row
    per_seed = {}
    for seed in ("0", "1", "2"):
        r = _result(0.70, 0.60, 0.40, 0.90, 0.85)
        r["detection"].update({k: {"map": {"0.5": v}} for k, v in {
            "contrastive/frozen/2": 0.55, "regression/frozen/2": 0.65, "random/frozen/2": 0.10,
            "contrastive/frozen/all": 0.95, "regression/frozen/all": 0.9, "random/frozen/all": 0.2}.items()})
        per_seed[seed] = r
    claims = {c["id"]: c for c in check_claims(per_seed, budgets=["2", "all"])}
    few = claims["detection_few_labels"]
    assert few["per_seed"]["0"] == {"contrastive": 0.55, "regression": 0.65, "random": 0.40}
    assert few["verdict"] == FAILS and "regression/frozen" in few["criterion"] and "random/finetuned" in few["criterion"]
    gain = claims["detection_gain_low_data"]["per_seed"]["0"]
    assert math.isclose(gain["gain@2"], 0.55 - 0.40) and math.isclose(gain["gain@all"], 0.95 - 0.85)
    # a plan without frozen rows falls back to the fine-tuned ones
    only_finetuned = check_claims({s: _result(0.70, 0.60, 0.40, 0.90, 0.85) for s in "012"}, budgets=["2", "all"])
    assert next(c for c in only_finetuned if c["id"] == "detection_few_labels")["per_seed"]["0"]["contrastive"] == 0.70


def test_check_claims_one_flipped_seed_and_quick():
    per_seed = {"0": _result(0.60, 0.50, 0.40, 0.70, 0.65), "1": _result(0.40, 0.50, 0.60, 0.71, 0.66),
                "2": _result(0.61, 0.51, 0.39, 0.72, 0.64)}
    claims = {c["id"]: c for c in check_claims(per_seed, budgets=["2", "all"])}
    assert claims["detection_few_labels"]["verdict"] == FAILS and "seed(s) 1" in claims["detection_few_labels"]["reason"]
    quick = check_claims(per_seed, budgets=["2", "all"], quick=True)
    assert {c["holds"] for c in quick} == {None} and {c["verdict"] for c in quick} == {NOT_JUDGED}


@pytest.mark.parametrize("n", [1, 2])
def test_check_claims_with_too_few_seeds_never_holds(n):
    per_seed = {str(i): _result(0.60, 0.50, 0.40, 0.70, 0.65) for i in range(n)}
    claims = check_claims(per_seed, budgets=["2", "all"])
    # a claim some seed contradicts does not hold; every other one is undetermined, never "holds"
    for c in claims:
        disagrees = any("disagree" in row for row in c["outcomes"].values())
        assert c["verdict"] == (FAILS if disagrees else UNDETERMINED), c["id"]
    assert {c["verdict"] for c in claims} == {FAILS, UNDETERMINED}


def test_a_claim_the_plan_cannot_test_is_undetermined_and_still_counted():
    good = {s: _result(0.60, 0.50, 0.40, 0.70, 0.65) for s in "012"}
    full_plan = {c["id"] for c in check_claims(good, budgets=["2", "all"])}
    assert len(full_plan) == 12
    # one label budget: "more labels" and "gain at few labels" compare a budget with itself (a difference of 0,
    # which would read as three disagreeing seeds); they are untestable, the few-label claim is not
    one_budget = {c["id"]: c for c in check_claims(good, budgets=["2"])}
    assert set(one_budget) == full_plan
    for cid in ("detection_more_labels", "detection_gain_low_data"):
        c = one_budget[cid]
        assert (c["holds"], c["verdict"]) == (None, UNDETERMINED) and "one label budget (2)" in c["reason"]
        assert c["outcomes"] == {s: ["missing"] * len(c["outcomes"][s]) for s in "012"}
    assert one_budget["detection_few_labels"]["verdict"] == HOLDS
    # no regression detector: the three-arm claim is untestable, the random-only one still judged
    no_regression = {c["id"]: c for c in check_claims(good, budgets=["2", "all"], variants=[
        "random/finetuned", "contrastive/finetuned"])}
    assert no_regression["detection_few_labels"]["verdict"] == UNDETERMINED
    assert "no detector of the regression arm" in no_regression["detection_few_labels"]["reason"]
    assert no_regression["detection_more_labels"]["verdict"] == HOLDS
    # no egomotion results: the claim stays listed, undetermined
    for r in good.values():
        del r["egomotion"]
    ego = next(c for c in check_claims(good, budgets=["2", "all"]) if c["id"] == "egomotion_vs_icp")
    assert ego["verdict"] == UNDETERMINED and "lacks a number" in ego["reason"]


def test_each_claim_reads_its_own_rows_not_their_neighbours():
    # Every claim holds on the rows it should read; each decoy beside them (another mode, dimension, camera
    # setting, method, or the two sides swapped) would make it fail.
    def result() -> dict:
        r = _result(0.60, 0.50, 0.40, 0.70, 0.65, ret=(0.30, 0.10))
        r["detection"].update({"random/frozen/2": {"map": {"0.5": 0.90}},        # decoy: the claims read
                               "random/frozen/all": {"map": {"0.5": 0.10}}})     # random init end to end
        r["retrieval"]["contrastive"]["2d"]["p@1"] = 0.05                       # 2D fails, 3D holds
        r["moving"] = {
            "static": {"contrastive, GT egomotion": {"ap": 0.50}, "regression, GT egomotion": {"ap": 0.20},
                       "contrastive, egomotion module": {"ap": 0.10}, "2.5D Farneback": {"ap": 0.30},
                       "2.5D Farneback stabilised": {"ap": 0.70}},
            # module within 0.1 of the true poses and ahead of 2.5D by 0.03 and of stabilised 2.5D by 0.05; swapped
            # with the true poses' row it would lead 2.5D by only 0.01; the static setting's stabilised row would fail
            "moving": {"contrastive, egomotion module": {"ap": 0.63}, "contrastive, GT egomotion": {"ap": 0.61},
                       "2.5D Farneback": {"ap": 0.60}, "2.5D Farneback stabilised": {"ap": 0.58},
                       "regression, GT egomotion": {"ap": 0.90}}}
        # rotation and translation on different scales: swapping model and ICP, or R and t, fails
        r["egomotion"] = {"methods": {"model": {"rot_err_rad_mean": 0.001, "trans_err_m_mean": 0.02},
                                      "icp": {"rot_err_rad_mean": 0.010, "trans_err_m_mean": 0.03},
                                      "untrained module": {"rot_err_rad_mean": 0.2, "trans_err_m_mean": 0.3}}}
        return r

    claims = {c["id"]: c for c in check_claims({s: result() for s in "012"}, budgets=["2", "all"])}
    assert claims["detection_more_labels"]["verdict"] == HOLDS          # random/finetuned 0.65 > 0.40
    assert claims["retrieval_3d"]["verdict"] == HOLDS and claims["retrieval_2d"]["verdict"] == FAILS
    assert claims["moving_static_vs_regression"]["verdict"] == HOLDS    # static 0.50 vs 0.20 (moving: 0.61 vs 0.90)
    assert claims["moving_static_vs_2p5d"]["per_seed"]["0"] == {"contrastive": 0.50, "2.5D": 0.30, "regression": 0.20,
                                                                "2.5D, true 2D flow": None}   # shown, not judged
    assert claims["moving_camera_stabilised"]["verdict"] == HOLDS
    assert claims["egomotion_vs_icp"]["verdict"] == HOLDS
    assert claims["egomotion_vs_icp"]["per_seed"]["0"] == {"model R": 0.001, "ICP R": 0.010, "model t": 0.02,
                                                           "ICP t": 0.03, "untrained R": 0.2, "untrained t": 0.3}


def test_a_claim_an_untrained_control_also_meets_tests_no_training():
    """egomotion_vs_icp: the module's last stage has no weights, and untrained it reached ICP (session 25). When
    the untrained module is on par too, the claim is undetermined: it says nothing about the training. When the
    control misses either bound, the trained module's being on par is training's doing: the claim holds."""
    def per_seed(untrained_r: float, untrained_t: float) -> dict:
        def one() -> dict:
            r = _result(0.60, 0.50, 0.40, 0.70, 0.65)
            r["egomotion"]["methods"]["untrained module"] = {"rot_err_rad_mean": untrained_r,
                                                             "trans_err_m_mean": untrained_t}
            return r
        return {s: one() for s in "012"}

    def ego(untrained_r: float, untrained_t: float) -> dict:
        return next(c for c in check_claims(per_seed(untrained_r, untrained_t), budgets=["2", "all"])
                    if c["id"] == "egomotion_vs_icp")

    on_par_untrained = ego(0.09, 0.04)           # the model's 0.1 / 0.04 against ICP's 0.09 / 0.04
    assert on_par_untrained["verdict"] == UNDETERMINED
    assert "untrained control meets the claim too" in on_par_untrained["reason"]
    assert on_par_untrained["outcomes"]["0"] == ["agree", "agree", "vacuous"]
    assert ego(0.09, 0.2)["verdict"] == HOLDS     # untrained off in translation: training brings that
    assert ego(0.5, 0.04)["verdict"] == HOLDS     # untrained off in rotation
    missing = per_seed(0.5, 0.4)
    del missing["1"]["egomotion"]["methods"]["untrained module"]
    ego_missing = next(c for c in check_claims(missing, budgets=["2", "all"]) if c["id"] == "egomotion_vs_icp")
    assert ego_missing["verdict"] == UNDETERMINED and ego_missing["reason"].startswith("seed 1 lacks a number")


def test_a_gain_at_full_labels_between_saturated_detectors_decides_nothing():
    """detection_gain_low_data: with all labels both detectors at mAP ≥ 0.98 leave a gain of ~0 there by
    construction, so "largest at few labels" would follow from the few-label gain alone: undetermined."""
    saturated = {s: _result(0.60, 0.50, 0.40, 0.995, 0.99) for s in "012"}
    claim = next(c for c in check_claims(saturated, budgets=["2", "all"]) if c["id"] == "detection_gain_low_data")
    assert claim["verdict"] == UNDETERMINED and "saturated" in claim["reason"]
    assert claim["outcomes"]["0"] == ["agree", "agree", "vacuous"]
    room = {s: _result(0.60, 0.50, 0.40, 0.995, 0.90) for s in "012"}    # random-init still short of the ceiling
    assert next(c for c in check_claims(room, budgets=["2", "all"])
                if c["id"] == "detection_gain_low_data")["verdict"] == HOLDS


def test_with_three_budgets_the_few_label_gain_is_compared_with_the_next_budget_up():
    """Budgets 2, 8, all: the gain at 2 labels against the gain at 8 (with all labels every detector saturates);
    a saturated 8-label pair is still undetermined."""
    def result(c8: float, r8: float) -> dict:
        r = _result(0.60, 0.50, 0.40, 1.0, 0.999)
        r["detection"]["contrastive/finetuned/8"] = {"map": {"0.5": c8}}
        r["detection"]["random/finetuned/8"] = {"map": {"0.5": r8}}
        return r

    def gain_claim(c8: float, r8: float) -> dict:
        return next(c for c in check_claims({s: result(c8, r8) for s in "012"}, budgets=["2", "8", "all"])
                    if c["id"] == "detection_gain_low_data")

    held = gain_claim(0.90, 0.86)                 # gain 0.2 at 2 labels against 0.04 at 8
    assert held["verdict"] == HOLDS and set(held["per_seed"]["0"]) >= {"gain@2", "gain@8"}
    assert "gain@all" not in held["per_seed"]["0"]
    assert gain_claim(0.90, 0.60)["verdict"] == FAILS          # gain 0.3 at 8 labels: larger than at 2
    assert gain_claim(0.99, 0.985)["verdict"] == UNDETERMINED  # both saturated at 8 labels too


def test_each_claims_per_seed_list_is_in_the_outcome_tables_seed_order():
    """The '[…]' of a claim's figures is unlabelled: it must follow the report's seed columns (numeric order), not
    the order the seeds were run in."""
    per_seed = {"10": _result(0.60, 0.50, 0.40, 0.70, 0.65, ret=(0.31, 0.10)),
                "2": _result(0.60, 0.50, 0.40, 0.70, 0.65, ret=(0.22, 0.10))}
    retrieval = next(c for c in check_claims(per_seed, budgets=["2", "all"]) if c["id"] == "retrieval_3d")
    assert list(retrieval["per_seed"]) == ["2", "10"]
    assert "contrastive 0.265 ± " in retrieval["ours"] and "[0.220, 0.310]" in retrieval["ours"]
