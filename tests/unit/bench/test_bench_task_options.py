"""BenchConfig.task_options: per-stage-kind task options of `bench paper`, checked, merged and recorded."""

import json

import pytest

from services.bench.paper import _check_same_plan
from services.bench.plan import BenchConfig, BenchConfigError, plan_for
from services.cli.main import main

OPTIONS = {"mapper": {"encoder_full_res": 16}, "pretrain": {"coeff_match": 1.0},
           "flow_features": {"refine_radius": [3, 1, 3], "encoder_full_res": 8}}


def test_stage_options_merge_mapper_then_kind_then_protocol():
    config = plan_for("tiny", quick=True, task_options=OPTIONS)
    assert config.stage_options("pretrain", {"objective": "contrastive"}) == {
        "encoder_full_res": 16, "coeff_match": 1.0, "objective": "contrastive"}
    # the kind's own value wins over the mapper's; the protocol's are added last
    assert config.stage_options("flow_features", {"inputs": "features"}) == {
        "encoder_full_res": 8, "refine_radius": [3, 1, 3], "inputs": "features"}
    assert config.stage_options("flow_volume", {"inputs": "volume"}) == {"encoder_full_res": 16, "inputs": "volume"}
    assert plan_for("tiny", quick=True).stage_options("detector", {"labels": None}) == {"labels": None}


def test_contrastive_only_options_reach_the_contrastive_pretraining_only():
    options = {"mapper": {"encoder_full_res": 16}, "pretrain": {"coeff_match": 1.0},
               "pretrain_contrastive": {"shift_positives": 3, "coeff_local_negatives": 0.5}}
    config = plan_for("tiny", quick=True, task_options=options)
    assert config.stage_options("pretrain", {"objective": "contrastive"}) == {
        "encoder_full_res": 16, "coeff_match": 1.0, "shift_positives": 3, "coeff_local_negatives": 0.5,
        "objective": "contrastive"}
    assert config.stage_options("pretrain", {"objective": "regression"}) == {
        "encoder_full_res": 16, "coeff_match": 1.0, "objective": "regression"}
    for kind in ("occupancy", "detector", "flow_features"):
        assert "shift_positives" not in config.stage_options(kind, {})


def test_a_contrastive_only_option_redoes_the_contrastive_arm_only(tmp_path):
    from services.bench.replan import stage_digests

    base = plan_for("tiny", quick=True, seeds=(0,), task_options={"pretrain": {"coeff_match": 1.0}})
    shifted = plan_for("tiny", quick=True, seeds=(0,), task_options={
        "pretrain": {"coeff_match": 1.0}, "pretrain_contrastive": {"shift_positives": 3}})
    old, new = stage_digests(base, tmp_path), stage_digests(shifted, tmp_path)
    changed = {name for name in old if old[name] != new[name]}
    assert "seed0/pretrain_contrastive" in changed and "seed0/flow_contrastive" in changed
    assert not any("regression" in name or "random" in name for name in changed), sorted(changed)
    assert "seed0/pretrain_regression" in old


def test_task_options_round_trip_and_old_plans_read_as_none():
    config = plan_for("tiny", quick=True, task_options=OPTIONS)
    assert BenchConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    old = plan_for("tiny", quick=True).to_dict()
    del old["task_options"]
    assert BenchConfig.from_dict(old).task_options == {}


