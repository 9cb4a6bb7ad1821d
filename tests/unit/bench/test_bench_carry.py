"""services.bench.carry: which files a carry holds (against a hand-written list for a hand-built work directory
with a finished stage, a stage under way, an evaluation and the temporaries), and a save → restore round trip
that regenerates the datasets and refuses a tampered carry, a carry that leaves its folder, a restore over an
existing benchmark, datasets that come out different, and a stage under way on Ray Train."""

import json
import shutil
from pathlib import Path

import pytest

from services.bench.carry import CARRY_MANIFEST, CarryError, carried_files, restore_carry, save_carry
from services.bench.paper import _data_stages
from services.bench.plan import plan_for
from services.bench.stages import StageRunner
from tests.bench_checkpoints import write_checkpoint


def _write(path: Path, text: str = "x") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def _checkpoint(root: Path, step: int, *, complete: bool = True) -> None:
    write_checkpoint(root, step, torn=None if complete else "state")


def _work_dir(work: Path) -> None:
    """A benchmark work directory with every kind of file the carry must keep or leave (real datasets)."""
    config = plan_for("tiny", seeds=(0,), quick=True)
    _data_stages(StageRunner(work, log=lambda line: None), config)
    _write(work / "plan.json", json.dumps(config.to_dict()))
    _write(work / "stages.jsonl", '{"stage": "data/train"}\n')
    s = work / "seed0"
    _write(s / "worker.log", "log")
    _write(s / "worker.pid", "999999999\n")   # left by a worker killed outright: a dead pid, not carried
    done = s / "pretrain_contrastive"            # finished: stopping.json written
    for name in ("metrics.jsonl", "stopping.json", "stage.json", "selected/bundle.json", "selected/weights.safetensors",
                 "bundle/bundle.json", "bundle/weights.safetensors", "stopping.partial.json"):
        _write(done / name)
    _checkpoint(done / "checkpoints", 100)
    _checkpoint(done / "checkpoints", 200)
    going = s / "detector_contrastive_frozen_L2"  # under way: no stopping.json
    for name in ("metrics.jsonl", "stopping.partial.json", "stage.partial.json", "selected/bundle.json",
                 "selected/weights.safetensors", "bundle/bundle.json", "labelled_data/manifest.json",
                 "labelled_data/shard-00000.tar"):
        _write(going / name)
    _checkpoint(going / "checkpoints", 100)
    _checkpoint(going / "checkpoints", 200)
    _checkpoint(going / "checkpoints", 300, complete=False)   # cut off while written
    # newer still, its state.json whole but its weights cut short: the loop would skip it for 200, so the carry
    # must too (it carried this one alone, and the restored stage then had nothing to resume from)
    write_checkpoint(going / "checkpoints", 350, torn="weights")
    staged = going / "checkpoints" / ".staging_400_x1y2"          # written whole, then killed before its rename
    _write(staged / "state.json", json.dumps({"step": 400, "config": {}, "metrics": {}}))
    _write(staged / "task.safetensors", "weights at 400")
    _write(going / "selected.tmp" / "bundle.json")             # temporaries of a selection cut off
    _write(s / "egomotion" / "labelled_data" / "manifest.json")  # a stage stopped before its first step
    _write(s / "eval" / "detection" / "contrastive_frozen_L2" / "metrics.json", "{}")
    _write(s / "eval" / "detection" / "contrastive_frozen_L2" / "stage.json", "{}")


EXPECTED = {  # the slow, obvious reference: written out by hand
    "plan.json", "stages.jsonl", "seed0/worker.log",
    "data/train/stage.json", "data/test/stage.json", "data/val/stage.json",
    "seed0/pretrain_contrastive/metrics.jsonl", "seed0/pretrain_contrastive/stopping.json",
    "seed0/pretrain_contrastive/stage.json", "seed0/pretrain_contrastive/selected/bundle.json",
    "seed0/pretrain_contrastive/selected/weights.safetensors", "seed0/pretrain_contrastive/stopping.partial.json",
    "seed0/detector_contrastive_frozen_L2/metrics.jsonl", "seed0/detector_contrastive_frozen_L2/stopping.partial.json",
    "seed0/detector_contrastive_frozen_L2/stage.partial.json",
    "seed0/detector_contrastive_frozen_L2/selected/bundle.json",
    "seed0/detector_contrastive_frozen_L2/selected/weights.safetensors",
    "seed0/detector_contrastive_frozen_L2/checkpoints/checkpoint_00000200/task.safetensors",
    "seed0/detector_contrastive_frozen_L2/checkpoints/checkpoint_00000200/optimizer.pt",
    "seed0/detector_contrastive_frozen_L2/checkpoints/checkpoint_00000200/state.json",
    "seed0/eval/detection/contrastive_frozen_L2/metrics.json", "seed0/eval/detection/contrastive_frozen_L2/stage.json",
}


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("bench") / "report" / "work"
    _work_dir(work)
    return work


