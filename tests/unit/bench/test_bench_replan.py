"""`bench paper --rerun-changed`: which stages a changed plan touches (services.bench.replan), found by
walking both plans dry. The expected sets are written out by hand from the stage graph in
services/bench/paper.py's docstring: that list is the slow, obvious reference."""

from __future__ import annotations

from dataclasses import replace

import pytest

from services.bench.plan import plan_for, with_steps
from services.bench.plan import BenchConfigError
from services.bench.replan import (
    _dry_run, changed_stages, forget_changed, forget_matching, matching_and_downstream, stage_digests,
)
from services.bench.stages import StageRunner, stage_digest



def _detectors(plan) -> set[str]:
    """Draw 0 of a budget is named as before label draws existed; the smallest budget's further draws add
    `_draw<d>`."""
    few = min(b for b in plan.label_budgets if b is not None)
    return {f"detector_{arm}_{mode}_L{'all' if budget is None else budget}" + (f"_draw{d}" if d else "")
            for arm, mode in plan.detector_variants for budget in plan.label_budgets
            for d in range(plan.label_draws if budget == few else 1)}


@pytest.fixture
def plan():
    return plan_for("tiny", quick=True, seeds=(0,))


def _with_options(plan, **options):
    return replace(plan, task_options={**plan.task_options, **options})


def test_digest_is_canonical_and_depends_on_spec_and_inputs():
    assert stage_digest({"a": 1, "b": [1, 2]}, ["x"]) == stage_digest({"b": [1, 2], "a": 1}, ["x"])
    assert stage_digest({"a": 1}, ["x"]) != stage_digest({"a": 2}, ["x"])
    assert stage_digest({"a": 1}, ["x"]) != stage_digest({"a": 1}, ["y"])
    assert stage_digest({"a": 1}, ["x", "y"]) != stage_digest({"a": 1}, ["y", "x"])


def test_dry_runner_records_without_running_or_writing(tmp_path):
    stages = StageRunner(tmp_path / "work", log=lambda _: None, dry=True)
    ran = []
    stages.run("a", "done", lambda d: ran.append(d), spec={"k": 1})
    stages.run("b", "done", lambda d: ran.append(d), after=["a"])
    assert ran == [] and not (tmp_path / "work").exists() and set(stages.digests) == {"a", "b"}
    assert stages.name_of(tmp_path / "work" / "b" / "selected") == "b"
    with pytest.raises(KeyError):
        stages.name_of(tmp_path / "work" / "c")


def test_every_stage_has_a_digest_and_an_unchanged_plan_changes_nothing(plan, tmp_path):
    digests = stage_digests(plan, tmp_path)
    trained = {"pretrain_regression", "pretrain_contrastive", "occupancy_contrastive", "flow_regression",
               "flow_contrastive", "flow_volume", "egomotion", *_detectors(plan)}
    assert {n for n in digests if n.startswith("seed0/") and "/eval/" not in n} == {f"seed0/{t}" for t in trained}
    assert len(set(digests.values())) == len(digests)  # no two stages alike
    assert changed_stages(plan, plan, tmp_path) == []
    # the device is no part of a stage's identity
    assert changed_stages(plan, replace(plan, device="cuda"), tmp_path) == []
    # nor are the Ray workers, but for the detectors whose labels they must share: 2 labels on 2 workers
    # train one record per worker and step (BatchNorm sees one), so those stages and their scores change
    assert sorted(changed_stages(plan, replace(plan, workers=2), tmp_path)) == sorted(
        f"seed0/{prefix}{arm}_{mode}_L2{draw}" for prefix in ("detector_", "eval/detection/")
        for arm, mode in plan.detector_variants for draw in ("", "_draw1"))


def test_a_feature_flow_option_touches_the_arms_flow_and_what_reads_it(plan, tmp_path):
    new = _with_options(plan, flow_features={"refine_radius": [2, 1, 2]})
    assert sorted(changed_stages(plan, new, tmp_path)) == sorted(
        ["seed0/flow_regression", "seed0/flow_contrastive", "seed0/eval/flow/regression",
         "seed0/eval/flow/contrastive", "seed0/eval/moving/all"])


def test_a_pretraining_option_touches_everything_downstream_of_pretraining(plan, tmp_path):
    changed = set(changed_stages(plan, _with_options(plan, pretrain={"coeff_match": 0.5}), tmp_path))
    untouched = {"data/train", "data/test", "data/val", "seed0/egomotion", "seed0/eval/egomotion/moving_camera",
                 "seed0/eval/retrieval/random", "seed0/detector_random_finetuned_L2",
                 "seed0/detector_random_finetuned_Lall", "seed0/eval/detection/random_finetuned_L2",
                 "seed0/eval/detection/random_finetuned_Lall", "seed0/detector_random_finetuned_L2_draw1",
                 "seed0/eval/detection/random_finetuned_L2_draw1"}
    assert changed == set(stage_digests(plan, tmp_path)) - untouched


def test_more_label_draws_add_stages_and_keep_every_existing_one(plan, tmp_path):
    """A benchmark run with one draw, continued with `--label-draws 2 --rerun-changed`, keeps all its stages
    (draw 0's digests are those of before draws existed) and only adds the new draws' detectors and evaluations."""
    one, two = replace(plan, label_draws=1), replace(plan, label_draws=2)
    before, after = stage_digests(one, tmp_path), stage_digests(two, tmp_path)
    assert all(after[name] == digest for name, digest in before.items())
    added = set(after) - set(before)
    assert added == {f"seed0/{d}" for d in _detectors(two) - _detectors(one)} | {
        f"seed0/eval/detection/{d[len('detector_'):]}" for d in _detectors(two) - _detectors(one)}
    assert len(added) == 2 * len(plan.detector_variants)              # draw 1: a detector + its evaluation
    # the "changed" stages are exactly the added ones, which have no directory yet: nothing is redone
    assert sorted(changed_stages(one, two, tmp_path)) == sorted(added)
    assert sorted(changed_stages(two, one, tmp_path)) == sorted(added)   # fewer draws: the dropped ones go


