"""The two pretraining arms train the same fixed number of steps in every preset's plan (services/bench/plan.py,
`_pretraining`): the claims compare the objectives, and a plateau rule on each arm's own held-out loss let the
noisier contrastive loss stop its arm at a third of regression's steps (docs/findings.md)."""

from __future__ import annotations

import pytest

from services.bench.plan import PRETRAINED_ARMS, plan_for
from services.bench.replan import _dry_run

# The plateau bounds the presets' pretrainings had before the fixed rule: the fixed length is that bound.
BOUNDS = {"tiny": 1500, "small": 3000, "paper": 200_000}


@pytest.mark.parametrize("preset", sorted(BOUNDS))
def test_each_preset_pretrains_both_arms_a_fixed_equal_length(preset, tmp_path):
    plan = plan_for(preset)
    stages = _dry_run(plan, tmp_path)   # the specs each stage would run with (nothing is run or written)
    rules = [stages.specs[f"seed0/pretrain_{arm}"]["rule"] for arm in PRETRAINED_ARMS]
    assert rules[0] == rules[1], "the arms' pretraining rules differ"
    assert rules[0]["kind"] == "fixed"
    assert rules[0]["min_steps"] == rules[0]["max_steps"] == BOUNDS[preset]
    assert not list(tmp_path.iterdir()), "a dry run wrote to the work directory"


def test_the_other_stages_keep_their_held_out_rules():
    rules = plan_for("small").rules
    assert {rules.flow.kind, rules.egomotion.kind, rules.occupancy.kind} == {"plateau"}
    assert rules.detector.kind == "epochs"


def test_each_seed_trains_its_flows_right_after_its_pretrainings(tmp_path):
    # the flow claims are what a change of the pretrainings is for: a regeneration answers them first
    names = [n for n in _dry_run(plan_for("small"), tmp_path).inputs if n.startswith("seed0/")]
    trained = [n for n in names if "/eval/" not in n]
    assert trained[:5] == ["seed0/pretrain_regression", "seed0/pretrain_contrastive", "seed0/flow_regression",
                           "seed0/flow_contrastive", "seed0/flow_volume"]