def test_a_carry_holds_exactly_what_cannot_be_remade(work):
    assert set(carried_files(work)) == EXPECTED


def test_save_then_restore_rebuilds_the_work_directory_and_its_datasets(work, tmp_path):
    carry = tmp_path / "carry"
    _write(carry / "README.md", "what this carry is")    # notes beside an earlier carry survive a save
    _write(carry / "continue.sh", "bench paper ...")
    saved = save_carry(work.parent, carry, log=lambda line: None)
    assert set(saved["files"]) == EXPECTED and set(saved["data"]) == {"train", "test", "val"}
    assert saved["progress"] == {"finished": ["seed0/eval/detection/contrastive_frozen_L2", "seed0/pretrain_contrastive"],
                                 "under_way": {"seed0/detector_contrastive_frozen_L2": 200}}
    assert (carry / "README.md").read_text() == "what this carry is"
    assert (carry / "continue.sh").read_text() == "bench paper ..."
    assert sorted(p.name for p in (carry / "work" / "data").rglob("*") if p.is_file()) == ["stage.json"] * 3
    restored = tmp_path / "restored"
    restore_carry(carry, restored, log=lambda line: None)
    for rel in EXPECTED - {"stages.jsonl"}:   # the data stages' times too: the carried ones, not the regeneration's
        assert (restored / "work" / rel).read_bytes() == (work / rel).read_bytes(), rel
    # the journal: the carried lines, then the regenerated data stages'
    journal = (restored / "work" / "stages.jsonl").read_text()
    assert journal.startswith((work / "stages.jsonl").read_text())
    assert [json.loads(l)["stage"] for l in journal.splitlines()[1:]] == ["data/train", "data/test", "data/val"]
    for split in ("train", "test", "val"):
        assert (json.loads((restored / "work" / "data" / split / "manifest.json").read_text())["shards"]
                == json.loads((work / "data" / split / "manifest.json").read_text())["shards"])
    # nothing the carry leaves out came back
    assert not (restored / "work" / "seed0" / "pretrain_contrastive" / "checkpoints").exists()
    assert not (restored / "work" / "seed0" / "detector_contrastive_frozen_L2" / "labelled_data").exists()
    # saving again replaces the carry: a file gone from the work dir is gone from the carry
    (work / "seed0" / "worker.log").rename(work / "seed0" / "worker.log.moved")
    try:
        again = save_carry(work.parent, carry, log=lambda line: None)
    finally:
        (work / "seed0" / "worker.log.moved").rename(work / "seed0" / "worker.log")
    assert "seed0/worker.log" not in again["files"] and not (carry / "work" / "seed0" / "worker.log").exists()


@pytest.fixture
def carry(work, tmp_path) -> Path:
    carry = tmp_path / "carry"
    save_carry(work.parent, carry, log=lambda line: None)
    return carry


def test_a_changed_or_missing_carried_file_is_refused_by_name(carry, tmp_path):
    target = carry / "work" / "seed0" / "pretrain_contrastive" / "stopping.json"
    target.write_text("changed")
    with pytest.raises(CarryError, match="work/seed0/pretrain_contrastive/stopping.json does not match its sha256"):
        restore_carry(carry, tmp_path / "a", log=lambda line: None)
    target.unlink()
    with pytest.raises(CarryError, match="work/seed0/pretrain_contrastive/stopping.json is missing"):
        restore_carry(carry, tmp_path / "b", log=lambda line: None)
    assert not (tmp_path / "a" / "work").exists() and not (tmp_path / "b" / "work").exists()


def test_a_path_that_leaves_the_carry_is_refused(carry, tmp_path):
    manifest = json.loads((carry / CARRY_MANIFEST).read_text())
    manifest["files"]["../../outside"] = {"bytes": 1, "sha256": "0" * 64}
    (carry / CARRY_MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CarryError, match="'../../outside' leaves the work directory"):
        restore_carry(carry, tmp_path / "a", log=lambda line: None)


def test_a_manifest_without_the_plan_is_refused(carry, tmp_path):
    manifest = json.loads((carry / CARRY_MANIFEST).read_text())
    del manifest["files"]["plan.json"]
    (carry / CARRY_MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CarryError, match="files lacks plan.json"):
        restore_carry(carry, tmp_path / "a", log=lambda line: None)


