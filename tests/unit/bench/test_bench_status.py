"""services.bench.status on a hand-built work directory of the quick tiny plan: every stage of the plan listed
once, in a seed's order, finished / under way / to run by its marker and directory, a training stage under way
at the step of the checkpoint its loop resumes from with its rule's bound, the stage times from stage.json and
stage.partial.json, and the CLI's one-line error where there is no benchmark."""

import json
from pathlib import Path

import pytest

from services.bench.plan import plan_for, with_steps
from services.bench.replan import stage_digests
from services.bench.status import bench_status, format_status
from tests.bench_checkpoints import write_checkpoint


def _write(path: Path, value) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(value if isinstance(value, str) else json.dumps(value))


def _config():
    # a bound of its own per rule, so that a stage read under the wrong rule shows
    return with_steps(plan_for("tiny", seeds=(0, 1), quick=True), pretrain=11, detector=12, flow=13, egomotion=14,
                      occupancy=15)


def _checkpoint(root: Path, step: int) -> None:
    write_checkpoint(root, step)


@pytest.fixture
def out(tmp_path) -> Path:
    config = _config()
    work = tmp_path / "report" / "work"
    _write(work / "plan.json", config.to_dict())
    for split in ("train", "test", "val"):
        _write(work / "data" / split / "manifest.json", {})
        _write(work / "data" / split / "stage.json", {"stage": f"data/{split}", "seconds": 1.5})
    s0 = work / "seed0"
    _write(s0 / "pretrain_regression" / "stopping.json", {})
    _write(s0 / "pretrain_regression" / "stage.json", {"seconds": 100.0})
    going = s0 / "pretrain_contrastive"
    _write(going / "stage.partial.json", {"seconds": 40.0})
    for step in (1, 2):
        write_checkpoint(going / "checkpoints", step)
    write_checkpoint(going / "checkpoints", 3, torn="weights")   # cut short: a resume uses step 2
    _write(going / "checkpoints" / ".staging_9_x" / "state.json", {"step": 9, "config": {}})  # never resumed from
    import time
    _write(going / "metrics.jsonl", 'p": 1, "cut off"}\n'   # a tail's first line, cut
           + json.dumps({"step": 3, "total_steps": 11, "time": time.time() - 300, "start_step": 0}) + "\n"
           + json.dumps({"step": 4, "total_steps": 11, "time": time.time() - 120, "start_step": 0,
                         "steps_per_s": 0.05, "loss": 1.0}) + "\n")
    _write(s0 / "eval" / "retrieval" / "random" / "metrics.json", {})
    _write(s0 / "eval" / "retrieval" / "random" / "stage.json", {"seconds": 3.0})
    _write(work / "seed1" / "eval" / "flow" / "volume" / "stage.partial.json", {"seconds": 2.0})  # an evaluation stopped
    _checkpoint(work / "seed1" / "flow_volume" / "checkpoints", 5)
    _checkpoint(work / "seed1" / "occupancy_contrastive" / "checkpoints", 3)
    _checkpoint(work / "seed1" / "detector_regression_frozen_L2" / "checkpoints", 4)
    _checkpoint(work / "seed1" / "egomotion" / "ray_train" / "run" / "checkpoint_000000", 7)   # on Ray Train
    return tmp_path / "report"