@pytest.mark.parametrize("options, message", [
    ({"flow": {"radius": [2, 1, 2]}}, "unknown stage kind 'flow'"),
    ({"pretrain": [1]}, "must be an object"),
    ({"pretrain": {"objective": "regression"}}, "'objective'"),
    ({"flow_features": {"inputs": "volume"}}, "'inputs'"),
    ({"pretrain": {"shift_positives": 3}}, r"\['shift_positives'\]: contrastive-only.*pretrain_contrastive"),
    ({"pretrain": {"coeff_local_negatives": 1.0}}, r"\['coeff_local_negatives'\]: contrastive-only"),
    ({"mapper": {"local_negative_radius": 3}}, r"\['local_negative_radius'\]: contrastive-only"),
    # one arm gets nothing both arms have: that would compare recipes, not objectives
    ({"pretrain_contrastive": {"coeff_match": 1.0, "shift_positives": 3}},
     r"pretrain_contrastive'\] sets \['coeff_match'\]"),
    ({"pretrain_contrastive": {"objective": "regression"}}, "'objective'"),
])
def test_bad_task_options_are_refused_by_name(options, message):
    with pytest.raises(BenchConfigError, match=message):
        plan_for("tiny", quick=True, task_options=options)


def test_a_rerun_must_keep_the_task_options(tmp_path):
    plan = tmp_path / "work" / "plan.json"
    plan.parent.mkdir(parents=True)
    plain = plan_for("tiny", quick=True)
    old = plain.to_dict()
    del old["task_options"]  # written before the option existed: the tasks' defaults
    plan.write_text(json.dumps(old))
    _check_same_plan(plan, plain)
    with pytest.raises(BenchConfigError, match="task_options"):
        _check_same_plan(plan, plan_for("tiny", quick=True, task_options=OPTIONS))


def test_cli_task_options_reach_the_plan_and_bad_json_names_the_flag(tmp_path, monkeypatch, capsys):
    import services.bench.paper as paper

    seen = {}

    def fake_run(config, out, **kw):
        seen["config"] = config
        return {"claims": []}

    monkeypatch.setattr(paper, "run_paper_bench", fake_run)
    base = ["bench", "paper", "--quick", "--seeds", "1", "--out", str(tmp_path / "r")]
    assert main(base + ["--task-options", json.dumps(OPTIONS)]) == 0
    assert seen["config"].task_options == OPTIONS
    for bad, why in (("{not json", "not JSON"), ("[1, 2]", "JSON object")):
        with pytest.raises(SystemExit) as stop:
            main(base + ["--task-options", bad])
        err = capsys.readouterr().err
        assert stop.value.code == 2 and "--task-options" in err and why in err
    assert main(base + ["--task-options", '{"flow": {}}']) != 0  # a BenchConfigError: one line, no traceback
    assert "unknown stage kind 'flow'" in capsys.readouterr().err


def test_occupancy_stage_gets_the_mapper_options_and_its_own():
    config = plan_for("tiny", quick=True, task_options={"mapper": {"encoder_full_res": 16},
                                                        "occupancy": {"input_views": 1}})
    assert config.stage_options("occupancy", {}) == {"encoder_full_res": 16, "input_views": 1}


def test_every_stage_with_a_rule_has_a_steps_flag(tmp_path, monkeypatch):
    import services.bench.paper as paper
    from services.bench.plan import STAGE_NAMES, StageRule
    from services.cli.bench import STAGE_NAMES as CLI_STAGE_NAMES

    assert set(CLI_STAGE_NAMES) == set(STAGE_NAMES) == set(plan_for("small").rules.to_dict())
    seen = {}
    monkeypatch.setattr(paper, "run_paper_bench", lambda config, out, **kw: seen.update(config=config) or {"claims": []})
    assert main(["bench", "paper", "--seeds", "1", "--out", str(tmp_path / "r"), "--occupancy-steps", "7"]) == 0
    # the length is fixed; the stage's weight average stays
    assert seen["config"].rules.occupancy == StageRule.fixed(7, ema_decay=0.995)
    assert seen["config"].rules.flow == plan_for("small").rules.flow


def test_a_plan_without_the_occupancy_rule_is_refused_by_name():
    old = plan_for("tiny", quick=True).to_dict()
    del old["rules"]["occupancy"]
    with pytest.raises(BenchConfigError, match="occupancy"):
        BenchConfig.from_dict(old)