def test_not_a_carry_and_an_existing_benchmark_are_refused(carry, work, tmp_path):
    with pytest.raises(CarryError, match="no carry.json"):
        restore_carry(tmp_path / "nothing", tmp_path / "a", log=lambda line: None)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / CARRY_MANIFEST).write_text('{"format": "something else"}')
    with pytest.raises(CarryError, match="not a bench carry manifest"):
        restore_carry(tmp_path / "bad", tmp_path / "a", log=lambda line: None)
    with pytest.raises(CarryError, match="already holds a benchmark"):
        restore_carry(carry, work.parent, log=lambda line: None)
    with pytest.raises(CarryError, match="no benchmark here"):
        save_carry(tmp_path / "nothing", tmp_path / "c", log=lambda line: None)


def test_datasets_that_regenerate_differently_are_refused(carry, tmp_path):
    manifest = json.loads((carry / CARRY_MANIFEST).read_text())
    manifest["data"]["test"]["shards"][0]["sha256"] = "f" * 64
    (carry / CARRY_MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CarryError, match=r"regenerated dataset data/test differs .* trained on other bytes"):
        restore_carry(carry, tmp_path / "a", log=lambda line: None)
    # nothing is left that a `bench paper` rerun could take for a benchmark with its data made
    assert not (tmp_path / "a" / "work").exists() and not (tmp_path / "a" / "work.restoring").exists()


def test_a_stage_under_way_on_ray_train_is_refused(work, tmp_path):
    copy = tmp_path / "report" / "work"
    shutil.copytree(work, copy)
    going = copy / "seed0" / "detector_contrastive_frozen_L2"
    shutil.move(going / "checkpoints", going / "ray_train")
    with pytest.raises(CarryError, match="under way on Ray Train"):
        save_carry(copy.parent, tmp_path / "carry", log=lambda line: None)
    # finished, its Ray storage is left behind like any finished stage's checkpoints
    _write(going / "stopping.json")
    save_carry(copy.parent, tmp_path / "carry", log=lambda line: None)
    assert not any("ray_train" in rel for rel in json.loads((tmp_path / "carry" / CARRY_MANIFEST).read_text())["files"])


def test_a_run_still_being_written_is_refused(work, tmp_path):
    import subprocess
    import sys

    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (work / "seed0" / "worker.pid").write_text(f"{worker.pid}\n")
        with pytest.raises(CarryError, match=rf"still being written by pid {worker.pid} \(seed0/worker.pid\): stop"):
            save_carry(work.parent, tmp_path / "carry", log=lambda line: None)
        assert not (tmp_path / "carry").exists()
    finally:
        worker.kill()
        worker.wait()
        (work / "seed0" / "worker.pid").write_text("999999999\n")


def test_a_target_inside_or_above_the_benchmark_or_a_foreign_folder_is_refused(work, tmp_path, monkeypatch):
    # a carry replaces its folder whole: here it would have deleted the run's datasets and stages
    report = work.parent
    before = sorted(p.relative_to(report).as_posix() for p in report.rglob("*"))
    for target in (report, work, work / "seed0", report.parent):
        with pytest.raises(CarryError, match="must lie outside the benchmark's --out"):
            save_carry(report, target, log=lambda line: None)
    monkeypatch.chdir(work)   # `--to .`: resolved first (it has no name to build the temporary folder from)
    with pytest.raises(CarryError, match=r"--to \.: it must lie outside"):
        save_carry(report, ".", log=lambda line: None)
    assert sorted(p.relative_to(report).as_posix() for p in report.rglob("*")) == before
    foreign = tmp_path / "project"
    _write(foreign / "src" / "mine.txt", "keep me")
    _write(foreign / "work" / "theirs.txt", "keep me too")
    with pytest.raises(CarryError, match=r"holds folder\(s\) \['src', 'work'\] that a save would delete"):
        save_carry(report, foreign, log=lambda line: None)
    assert (foreign / "src" / "mine.txt").read_text() == "keep me"
    assert (foreign / "work" / "theirs.txt").read_text() == "keep me too"
    _write(tmp_path / "a_file")
    with pytest.raises(CarryError, match="a file is there"):
        save_carry(report, tmp_path / "a_file", log=lambda line: None)
    (tmp_path / "empty").mkdir()
    save_carry(report, tmp_path / "empty", log=lambda line: None)   # new or empty: fine, and so is a second save
    save_carry(report, tmp_path / "empty", log=lambda line: None)
    assert (tmp_path / "empty" / CARRY_MANIFEST).is_file()


def test_a_carried_plan_that_is_not_a_plan_is_refused_before_anything_is_written(carry, tmp_path):
    from core.data.shards import sha256_file

    plan = carry / "work" / "plan.json"
    plan.write_text("{}")
    manifest = json.loads((carry / CARRY_MANIFEST).read_text())
    manifest["files"]["plan.json"] = {"bytes": plan.stat().st_size, "sha256": sha256_file(plan)}
    (carry / CARRY_MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CarryError, match="work/plan.json is not a benchmark plan"):
        restore_carry(carry, tmp_path / "a", log=lambda line: None)
    assert not (tmp_path / "a").exists()