def test_rules_and_evaluation_settings_touch_only_their_stages(plan, tmp_path):
    assert sorted(changed_stages(plan, with_steps(plan, egomotion=3), tmp_path)) == [
        "seed0/egomotion", "seed0/eval/egomotion/moving_camera", "seed0/eval/moving/all"]
    assert changed_stages(plan, replace(plan, moving_iou=0.25), tmp_path) == ["seed0/eval/moving/all"]
    assert sorted(changed_stages(plan, replace(plan, retrieval_cube=5), tmp_path)) == [
        f"seed0/eval/retrieval/{arm}" for arm in ("contrastive", "random", "regression")]
    # more test records: every evaluation, no training
    changed = changed_stages(plan, replace(plan, test_episodes=plan.test_episodes + 1), tmp_path)
    assert "data/test" in changed and all(n == "data/test" or "/eval/" in n for n in changed)
    assert len(changed) == 1 + sum("/eval/" in n for n in stage_digests(plan, tmp_path))


def test_forget_changed_deletes_only_the_touched_stages_that_exist(plan, tmp_path):
    for name in ("seed0/flow_contrastive", "seed0/pretrain_contrastive", "seed0/eval/flow/contrastive"):
        (tmp_path / name).mkdir(parents=True)
        (tmp_path / name / "metrics.json").write_text("{}")
    lines = []
    removed = forget_changed(plan, _with_options(plan, flow_features={"refine_radius": [2, 1, 2]}), tmp_path,
                             lines.append)
    assert removed == ["seed0/flow_contrastive", "seed0/eval/flow/contrastive"]
    assert not (tmp_path / "seed0/flow_contrastive").exists() and (tmp_path / "seed0/pretrain_contrastive").exists()
    assert "2 finished or started stage(s) redone" in lines[-1]


def test_seeds_outside_this_run_and_stages_the_new_plan_drops_are_covered(plan, tmp_path):
    # seed 1 ran under the old plan and is not in this run: its touched stages go too (a later run with the
    # new plan and seeds 0, 1 would otherwise skip them and mix the plans)
    (tmp_path / "seed1").mkdir()
    new = _with_options(plan, flow_features={"refine_radius": [2, 1, 2]})
    assert "seed1/flow_contrastive" in changed_stages(plan, new, tmp_path)
    # a label budget dropped: its detectors and their evaluations are stages the new plan no longer has
    fewer = replace(plan, label_budgets=(None,))
    dropped = set(changed_stages(plan, fewer, tmp_path))
    assert dropped == {f"seed{s}/{d}" for s in (0, 1) for d in _detectors(plan) if "_L2" in d} | {
        f"seed{s}/eval/detection/{d[len('detector_'):]}" for s in (0, 1) for d in _detectors(plan) if "_L2" in d}


def _downstream_slow(inputs: dict, start: set) -> set:
    """Every stage reading (directly or through others) a stage of `start`, and `start`: a fixpoint loop."""
    chosen = set(start)
    while True:
        more = {n for n, ins in inputs.items() if chosen.intersection(ins)} - chosen
        if not more:
            return chosen
        chosen |= more


def test_redo_names_the_matching_stages_and_everything_downstream(plan, tmp_path):
    inputs = _dry_run(plan, tmp_path).inputs
    redo = matching_and_downstream(plan, tmp_path, ["seed*/egomotion"])
    assert set(redo) == _downstream_slow(inputs, {"seed0/egomotion"})
    assert redo[0] == "seed0/egomotion" and "seed0/eval/moving/all" in redo   # the pipeline reads the module
    assert not any("pretrain" in n or "detector" in n for n in redo)
    assert redo == [n for n in inputs if n in set(redo)]                        # in the plan's order
    # a pretraining reaches almost everything of its seed; an evaluation only itself
    pretrain = matching_and_downstream(plan, tmp_path, ["seed0/pretrain_contrastive"])
    assert set(pretrain) == _downstream_slow(inputs, {"seed0/pretrain_contrastive"}) and len(pretrain) > 10
    evals = matching_and_downstream(plan, tmp_path, ["seed0/eval/occupancy/*"])
    assert evals and all(n.startswith("seed0/eval/occupancy/") for n in evals)
    with pytest.raises(BenchConfigError, match="'seed0/nothing'"):
        matching_and_downstream(plan, tmp_path, ["seed*/egomotion", "seed0/nothing"])


def test_forget_matching_deletes_the_named_and_downstream_stages_of_every_seed_on_disk(plan, tmp_path):
    for name in ("seed0/egomotion", "seed0/eval/moving/all", "seed0/flow_volume", "seed1/egomotion"):
        (tmp_path / name).mkdir(parents=True)
        (tmp_path / name / "metrics.json").write_text("{}")
    lines = []
    removed = forget_matching(plan, tmp_path, ["seed*/egomotion"], lines.append)   # the plan has seed 0 only
    assert removed == ["seed0/egomotion", "seed0/eval/moving/all", "seed1/egomotion"]
    assert (tmp_path / "seed0/flow_volume").exists() and not (tmp_path / "seed1/egomotion").exists()
    assert "3 finished or started stage(s) redone" in lines[-1]