def test_every_stage_of_the_plan_is_listed_once_with_its_state(out):
    config = _config()
    status = bench_status(out)
    rows = {r["name"]: r for r in status["stages"]}
    assert list(rows) == list(stage_digests(config, out / "work"))   # the plan's stages, in its order
    finished = {"data/train", "data/test", "data/val", "seed0/pretrain_regression", "seed0/eval/retrieval/random"}
    under_way = {"seed0/pretrain_contrastive", "seed1/eval/flow/volume", "seed1/flow_volume",
                 "seed1/occupancy_contrastive", "seed1/detector_regression_frozen_L2", "seed1/egomotion"}
    assert {n for n, r in rows.items() if r["state"] == "finished"} == finished
    assert {n for n, r in rows.items() if r["state"] == "under way"} == under_way
    assert status["counts"] == {"finished": 5, "under way": 6, "to run": len(rows) - 11}
    assert [(rows[n]["step"], rows[n]["max_steps"]) for n in ("seed1/flow_volume", "seed1/occupancy_contrastive",
            "seed1/detector_regression_frozen_L2", "seed1/egomotion")] == [(5, 13), (3, 15), (4, 12), (7, 14)]
    assert rows["seed0/pretrain_regression"]["seconds"] == 100.0
    going = rows["seed0/pretrain_contrastive"]
    assert (going["step"], going["max_steps"], going["seconds"]) == (2, 11, 40.0)
    assert (going["logged"]["step"], going["logged"]["total_steps"], going["logged"]["steps_per_s"]) == (4, 11, 0.05)
    assert 119 <= going["logged"]["age_s"] < 180 and rows["seed1/flow_volume"]["logged"] is None
    stopped_eval = rows["seed1/eval/flow/volume"]
    assert (stopped_eval["step"], stopped_eval["seconds"]) == (None, 2.0)


def test_the_summary_says_per_seed_what_is_under_way_and_what_runs_next(out):
    text = format_status(bench_status(out), "R")
    lines = text.splitlines()
    assert lines[0].startswith("bench R: preset tiny, seeds [0, 1]: 5 of ") and "6 under way" in lines[0]
    assert lines[1] == "  data: 3 of 3 finished"
    assert lines[2].startswith("  seed0: 2 of ") and "under way: pretrain_contrastive at step 2 (its rule stops by " in lines[2]
    assert "40 s in stopped attempts" in lines[2] and "next to run: flow_regression" in lines[2]   # flows run right after the pretrainings
    # the loop's newest progress line: 7 steps to go at 0.05 steps/s, written two minutes ago
    assert "; logged step 4 of 11, 0.05 steps/s (~2 min to go at that pace), 2 min ago;" in lines[2]
    assert "logged" not in lines[3]   # no progress line written: nothing said
    assert "under way: eval/flow/volume, 2 s in stopped attempts" in lines[3] and "next to run: pretrain_regression" in lines[3]
    assert "under way: flow_volume at step 5 (its rule stops by 13)" in lines[3]


def test_a_detector_under_an_epochs_rule_is_bounded_by_its_epochs_not_the_rules_cap(tmp_path):
    """The epochs rule stops at its epochs' steps within [min, max] (the training call logs them as its total),
    not at max_steps: '(its rule stops by 2000)' beside 'logged step 100 of 800' was the old line."""
    import time

    config = plan_for("tiny", seeds=(0,))
    assert config.rules.detector.kind == "epochs"
    work = tmp_path / "report" / "work"
    _write(work / "plan.json", config.to_dict())
    going = work / "seed0" / "detector_random_finetuned_L2"
    write_checkpoint(going / "checkpoints", 20)
    _write(going / "metrics.jsonl", json.dumps({"step": 25, "total_steps": 80, "time": time.time(), "start_step": 0,
                                                "steps_per_s": 1.0}) + "\n")
    row = next(r for r in bench_status(tmp_path / "report")["stages"] if r["name"] == "seed0/detector_random_finetuned_L2")
    assert (row["state"], row["step"], row["max_steps"]) == ("under way", 20, 80)
    assert config.rules.detector.max_steps != 80


def test_no_benchmark_is_one_line_exit_2(tmp_path, capsys):
    from services.cli.main import main

    assert main(["bench", "status", "--out", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"n3dmap bench: error: {tmp_path / 'nothing'}: no benchmark here (no work/plan.json); give the --out of `bench paper`"


def test_a_plan_of_an_older_n3dmap_is_one_line_exit_2(tmp_path, capsys):
    from services.cli.main import main

    _write(tmp_path / "work" / "plan.json", {"preset": "tiny", "seeds": [0]})   # no "rules"
    assert main(["bench", "status", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not a benchmark plan of this n3dmap" in err and "Traceback" not in err