def test_contrastive_only_options_switched_off_are_accepted():
    plan = plan_for("tiny", quick=True, task_options={"pretrain": {"shift_positives": 0, "coeff_local_negatives": 0.0}})
    assert plan.stage_options("pretrain", {"objective": "regression"})["shift_positives"] == 0


def test_the_random_arm_has_the_trained_arms_architecture():
    # the untrained retrieval row must be the model the arms train (here: with the full-resolution branch),
    # untrained, not the preset's default architecture
    from core.presets import TINY
    from core.tasks import build_task
    from services.bench.evaluations import random_pretrain_bundle

    config = plan_for("tiny", task_options={"mapper": {"encoder_full_res": 4}})
    options = config.stage_options("pretrain", {"objective": "contrastive"})
    random = random_pretrain_bundle(TINY, seed=0, device="cpu", task_options=options)
    trained = build_task("pretrain", TINY, **options).exported_modules()
    default = random_pretrain_bundle(TINY, seed=0, device="cpu")
    shapes = {name: {k: v.shape for k, v in m.state_dict().items()} for name, m in trained.items()}
    assert {name: {k: v.shape for k, v in m.state_dict().items()} for name, m in random.modules.items()} == shapes
    assert {name: {k: v.shape for k, v in m.state_dict().items()} for name, m in default.modules.items()} != shapes


# The recipe the small report's regeneration runs with (carry/bench-paper-small/continue.sh).
RECIPE = {"mapper": {"encoder_full_res": 16}, "pretrain": {"coeff_match": 1.0, "coeff_occ": 3.0},
          "pretrain_contrastive": {"shift_positives": 3},
          "flow_features": {"refine_radius": [3, 1, 3], "refine_aggregate": [1, 1, 1]}}


def test_every_training_stage_is_checked_with_the_options_it_will_get(tmp_path, monkeypatch):
    import core.tasks
    from services.bench.task_options import check_task_options

    built = []
    real = core.tasks.build_task
    monkeypatch.setattr(core.tasks, "build_task", lambda task, preset, **o: built.append((task, o)) or real(task, preset, **o))
    config = plan_for("tiny", quick=True, seeds=(0, 1), task_options=RECIPE)
    check_task_options(config, tmp_path / "work")
    expected = [("pretrain", config.stage_options("pretrain", {"objective": "contrastive"})),
                ("pretrain", config.stage_options("pretrain", {"objective": "regression"})),
                ("occupancy", config.stage_options("occupancy", {})),
                ("flow", config.stage_options("flow_features", {"inputs": "features"})),
                ("flow", config.stage_options("flow_volume", {"inputs": "volume"}))]
    for task, options in expected:
        assert (task, options) in built, (task, options)
    assert any(task == "detector" for task, _ in built) and any(task == "egomotion" for task, _ in built)
    # each distinct (task, options) once, however many seeds and label draws share it
    assert len(built) == len({(t, json.dumps(o, sort_keys=True)) for t, o in built})
    assert not (tmp_path / "work").exists()


@pytest.mark.parametrize("options, message", [
    ({"pretrain": {"coef_match": 1.0}}, r"stage seed0/pretrain_\w+ \(task pretrain\).*coef_match"),
    ({"occupancy": {"coeff_match": 1.0}}, r"stage seed0/occupancy_contrastive \(task occupancy\).*coeff_match"),
    ({"flow_features": {"refine_radius": [3, 1]}}, r"stage seed0/flow_\w+ \(task flow\).*refine_radius"),
    ({"detector": {"bogus": 2}}, r"stage seed0/detector_.*bogus"),
])
def test_a_field_a_task_refuses_stops_the_run_before_anything_is_written(tmp_path, options, message):
    from services.bench.paper import run_paper_bench

    config = plan_for("tiny", quick=True, seeds=(0,), task_options=options)   # the kinds are valid: accepted
    with pytest.raises(BenchConfigError, match=message):
        run_paper_bench(config, tmp_path / "r", log=lambda _: None)
    assert not (tmp_path / "r").exists()
